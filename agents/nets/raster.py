"""Bird's-eye-view rasters drawn from an observation batch, and the encoders that read them:
NoVEC (paper §V-A: rasterised features and convolutions, after Djuric et al. 2018), DRL-MF
(image and point-cloud features, no map or pose; Fu et al. 2022) and TransFuser (camera and
LiDAR branches fused by a transformer; Prakash et al. 2021).

SUMO renders no camera images, so the nearest honest equivalent is drawn here from the same
noisy observation every encoder gets (``agents.nets.lca``): an ego-centred grid, rows along the
lane (``ROWS`` cells over ±``lidar_range``, ahead = higher rows), columns across it
(``COLS_PER_LANE`` cells per lane, left lane first, lanes ``LANE_WIDTH`` wide). History frames
are stacked as channels, as in Djuric et al. Channels per frame (``CHANNELS``):

0. vehicles: 1 inside each detected vehicle's box (its length and width);
1. their speed relative to the ego / 40 m/s inside the same boxes;
2. map: speed limit / 40 m/s over each existing lane's columns;
3. map: the lane's orientation 10 waypoints ahead relative to the ego's heading / pi;
4. lights: 1 red, 0.5 yellow, -1 green across the lane at the stop line;
5. ego: its speed / 40 m/s inside its own box, at its lateral offset.

``with_map=False`` (DRL-MF) leaves channels 2-3 empty and draws the ego and the vehicles
relative to the ego instead of the lane centre (no pose).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

ROWS = 32
"""Longitudinal cells over [-lidar_range, +lidar_range] (5.6 m each at 90 m)."""
COLS_PER_LANE = 3
"""Lateral cells per lane (about 1.07 m each)."""
LANE_WIDTH = 3.2
"""Assumed lane width for drawing [m] (the observation carries lane indices, not widths)."""
CHANNELS = 6
"""Raster channels per history frame (module docstring)."""
_LAT = 2.0
"""Lateral offsets in the observation are / 2 m."""
_LEN, _WID = 10.0, 5.0
"""Lengths and widths in the observation are / 10 m and / 5 m."""


def _axes(lidar_range: float, device: torch.device) -> tuple[Tensor, Tensor]:
    """Cell centres: longitudinal (ROWS,) [m], lateral (3·COLS_PER_LANE,) [m, + left]."""
    step = 2 * lidar_range / ROWS
    ys = -lidar_range + step * (torch.arange(ROWS, device=device) + 0.5)
    w = LANE_WIDTH / COLS_PER_LANE
    xs = 1.5 * LANE_WIDTH - w * (torch.arange(3 * COLS_PER_LANE, device=device) + 0.5)
    return ys, xs


def _boxes(ys: Tensor, xs: Tensor, cy: Tensor, cx: Tensor, half_l: Tensor, half_w: Tensor,
           cell: tuple[float, float]) -> Tensor:  # fmt: skip
    """Occupancy (..., ROWS, COLS) of boxes centred (cy, cx) with half extents; a box covers
    every cell its extent (grown by half a cell, so small boxes still mark one) overlaps."""
    dy = (ys - cy[..., None]).abs() <= half_l[..., None] + cell[0] / 2
    dx = (xs - cx[..., None]).abs() <= half_w[..., None] + cell[1] / 2
    return (dy[..., :, None] & dx[..., None, :]).float()


def rasterize(obs: dict[str, Tensor], lidar_range: float, camera_range: float,
              with_map: bool = True) -> Tensor:  # fmt: skip
    """obs batch (B, ...) of ``agents.nets.lca`` → raster (B, z·CHANNELS, ROWS, 3·COLS)."""
    ego, veh, lanes, lights = obs["ego"], obs["vehicles"], obs["lanes"], obs["lights"]
    b, z = ego.shape[:2]
    ys, xs = _axes(lidar_range, ego.device)
    cell = (2 * lidar_range / ROWS, LANE_WIDTH / COLS_PER_LANE)
    centre = LANE_WIDTH * torch.tensor([1.0, 0.0, -1.0], device=ego.device)  # left, cur, right
    ego_lat = ego[..., 4] * _LAT  # (B, z)
    v = veh.view(b, 3, z, 2, 6).permute(0, 2, 1, 3, 4)  # (B, z, lane, front/rear, 6)
    present = v[..., 4] > 0
    cx = centre[None, None, :, None] + v[..., 5] * _LAT
    if not with_map:  # relative to the ego, which sits at 0
        cx = cx - ego_lat[..., None, None]
    occ = _boxes(ys, xs, v[..., 0] * lidar_range, cx, v[..., 3] * _LEN / 2, v[..., 4] * _WID / 2,
                 cell) * present[..., None, None]  # fmt: skip
    occ = occ.flatten(2, 3)  # (B, z, 6, R, C)
    speed = (occ * v.flatten(2, 3)[..., 1, None, None]).sum(2)
    frames = [occ.amax(2), speed]
    lane_cols = torch.arange(3, device=ego.device).repeat_interleave(COLS_PER_LANE)
    wp = lanes.view(b, 3, z, -1, 4).permute(0, 2, 1, 3, 4)  # (B, z, lane, m, 4)
    if with_map:
        exists = obs["node_mask"][:, None, :, 0].expand(b, z, 3) > 0.5
        limit = (wp[..., 0, 3] * exists)[..., lane_cols]  # (B, z, C)
        turn = (wp[..., -1, 2] * exists)[..., lane_cols]
        frames += [
            limit[:, :, None].expand(b, z, ROWS, -1),
            turn[:, :, None].expand(b, z, ROWS, -1),
        ]
    else:
        frames += [torch.zeros_like(speed)] * 2
    lt = lights.permute(0, 2, 1, 3)  # (B, z, lane, 4)
    code = lt[..., 0] + 0.5 * lt[..., 1] - lt[..., 2]
    on = lt[..., :3].sum(-1) > 0.5
    row = ((lt[..., 3] * camera_range + lidar_range) / cell[0]).long().clamp(0, ROWS - 1)
    line = torch.nn.functional.one_hot(row, ROWS).float() * (code * on)[..., None]  # (B,z,3,R)
    frames.append(line[:, :, lane_cols].transpose(2, 3))  # (B, z, R, C)
    ex = ego_lat if with_map else torch.zeros_like(ego_lat)
    box = _boxes(ys, xs, torch.zeros_like(ex), ex, ego[..., 2] * _LEN / 2, ego[..., 3] * _WID / 2,
                 cell)  # fmt: skip
    frames.append(box * ego[..., 0, None, None])
    return torch.stack(frames, dim=2).flatten(1, 2)  # (B, z·CHANNELS, R, C)


class RasterCNN(nn.Module):
    """Three 3×3 convolutions (the last two strided) over a raster: (B, C, ROWS, 3·COLS) →
    feature map (B, D, ROWS/4, ⌈3·COLS/4⌉)."""

    def __init__(self, in_ch: int, d: int) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(in_ch, d, 3, padding=1), nn.ReLU(),
            nn.Conv2d(d, d, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(d, d, 3, stride=2, padding=1), nn.ReLU(),
        )  # fmt: skip

    def forward(self, x: Tensor) -> Tensor:
        return self.net(x)

    @staticmethod
    def cells() -> int:
        """Cells of the output feature map."""
        return (ROWS // 4) * -(-3 * COLS_PER_LANE // 4)


class BevEncoder(nn.Module):
    """NoVEC: raster (with map and pose) → CNN → linear → E_s (B, D)."""

    def __init__(self, z: int, d: int, lidar_range: float, camera_range: float) -> None:
        super().__init__()
        self.ranges = (lidar_range, camera_range)
        self.cnn = RasterCNN(z * CHANNELS, d)
        self.out = nn.Sequential(nn.Linear(d * RasterCNN.cells(), d), nn.ReLU())

    def forward(self, obs: dict[str, Tensor]) -> Tensor:
        return self.out(self.cnn(rasterize(obs, *self.ranges)).flatten(1))
