"""Observation: space membership, ground truth with noise off, history, action mask (real SUMO)."""

from __future__ import annotations

import numpy as np
import pytest

from mixed_traffic.config import EnvConfig, SensorConfig
from mixed_traffic.sensing.lane_graph import next_route_edge
from mixed_traffic.sensing.observation import (
    LEFT_CHANGE,
    RIGHT_CHANGE,
    SPEED_SCALE,
    ObservationBuilder,
    observation_space,
)
from mixed_traffic.sensing.perception import Perception

from .conftest import start_sim
from .test_perception import brute_force, drop_network, routes_of, start_drop


def observe(sim, cfg, builder, perception, rng, routes_cache):
    """One step's observations for all AVs of ``sim``; returns (snap, ids, rows, obs)."""
    snap = sim.step(1)
    rows = np.flatnonzero(snap.is_av)
    ids = [snap.ids[r] for r in rows]
    for a in ids:
        if a not in routes_cache:
            routes_cache[a] = [sim.hdmap.edge_row[e] for e in sim.backend.vehicle_route(a)]
    routes = [routes_cache[a] for a in ids]
    nxt = next_route_edge(routes, snap.route_index[rows])
    states = sim.backend.tls_states(perception.tls_ids)
    _, sensed = perception.sense(snap, rows, nxt, states, rng)
    return snap, ids, rows, builder.build(snap, ids, rows, sensed, routes)


def test_space_shapes() -> None:
    cfg = EnvConfig(sensors=SensorConfig(history=4, waypoints=7))
    sp = observation_space(cfg)
    assert sp["ego"].shape == (4, 5)
    assert sp["lanes"].shape == (3, 4, 28)
    assert sp["vehicles"].shape == (3, 4, 12)
    assert sp["lights"].shape == (3, 4, 4)
    assert sp["node_mask"].shape == (3, 3) and sp["action_mask"].shape == (3,)
    assert sp["signals"].shape == (3,)


@pytest.mark.parametrize("weather, reach", [("fog", 1.0), ("rain", 1.0), ("normal", 1.5)])
def test_every_observation_is_in_the_space(tmp_path, weather, reach) -> None:
    """Also with a detection range beyond the nominal one: distances then read up to ``reach``
    and the space holds them."""
    density = 180.0 if reach == 1.0 else 20.0
    sim = start_sim(tmp_path, density=density, penetration=0.5, weather=weather,
                    sensors=SensorConfig(range_factor=reach))  # fmt: skip
    try:
        cfg = sim.config
        space = observation_space(cfg)
        assert space["vehicles"].high[0, 0, 0] == reach and space["vehicles"].high[0, 0, 1] == 1
        builder = ObservationBuilder(cfg, sim.hdmap)
        perception = Perception(cfg.sensors, sim.hdmap, cfg.weather)
        rng, cache = np.random.default_rng(0), {}
        for _ in range(15):
            _, ids, _, obs = observe(sim, cfg, builder, perception, rng, cache)
            assert set(obs) == set(ids) and len(ids) > 12
            for a in ids:
                assert space.contains(obs[a]), a
        far = max(np.abs(obs[a]["vehicles"][..., [0, 6]]).max() for a in ids)
        assert (far > 1.0) == (reach > 1.0), far
    finally:
        sim.backend.close()


