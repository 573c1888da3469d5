"""Headless bird's-eye rendering of a snapshot (``render_mode="rgb_array"``) with Pillow.

Lanes are drawn from the HD map, AVs red, conventional vehicles grey-blue, traffic lights as
coloured bars at their stop lines. The view follows a vehicle (the first live agent by default).
``FrameCollector`` + ``record_gif`` turn an episode's frames into an animated GIF.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.snapshot import TrafficSnapshot

AV_COLOUR = (220, 40, 40)
HV_COLOUR = (150, 170, 200)
LANE_COLOUR = (70, 70, 70)
MARK_COLOUR = (200, 200, 200)
BACKGROUND = (30, 90, 40)
LIGHT_COLOURS = {"r": (230, 0, 0), "y": (240, 200, 0), "g": (0, 200, 0), "G": (0, 230, 0)}


@dataclass(frozen=True)
class View:
    width_m: float = 160.0
    """Width of the window [m]."""
    height_m: float = 80.0
    """Height of the window [m]."""
    px_per_m: float = 6.0
    """Resolution [px/m]."""


class Renderer:
    """Draws snapshots of one network; lane polygons are prepared once."""

    def __init__(self, hdmap: HDMap, view: View | None = None) -> None:
        self.hdmap = hdmap
        self.view = view or View()
        self._lanes = [
            (hdmap.wp_xyz[o : o + c, :2], float(hdmap.lane_width[i]), _left_edge(hdmap, i))
            for i, (o, c) in enumerate(zip(hdmap.wp_offset, hdmap.wp_count))
            if c > 1
        ]
        self._stop_lines = {
            key: (hdmap.wp_xyz[hdmap.wp_offset[key[0]] + hdmap.wp_count[key[0]] - 1, :2], tls)
            for key, tls in hdmap.tls_links.items()
        }

    def draw(
        self,
        snap: TrafficSnapshot,
        centre: np.ndarray | int | None = None,
        tls_state: dict[str, str] | None = None,
    ) -> np.ndarray:
        """(H, W, 3) uint8 image of the window around ``centre`` (x, y) [m] or the vehicle in
        that snapshot row (int; default: the vehicles' mean)."""
        v = self.view
        w, h = int(v.width_m * v.px_per_m), int(v.height_m * v.px_per_m)
        if isinstance(centre, int | np.integer):
            centre = np.array([snap.x[centre], snap.y[centre]])
        if centre is None:
            centre = (
                np.array([snap.x.mean(), snap.y.mean()])
                if snap.n
                else self.hdmap.wp_xyz[:, :2].mean(0)
            )
        img = Image.new("RGB", (w, h), BACKGROUND)
        draw = ImageDraw.Draw(img)

        def to_px(xy: np.ndarray) -> list[tuple[float, float]]:
            p = (np.asarray(xy) - centre) * v.px_per_m
            return [(w / 2 + a, h / 2 - b) for a, b in p.reshape(-1, 2)]

        reach = max(v.width_m, v.height_m)
        for pts, width, _ in self._lanes:
            near = np.abs(pts - centre).max(axis=1) < reach
            if near.any():
                draw.line(to_px(pts[near]), fill=LANE_COLOUR, width=max(1, int(width * v.px_per_m)))
        for _, _, edge in self._lanes:  # lane markings on top of all asphalt
            near = np.abs(edge - centre).max(axis=1) < reach
            if near.sum() > 1:
                draw.line(to_px(edge[near]), fill=MARK_COLOUR, width=1)
        for (_, _), (xy, (tls, idx)) in self._stop_lines.items():
            state = (tls_state or {}).get(tls, "")
            if 0 <= idx < len(state):
                (px, py) = to_px(xy)[0]
                r = 0.8 * v.px_per_m
                draw.ellipse(
                    (px - r, py - r, px + r, py + r),
                    fill=LIGHT_COLOURS.get(state[idx], MARK_COLOUR),
                )
        for i in range(snap.n):
            draw.polygon(to_px(_corners(snap, i)), fill=AV_COLOUR if snap.is_av[i] else HV_COLOUR)
        return np.asarray(img)


def _left_edge(hdmap: HDMap, lane: int) -> np.ndarray:
    """(W, 2) points of a lane's left boundary."""
    sl = slice(hdmap.wp_offset[lane], hdmap.wp_offset[lane] + hdmap.wp_count[lane])
    hdg = hdmap.wp_heading[sl]
    normal = np.stack([-np.sin(hdg), np.cos(hdg)], axis=1)
    return hdmap.wp_xyz[sl, :2] + normal * hdmap.lane_width[lane] / 2


def _corners(snap: TrafficSnapshot, i: int) -> np.ndarray:
    """(4, 2) corners of vehicle i; SUMO positions are the front bumper centre."""
    c, s = np.cos(snap.heading[i]), np.sin(snap.heading[i])
    fwd, left = np.array([c, s]), np.array([-s, c])
    front = np.array([snap.x[i], snap.y[i]])
    back = front - fwd * snap.length[i]
    half = left * snap.width[i] / 2
    return np.array([front + half, front - half, back - half, back + half])


class FrameCollector:
    """Keeps every ``every``-th frame of an episode, at most ``max_frames`` of them, each scaled
    down so its longer side is at most ``max_side`` pixels (bounded GIF size).

    Usage with an env made with ``render_mode="rgb_array"``::

        frames = FrameCollector(every=2)
        frames.add(env.render())          # after reset and after each step
        record_gif(frames.frames, "out.gif", fps=env.metadata["render_fps"] / frames.every)
    """

    def __init__(self, every: int = 1, max_frames: int = 600, max_side: int = 640) -> None:
        if every < 1 or max_frames < 1 or max_side < 16:
            raise ValueError(
                f"FrameCollector: every={every} and max_frames={max_frames} must be >= 1, "
                f"max_side={max_side} >= 16"
            )
        self.every, self.max_frames, self.max_side = every, max_frames, max_side
        self.frames: list[np.ndarray] = []
        self._seen = 0

    def add(self, frame: np.ndarray | None) -> None:
        """Offer one frame (``None``, e.g. from a non-rendering env, is ignored)."""
        if frame is None:
            return
        keep = self._seen % self.every == 0 and len(self.frames) < self.max_frames
        self._seen += 1
        if not keep:
            return
        img = Image.fromarray(np.asarray(frame, dtype=np.uint8))
        if max(img.size) > self.max_side:
            scale = self.max_side / max(img.size)
            img = img.resize((max(1, round(img.width * scale)), max(1, round(img.height * scale))))
        self.frames.append(np.asarray(img))


def record_gif(frames: list[np.ndarray], path: str | Path, fps: float = 10.0) -> Path:
    """Write (H, W, 3) uint8 frames as a looping animated GIF at ``fps`` (Pillow); the path.

    Written to a temporary file and renamed, so a failed write leaves nothing half-written.
    """
    if not frames:
        raise ValueError(
            "record_gif: no frames to write (was the env made with render_mode='rgb_array'?)"
        )
    if fps <= 0:
        raise ValueError(f"record_gif: fps={fps} must be > 0")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images = [Image.fromarray(np.asarray(f, dtype=np.uint8)) for f in frames]
    tmp = path.with_name(path.name + ".part")
    images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:],
                   duration=max(20, round(1000 / fps)), loop=0, optimize=False)  # fmt: skip
    os.replace(tmp, path)
    return path
