"""Flow metrics: hand-computed pure functions and recorder cases, and a real SUMO run on straight."""

from __future__ import annotations

import numpy as np
import pytest

from mixed_traffic.config import EnvConfig
from mixed_traffic.env.flow_metrics import (
    FlowRecorder,
    delay_index,
    density_per_km,
    entry_time,
    exit_time,
)
from mixed_traffic.world.registry import load_scenario
from mixed_traffic.world.snapshot import TrafficSnapshot

from .conftest import start_sim


def test_entry_and_exit_interpolation_by_hand() -> None:
    # 3 m past the start at 10 m/s, observed at t = 5.0 s: crossed at 4.7 s
    assert entry_time(np.array([5.0]), np.array([3.0]), np.array([10.0]), np.array([4.9]))[
        0
    ] == pytest.approx(4.9)
    assert entry_time(np.array([5.0]), np.array([0.5]), np.array([10.0]), np.array([4.9]))[
        0
    ] == pytest.approx(4.95)
    # 998 m of a 1000 m segment at 20 m/s at t = 50 s: end reached at 50.1 s, capped by the next sample
    assert exit_time(
        np.array([50.0]), np.array([998.0]), np.array([20.0]), 1000.0, np.array([50.1])
    )[0] == pytest.approx(50.1)
    assert exit_time(
        np.array([50.0]), np.array([999.0]), np.array([20.0]), 1000.0, np.array([50.1])
    )[0] == pytest.approx(50.05)
    # standing vehicle: no extrapolation beyond the observations
    assert exit_time(
        np.array([50.0]), np.array([999.0]), np.array([0.0]), 1000.0, np.array([50.1])
    )[0] == pytest.approx(50.1)


def test_density_and_delay_index_by_hand() -> None:
    assert density_per_km(30, 500.0) == pytest.approx(60.0)
    di = delay_index(np.array([72.0, 36.0, 1.0]), np.array([36.0, 36.0, 0.0]))
    np.testing.assert_allclose(di[:2], [2.0, 1.0])
    assert np.isnan(di[2])


def _snapshot(
    hd, t: float, ids: list[str], s_road: list[float], v: float, edges: list[str]
) -> TrafficSnapshot:
    """Vehicles on the rightmost lane at road positions ``s_road`` [m] along ``edges``."""
    n = len(ids)
    starts = np.cumsum([0.0] + [float(hd.edge_length[hd.edge_of(e)]) for e in edges])
    edge = np.empty(n, np.int32)
    lane = np.empty(n, np.int32)
    pos = np.empty(n)
    for i, s in enumerate(s_road):
        k = int(np.searchsorted(starts, s, side="right") - 1)
        e = hd.edge_of(edges[k])
        edge[i], lane[i], pos[i] = e, hd.edge_lanes[e, 0], s - starts[k]
    z = np.zeros(n)
    return TrafficSnapshot(
        time=t, ids=ids, is_av=np.zeros(n, bool), x=z, y=z, z=z, heading=z, speed=np.full(n, v),
        accel=z, lane=lane, lane_index=np.zeros(n, np.int16), lane_pos=pos, lateral=z,
        length=np.full(n, 5.0), width=np.full(n, 1.8), edge=edge,
        route_index=np.zeros(n, np.int32), route_length=np.full(n, 3, np.int32),
    )  # fmt: skip