def test_noise_off_observation_matches_ground_truth(tmp_path) -> None:
    sim = start_sim(tmp_path, density=120.0, penetration=0.5, weather="normal")
    try:
        cfg = EnvConfig(**{**sim.config.__dict__, "sensors": SensorConfig(noise=False)})
        builder = ObservationBuilder(cfg, sim.hdmap)
        perception = Perception(cfg.sensors, sim.hdmap, cfg.weather)
        rng, cache = np.random.default_rng(0), {}
        for _ in range(3):
            snap, ids, rows, obs = observe(sim, cfg, builder, perception, rng, cache)
        R = cfg.sensors.lidar_range
        limit = sim.hdmap.lane_speed[0]
        for a, r in zip(ids, rows):
            o = obs[a]
            ego = o["ego"][-1]
            assert ego[0] == pytest.approx(snap.speed[r] / SPEED_SCALE, abs=1e-6)
            assert ego[2] == pytest.approx(snap.length[r] / 10.0)
            assert ego[4] == pytest.approx(np.clip(snap.lateral[r] / 2.0, -1, 1), abs=1e-6)
            for col, d in enumerate((+1, 0, -1)):
                k = snap.lane_index[r] + d
                exists = 0 <= k < 3
                assert o["node_mask"][col, 0] == exists
                if not exists:
                    assert not o["lanes"][col, -1].any() and not o["vehicles"][col, -1].any()
                    continue
                wp = o["lanes"][col, -1].reshape(-1, 4)
                np.testing.assert_allclose(wp[:, 1], d / 4.0)  # lane index relative to ego
                np.testing.assert_allclose(wp[:, 3], limit / SPEED_SCALE, rtol=1e-6)
                np.testing.assert_allclose(wp[:, 0], 0.0, atol=1e-6)  # flat road
                f, b = brute_force(snap, r, k, R)
                veh = o["vehicles"][col, -1]
                if np.isfinite(f):
                    assert veh[0] * R == pytest.approx(f, abs=0.3)
                    j = np.flatnonzero(
                        np.isclose(snap.x - snap.x[r], f, atol=0.3) & (snap.lane_index == k)
                    )
                    dv = (snap.speed[j] - snap.speed[r]) / SPEED_SCALE
                    assert np.any(np.isclose(veh[1], dv, atol=1e-5))
                    assert veh[4] == pytest.approx(1.8 / 5.0)
                else:
                    assert not veh[:6].any()
                if np.isfinite(b):
                    assert veh[6] * R == pytest.approx(b, abs=0.3)
                else:
                    assert not veh[6:].any()
                assert o["node_mask"][col, 1] == (np.isfinite(f) or np.isfinite(b))
            assert not o["lights"].any() and not o["signals"].any()  # no signals on the road
    finally:
        sim.backend.close()


def test_history_shifts_one_frame_per_build(tmp_path) -> None:
    sim = start_sim(tmp_path, density=120.0, penetration=0.5)
    try:
        cfg = sim.config
        z = cfg.sensors.history
        builder = ObservationBuilder(cfg, sim.hdmap)
        perception = Perception(cfg.sensors, sim.hdmap, cfg.weather)
        rng, cache = np.random.default_rng(0), {}
        _, ids, _, first = observe(sim, cfg, builder, perception, rng, cache)
        a = ids[0]
        assert not first[a]["ego"][:-1].any() and first[a]["ego"][-1, 2] > 0  # zero-padded
        _, ids2, _, second = observe(sim, cfg, builder, perception, rng, cache)
        for key in ("ego",):
            np.testing.assert_array_equal(second[a][key][-2], first[a][key][-1])
            assert not second[a][key][: z - 2].any()
        for key in ("lanes", "vehicles", "lights"):
            np.testing.assert_array_equal(second[a][key][:, -2], first[a][key][:, -1])
        # an output is a copy: building again does not change what was returned
        before = second[a]["ego"].copy()
        observe(sim, cfg, builder, perception, rng, cache)
        np.testing.assert_array_equal(second[a]["ego"], before)
        # a forgotten agent starts again from zeros
        builder.drop([a])
        _, _, _, again = observe(sim, cfg, builder, perception, rng, cache)
        assert not again[a]["ego"][:-1].any()
        builder.reset()
        _, _, _, fresh = observe(sim, cfg, builder, perception, rng, cache)
        assert not fresh[ids2[1]]["ego"][:-1].any()
    finally:
        sim.backend.close()


