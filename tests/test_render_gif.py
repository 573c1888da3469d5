"""GIF recording of an rgb_array episode (real SUMO)."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from mixed_traffic.env import parallel_env
from mixed_traffic.env.render import FrameCollector, record_gif


def test_short_recording_writes_a_valid_animated_gif(tmp_path) -> None:
    e = parallel_env(render_mode="rgb_array", density=60.0, penetration=0.3, episode_length=5.0)
    frames = FrameCollector(every=2, max_side=200)
    try:
        e.reset(seed=0)
        frames.add(e.render())
        for _ in range(8):
            act = {a: {"decision": 1, "params": np.zeros((3, 2), np.float32)} for a in e.agents}
            e.step(act)
            frames.add(e.render())
    finally:
        e.close()
    assert len(frames.frames) == 5  # frames 0, 2, 4, 6, 8 of 9
    assert all(max(f.shape[:2]) <= 200 for f in frames.frames)
    out = record_gif(frames.frames, tmp_path / "sub" / "out.gif", fps=5)
    with Image.open(out) as gif:
        assert gif.format == "GIF" and gif.n_frames == 5 and gif.is_animated
        assert max(gif.size) <= 200
        gif.seek(0)
        colours = np.unique(np.asarray(gif.convert("RGB")).reshape(-1, 3), axis=0)
        assert len(colours) > 2  # road, vehicles, background: a real picture
    assert not list(tmp_path.rglob("*.part"))


def test_collector_bounds_and_errors(tmp_path) -> None:
    c = FrameCollector(every=1, max_frames=3)
    for _ in range(5):
        c.add(np.zeros((10, 10, 3), np.uint8))
    c.add(None)
    assert len(c.frames) == 3
    with pytest.raises(ValueError, match="no frames"):
        record_gif([], tmp_path / "x.gif")
    with pytest.raises(ValueError, match="every"):
        FrameCollector(every=0)