def test_recorder_constant_speed_vehicle_by_hand() -> None:
    """One car at 10 m/s from 395 m into the 400 m warm-up edge through the 1 km segment.

    It reaches the segment at 0.5 s and its end at 100.5 s: travel time 100 s; free-flow time at
    the 27.78 m/s limit 36.0 s; delay index 2.778. A second car starts inside the segment and
    must not count. Density is the time-mean count of cars inside per km.
    """
    sc = load_scenario("straight")
    hd = sc.hdmap
    edges = ["warmup", "meas", "exit"]
    rec = FlowRecorder(hd, sc.measurement, dt=0.1, warmup=0.0)
    for k in range(1, 1040):
        t = 0.1 * k
        rec.update(_snapshot(hd, t, ["a", "b"], [395.0 + 10.0 * t, 500.0 + 10.0 * t], 10.0, edges))
    tt = rec.vehicle_travel_times()
    assert list(tt) == ["a"]
    assert tt["a"] == pytest.approx(100.0, abs=1e-6)
    limit = float(hd.lane_speed[hd.edge_lanes[hd.edge_of("meas"), 0]])
    assert rec.free_flow_times(["a"])[0] == pytest.approx(1000.0 / limit, rel=1e-6)
    assert rec.delay_index(["a"])[0] == pytest.approx(100.0 * limit / 1000.0, rel=1e-6)
    # b was only partly inside (500 m -> 1400 m) at the same pace: same delay index
    assert rec.delay_index(["b"])[0] == pytest.approx(100.0 * limit / 1000.0, rel=1e-3)
    summary = rec.summary()
    assert summary["dt_tf"] == pytest.approx(100.0, abs=1e-6)
    assert summary["vehicles_crossed"] == 1
    assert summary["mean_speed"] == pytest.approx(10.0)
    assert summary["collisions"] == 0 and summary["teleports"] == 0
    # a is inside for 100 of the 103.9 s, b for its first 90 s: mean count ≈ (1000 + 899) / 1039
    assert summary["measured_density"] == pytest.approx((1000 + 899) / 1039, abs=0.01)


def test_fuel_per_distance_by_hand() -> None:
    """0.5 ml/s at 10 m/s inside the segment is 0.05 ml/m = 5 l/100 km; a car outside the
    segment (on the warm-up edge) and the steps before warm-up do not count."""
    sc = load_scenario("straight")
    hd = sc.hdmap
    rec = FlowRecorder(hd, sc.measurement, dt=0.1, warmup=1.0)
    for k in range(1, 30):
        snap = _snapshot(
            hd, 0.1 * k, ["a", "b"], [100.0, 500.0 + k], 10.0, ["warmup", "meas", "exit"]
        )
        snap.fuel = np.array([50.0, 0.5 if k >= 10 else 9.0])
        rec.update(snap)
    assert rec.summary()["fuel"] == pytest.approx(5.0)
    assert "speed_std_ahead" not in rec.summary()  # no av_window: not measured


def test_flow_metrics_on_a_real_straight_run(tmp_path) -> None:
    sim = start_sim(tmp_path, density=60.0, penetration=0.0, episode_length=100.0)
    rec = FlowRecorder(sim.hdmap, sim.scenario.measurement, sim.config.step_length, warmup=20.0)
    try:
        for _ in range(sim.config.steps_per_episode):
            rec.update(sim.step())
    finally:
        sim.backend.close()
    s = rec.summary()
    assert s["collisions"] == 0 and s["teleports"] == 0
    assert s["vehicles_crossed"] >= 30
    # the mean travel time matches the segment length over the space-mean speed
    assert s["dt_tf"] == pytest.approx(sim.scenario.measurement_length / s["mean_speed"], rel=0.15)
    assert s["measured_density"] == pytest.approx(60.0, rel=0.15)
    tt = np.array(list(rec.vehicle_travel_times().values()))
    limit = float(sim.hdmap.lane_speed.max())
    # nobody crosses faster than the speed limit x the largest speed factor (1.2)
    assert tt.min() >= 1000.0 / (1.2 * limit)
    di = rec.delay_index(list(rec.vehicle_travel_times()))
    assert np.all(di >= 0.95)
    # delay index = travel time / free-flow time, per vehicle
    np.testing.assert_allclose(di * rec.free_flow_times(list(rec.vehicle_travel_times())), tt)


def test_fuel_is_plausible_and_higher_per_km_in_stop_and_go() -> None:
    """SUMO's emission model (HBEFA4 petrol Euro 4 by default): 4-12 l/100 km for cars cruising
    on the highway; more per km in the ring's stop-and-go jam than in its free flow."""
    from mixed_traffic.experiments.runner import run_episode

    def fuel(scenario: str, density: float) -> float:
        cfg = EnvConfig(scenario=scenario, density=density, penetration=0.0, episode_length=60.0)
        return run_episode(cfg, "idm", warmup=20.0)["metrics"]["fuel"]

    assert 4.0 < fuel("straight", 30.0) < 12.0
    free, jam = fuel("ring", 25.0), fuel("ring", 85.0)
    assert 4.0 < free < 12.0
    assert jam > 1.5 * free