def test_action_mask_masks_missing_lanes_on_straight(tmp_path) -> None:
    sim = start_sim(tmp_path, density=120.0, penetration=0.5)
    try:
        cfg = sim.config
        builder = ObservationBuilder(cfg, sim.hdmap)
        perception = Perception(cfg.sensors, sim.hdmap, cfg.weather)
        snap, ids, rows, obs = observe(sim, cfg, builder, perception, np.random.default_rng(0), {})
        seen = set()
        for a, r in zip(ids, rows):
            k = int(snap.lane_index[r])
            mask = obs[a]["action_mask"]
            expect = [int(k < 2), 1, int(k > 0)]
            np.testing.assert_array_equal(mask, expect)
            seen.add(k)
        assert seen == {0, 1, 2}
    finally:
        sim.backend.close()


def test_mandatory_lane_change_before_a_lane_drop(tmp_path) -> None:
    hd = drop_network(tmp_path)
    # av_0: left lane 60 m before its end (mandatory); av_1: left lane, far from the end;
    # av_2: right lane near the end (its left lane ends: no change left); hv_0 leads av_2 on bc
    vehicles = [("av_0", "ab", 1, 236.0), ("av_1", "ab", 1, 50.0), ("av_2", "ab", 0, 280.0),
                ("hv_0", "bc", 0, 20.0)]  # fmt: skip
    backend = start_drop(tmp_path, hd, vehicles)
    try:
        cfg = EnvConfig(sensors=SensorConfig(noise=False))
        snap = backend.step()
        ids = ["av_0", "av_1", "av_2"]
        rows = np.array([snap.ids.index(v) for v in ids])
        assert list(snap.lane[rows]) == [
            hd.lane_row["ab_1"],
            hd.lane_row["ab_1"],
            hd.lane_row["ab_0"],
        ]
        routes = routes_of(backend, hd, ids)
        nxt = next_route_edge(routes, snap.route_index[rows])
        perception = Perception(cfg.sensors, hd, cfg.weather)
        _, sensed = perception.sense(
            snap, rows, nxt, backend.tls_states(perception.tls_ids), np.random.default_rng(0)
        )
        obs = ObservationBuilder(cfg, hd).build(snap, ids, rows, sensed, routes)
        np.testing.assert_array_equal(obs["av_0"]["action_mask"], [0, 0, 1])  # must go right
        np.testing.assert_array_equal(obs["av_1"]["action_mask"], [0, 1, 1])
        np.testing.assert_array_equal(
            obs["av_2"]["action_mask"], [0, 1, 0]
        )  # left lane leaves route
        assert observation_space(cfg).contains(obs["av_0"])
        # virtual stopped vehicle at the end line of ab_1, seen as av_0's front vehicle
        end = hd.lane_length[hd.lane_row["ab_1"]] - snap.lane_pos[rows[0]]
        front = obs["av_0"]["vehicles"][1, -1, :6]
        assert front[0] * cfg.sensors.lidar_range == pytest.approx(end, abs=1e-4)
        assert front[1] == pytest.approx(-snap.speed[rows[0]] / SPEED_SCALE, abs=1e-6)
        assert front[4] > 0 and obs["av_0"]["node_mask"][1, 1] == 1
        assert not obs["av_1"]["vehicles"][1, -1, :6].any()  # far from the end: nothing ahead
        # av_2 sees hv_0 across the junction as its leader (independent: x difference; the
        # junction lane bends 3.2 m sideways onto the single lane, so along-lane is ~0.8 m longer)
        j = snap.ids.index("hv_0")
        front2 = obs["av_2"]["vehicles"][1, -1]
        assert front2[0] * cfg.sensors.lidar_range == pytest.approx(
            snap.x[j] - snap.x[rows[2]] + 0.5, abs=0.5
        )
        # av_2 is 16 m before the signal: the light is detected on its lane only
        assert obs["av_2"]["node_mask"][1, 2] == 1 and obs["av_2"]["lights"][1, -1, :3].sum() == 1
        assert obs["av_2"]["node_mask"][0, 2] == 0
        assert LEFT_CHANGE == 0 and RIGHT_CHANGE == 2
    finally:
        backend.close()
