"""speed_std_ahead / speed_std_behind: hand-computed windows on the real ring and straight maps
(constructed snapshots, pure math), and finite values from real SUMO episodes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mixed_traffic.config import EnvConfig
from mixed_traffic.env.ahead_behind import AheadBehind, LaneReach, pooled_std_mean
from mixed_traffic.experiments.runner import run_episode
from mixed_traffic.world.registry import load_scenario
from mixed_traffic.world.snapshot import TrafficSnapshot


def _snap(hd, cars: list[tuple[str, str, float, float]]) -> TrafficSnapshot:
    """Vehicles (id, SUMO lane id, lane position [m], speed [m/s]); ids ``av_*`` are AVs."""
    n = len(cars)
    lane = np.array([hd.lane_row[c[1]] for c in cars], np.int32)
    z = np.zeros(n)
    return TrafficSnapshot(
        time=1.0, ids=[c[0] for c in cars], is_av=np.array([c[0].startswith("av_") for c in cars]),
        x=z, y=z, z=z, heading=z, speed=np.array([c[3] for c in cars]), accel=z, lane=lane,
        lane_index=hd.lane_index[lane], lane_pos=np.array([c[2] for c in cars]), lateral=z,
        length=np.full(n, 5.0), width=np.full(n, 1.8), edge=hd.lane_edge[lane],
        route_index=np.zeros(n, np.int32), route_length=np.ones(n, np.int32),
    )  # fmt: skip


def test_pooled_std_mean_by_hand() -> None:
    a, b = np.array([1.0, 3.0]), np.array([2.0, 2.0, 2.0, 6.0])
    n = np.array([2.0, 4.0, 0.0])
    s1 = np.array([a.sum(), b.sum(), 0.0])
    s2 = np.array([(a * a).sum(), (b * b).sum(), 0.0])
    assert pooled_std_mean(n, s1, s2) == pytest.approx((2 * a.std() + 4 * b.std()) / 6)
    assert pooled_std_mean(np.zeros(2), np.zeros(2), np.zeros(2)) is None


def test_ring_windows_are_the_two_halves_of_the_loop() -> None:
    """260 m ring (north_0 and south_0, 129.96 m each, 0.1 m junction lanes): the window is half
    the loop, 130.06 m, so every other vehicle is either ahead or behind, never both."""
    hd = load_scenario("ring").hdmap
    rec = AheadBehind(hd, window=200.0)
    loop = 2 * 129.96 + 2 * 0.1
    assert rec.window[hd.lane_row["north_0"]] == pytest.approx(loop / 2, abs=0.02)
    # av_0 at 10 m on north_0; distances ahead along the ring in the comments
    speeds = [(4.0, 8.0, 10.0, 10.0, 10.0), (8.0, 4.0, 10.0, 10.0, 12.0)]
    for h1, h2, h3, h4, h5 in speeds:
        rec.update(
            _snap(hd, [
                ("av_0", "north_0", 10.0, 7.0),
                ("h1", "north_0", 40.0, h1),  # 30 m ahead
                ("h2", "south_0", 5.0, h2),  # 125.06 m ahead
                ("h3", "south_0", 20.0, h3),  # 140.06 m ahead = 120.06 m behind
                ("h4", "south_0", 100.0, h4),  # 40.06 m behind
                ("h5", "north_0", 5.0, h5),  # 5 m behind
            ]),
            np.ones(6, bool),
        )  # fmt: skip
    out = rec.summary()
    ahead = [s[k] for s in speeds for k in (0, 1)]
    behind = [s[k] for s in speeds for k in (2, 3, 4)]
    assert out["speed_std_ahead"] == pytest.approx(np.std(ahead))
    assert out["speed_std_behind"] == pytest.approx(np.std(behind))


def test_straight_window_follows_the_lane_across_edges_and_stops_at_its_reach() -> None:
    """straight: meas_0 (1000 m) -> 0.1 m junction lane -> exit_0; window 200 m."""
    hd = load_scenario("straight").hdmap
    rec = AheadBehind(hd, window=200.0)
    for k, dv in enumerate((0.0, 4.0)):
        cars = [
            ("av_0", "meas_0", 900.0, 20.0),
            ("h1", "exit_0", 50.0, 20.0 + dv),  # 150.1 m ahead: in
            ("h2", "exit_0", 150.0, 99.0),  # 250.1 m ahead: out
            ("h3", "meas_1", 950.0, 99.0),  # the next lane: out
            ("av_1", "meas_0", 750.0, 10.0 - dv),  # an AV 150 m behind: in (and sampled itself)
            ("h4", "meas_0", 500.0, 99.0),  # 400 m behind av_0, 250 m behind av_1: out
        ]
        counted = np.array([True, False, False, False, k == 0, False])
        rec.update(_snap(hd, cars), counted)
    out = rec.summary()
    # av_0 sees h1 ahead (20, 24) and av_1 behind (10, 6); av_1 (1 step) sees av_0 ahead (20)
    # and nothing behind: the mean over AVs weights av_0's 2 samples against av_1's 1
    assert out["speed_std_ahead"] == pytest.approx((2 * 2.0 + 1 * 0.0) / 3)
    assert out["speed_std_behind"] == pytest.approx(2.0)


def test_reach_of_a_lane_without_successors_is_the_lane_alone() -> None:
    hd = load_scenario("straight").hdmap
    reach = LaneReach(hd, 200.0, ahead=True)
    row = hd.lane_row["exit_0"]
    assert reach.lane[row, 0] == row and np.all(reach.lane[row, 1:] == -1)
    with pytest.raises(ValueError, match="window=0"):
        AheadBehind(hd, window=0.0)


def test_ahead_behind_on_real_sumo_runs() -> None:
    """Finite spreads around SUMO-driven would-be AVs on the ring (the idm reference), and
    around AVs the env drives (ACC-LC) on straight; none without AVs."""
    ring = run_episode(EnvConfig(scenario="ring", penetration=0.05, episode_length=60.0), "idm",
                       warmup=20.0)["metrics"]  # fmt: skip
    for key in ("speed_std_ahead", "speed_std_behind"):
        assert math.isfinite(ring[key]) and 0.0 < ring[key] < 10.0
    cfg = EnvConfig(scenario="straight", density=120.0, penetration=0.5, episode_length=30.0)
    straight = run_episode(cfg, "acc-lc", warmup=10.0)["metrics"]
    for key in ("speed_std_ahead", "speed_std_behind"):
        assert math.isfinite(straight[key]) and 0.0 <= straight[key] < 10.0
    human = run_episode(EnvConfig(scenario="ring", penetration=0.0, episode_length=30.0), "idm",
                        warmup=10.0)["metrics"]  # fmt: skip
    assert human["speed_std_ahead"] is None and human["speed_std_behind"] is None
