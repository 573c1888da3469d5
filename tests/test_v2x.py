"""V2X downstream feed and the reward terms of the traffic around an agent (real SUMO; route
distances checked against SUMO's own ``getDrivingDistance``)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from gymnasium import spaces
from pettingzoo.test import parallel_api_test

from mixed_traffic.config import EnvConfig, RewardConfig, V2XConfig
from mixed_traffic.env import parallel_env
from mixed_traffic.env.reward import TERM_NAMES
from mixed_traffic.env.traffic_terms import TRAFFIC_TERMS
from mixed_traffic.provenance import record_meta
from mixed_traffic.sensing.observation import SPEED_SCALE, observation_space
from mixed_traffic.sensing.route_traffic import ring_pairs, route_frame, route_pairs
from mixed_traffic.world.ring import ring_lengths
from mixed_traffic.wrappers import FlatObservationWrapper

FOLLOW = {"decision": 1, "params": np.zeros((3, 2), np.float32)}
#: A feed without noise that measures every step and arrives at once.
EXACT = V2XConfig(update_period=0.1, latency=0.0, speed_noise=0.0)


def follow_all(env) -> dict:
    return {a: FOLLOW for a in env.agents}


def run(env, steps: int) -> tuple:
    out = None
    for _ in range(steps):
        out = env.step(follow_all(env))
    return out


def pairs_now(env, behind: float, ahead: float):
    """Route pairs of the env's live agents at its current snapshot."""
    snap, table = env._snap, env._table
    rows = table.live_rows(snap)
    frame = route_frame(env.hdmap, snap, rows.r, table.route_table[rows.slots],
                        table.route_len[rows.slots])  # fmt: skip
    if env.scenario.ring:
        return rows, ring_pairs(env.hdmap, snap, frame)
    return rows, route_pairs(env.hdmap, snap, frame, behind, ahead)


# ---------------------------------------------------------------------- config, spaces, records
def test_space_flat_wrapper_and_record_know_the_key() -> None:
    feed = V2XConfig(segments=(0.0, 50.0, 200.0, 500.0, 1500.0))
    cfg = EnvConfig(v2x=True, v2x_feed=feed)
    assert observation_space(cfg)["downstream"].shape == (4, 2)
    assert "downstream" not in observation_space(EnvConfig()).spaces  # off by default
    on = FlatObservationWrapper(parallel_env(config=cfg))
    off = FlatObservationWrapper(parallel_env(config=replace(cfg, v2x=False)))
    size = spaces.flatdim(on.observation_space("av_0")) - spaces.flatdim(
        off.observation_space("av_0")
    )
    assert size == 8
    sl = on.slices["downstream"]
    assert sl.stop - sl.start == 8
    saved = json.loads(json.dumps(record_meta(cfg)))["config"]
    assert saved["v2x"] is True and saved["v2x_feed"]["segments"] == list(feed.segments)
    assert EnvConfig.from_dict(saved) == cfg


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [({"segments": (0.0, 100.0, 100.0)}, "segments"), ({"segments": (50.0,)}, "segments"),
     ({"latency": -1.0}, "latency"), ({"update_period": 0.0}, "update_period"),
     ({"probe_share": 0.0}, "probe_share"), ({"speed_noise": float("nan")}, "speed_noise")],
)  # fmt: skip
def test_bad_feed_config_names_the_field(kwargs: dict, field: str) -> None:
    with pytest.raises(ValueError, match=rf"V2XConfig\.{field}="):
        V2XConfig(**kwargs)
    with pytest.raises(ValueError, match=r"EnvConfig\.v2x="):
        EnvConfig(v2x="yes")
    with pytest.raises(ValueError, match=r"RewardConfig\.followers="):
        RewardConfig(followers=0)


# ---------------------------------------------------------------------- PettingZoo API
@pytest.mark.parametrize(
    ("scenario", "fleet"), [("ring", False), ("straight", False), ("straight", True)]
)
def test_parallel_api_with_v2x(scenario: str, fleet: bool) -> None:
    """PettingZoo's API test passes with the key on (also a fixed fleet, whose agents re-enter);
    the observation batch holds it; the agents there from the start have reports by 2.5 s."""
    e = parallel_env(scenario=scenario, v2x=True, density=60.0, penetration=0.2,
                     episode_length=6.0, fixed_fleet=fleet)  # fmt: skip
    try:
        parallel_api_test(e, num_cycles=40)
        obs, _ = e.reset(seed=3)
        first = set(e.agents)
        obs, *_ = run(e, 25)  # past the first report (update 1 s + latency 1 s)
        batch = e.observation_batch()
        assert batch["downstream"].shape == (len(e.agents), 3, 2)
        assert np.array_equal(
            batch["downstream"], np.stack([obs[a]["downstream"] for a in e.agents])
        )
        old = [i for i, a in enumerate(e.agents) if a in first]
        assert old and (batch["downstream"][old, :, 0] > 0).all()  # a report has arrived
    finally:
        e.close()


# ---------------------------------------------------------------------- route distances
@pytest.mark.parametrize(
    ("scenario", "density"), [("urban", 30.0), ("merge", 90.0), ("ring", None)]
)
def test_route_distances_are_sumos_driving_distances(scenario: str, density: float | None) -> None:
    """Every vehicle ahead of an agent on its route within 400 m is paired with it, at
    SUMO's driving distance (junction lanes included; on a ring within one lap); one behind
    it on its route, at the distance SUMO drives that vehicle to the agent."""
    e = parallel_env(scenario=scenario, density=density, penetration=0.2, episode_length=30.0)
    try:
        e.reset(seed=1)
        run(e, 100)
        rows, pairs = pairs_now(e, 400.0, 400.0)
        api, snap = e._backend._api.vehicle, e._snap
        found = dict(zip(zip(pairs.agent.tolist(), pairs.vehicle.tolist()), pairs.distance))
        checked = behind = 0
        for i, a in enumerate(rows.ids):
            for v, vid in enumerate(snap.ids):
                if vid == a:
                    continue
                ref = api.getDrivingDistance(a, api.getRoadID(vid), api.getLanePosition(vid),
                                             api.getLaneIndex(vid))  # fmt: skip
                if 0.5 < ref < 399.5:  # SUMO reaches it along the agent's route
                    assert found.get((i, v)) == pytest.approx(ref, abs=1e-6), (a, vid)
                    checked += 1
                elif not e.scenario.ring and found.get((i, v), 0.0) < 0:
                    back = api.getDrivingDistance(vid, api.getRoadID(a), api.getLanePosition(a),
                                                  api.getLaneIndex(a))  # fmt: skip
                    if back >= 0:  # the vehicle's own route passes the agent
                        assert found[(i, v)] == pytest.approx(-back, abs=1e-6), (a, vid)
                        behind += 1
        assert checked > 20 and (behind > 10 or e.scenario.ring)
        if e.scenario.ring:
            assert (pairs.distance >= 0).all() and (pairs.distance < pairs.lap[pairs.agent]).all()
    finally:
        e.close()


# ---------------------------------------------------------------------- the feed
def test_ring_segments_wrap_around() -> None:
    """On a ring a vehicle d ahead counts in every segment holding d + k·lap: the 300-1000 m
    segment of a 260 m ring sees its traffic 2-3 times over (SUMO's distances, the ring's
    length from its lanes)."""
    e = parallel_env(scenario="ring", v2x=True, v2x_feed=EXACT, penetration=0.1,
                     episode_length=20.0)  # fmt: skip
    try:
        e.reset(seed=0)
        obs, *_ = run(e, 30)
        api, a = e._backend._api.vehicle, e.agents[0]
        lap = ring_lengths(e.scenario)[0]
        others = [v for v in api.getIDList() if v != a]
        dist = np.array([api.getDrivingDistance(a, api.getRoadID(v), api.getLanePosition(v))
                         for v in others])  # fmt: skip
        speed = np.array([api.getSpeed(v) for v in others])
        edges = EXACT.segments
        for s, (lo, hi) in enumerate(zip(edges, edges[1:])):
            w = np.array([sum(lo <= d + k * lap < hi for k in range(10)) for d in dist])
            assert w.sum() > 0
            got = obs[a]["downstream"][s]
            assert got[0] * SPEED_SCALE == pytest.approx((w * speed).sum() / w.sum(), abs=1e-3)
            assert got[1] == pytest.approx(w.sum() / (hi - lo) * 7.0, rel=1e-4)  # one lane
    finally:
        e.close()


def test_slower_traffic_ahead_reads_lower() -> None:
    """Slowing the vehicles 100-300 m ahead of an agent lowers that segment's speed, and the
    feed matches the mean speed of the vehicles SUMO puts there."""
    kw = dict(scenario="straight", v2x=True, v2x_feed=EXACT, density=60.0, penetration=0.1,
              episode_length=20.0)  # fmt: skip
    readings = []
    for slow in (False, True):
        e = parallel_env(**kw)
        try:
            e.reset(seed=2)
            run(e, 5)
            a = e.agents[0]
            rows, pairs = pairs_now(e, 0.0, 1000.0)
            i = rows.ids.index(a)
            mine = pairs.agent == i
            ahead = pairs.vehicle[mine & (pairs.distance >= 120.0) & (pairs.distance < 280.0)]
            assert len(ahead) >= 2
            if slow:
                for v in ahead.tolist():
                    e._backend._api.vehicle.setSpeed(e._snap.ids[v], 5.0)
            obs, *_ = run(e, 40)
            rows, pairs = pairs_now(e, 0.0, 1000.0)
            i = rows.ids.index(a)
            mine = pairs.agent == i
            seg = mine & (pairs.distance >= 100.0) & (pairs.distance < 300.0)
            seg &= pairs.vehicle != rows.r[i]
            truth = e._snap.speed[pairs.vehicle[seg]].mean()
            readings.append(obs[a]["downstream"][1, 0] * SPEED_SCALE)
            assert readings[-1] == pytest.approx(truth, abs=1e-3)
        finally:
            e.close()
    assert readings[1] < readings[0] - 5.0


def test_latency_and_update_period_hold_the_value() -> None:
    """Measured once a second, arriving 0.5 s later: the value changes only when a report
    arrives (at k + 0.5 s) and is held in between; nothing before the first arrives."""
    feed = V2XConfig(update_period=1.0, latency=0.5, speed_noise=0.5)
    e = parallel_env(scenario="ring", v2x=True, v2x_feed=feed, penetration=0.1,
                     episode_length=20.0)  # fmt: skip
    try:
        obs, _ = e.reset(seed=0)
        a = e.agents[0]
        first_measure = e.sim_time
        prev, changes = obs[a]["downstream"].copy(), []
        assert not prev.any()
        for _ in range(45):
            obs, *_ = e.step(follow_all(e))
            now = obs[a]["downstream"]
            if e.sim_time < first_measure + 0.5 - 1e-6:
                assert not now.any()
            if not np.array_equal(now, prev):
                changes.append(round(e.sim_time, 3))
            prev = now.copy()
        assert changes[0] == pytest.approx(first_measure + 0.5)
        assert changes[1:] == pytest.approx([k + 0.5 for k in range(1, len(changes))])
        assert len(changes) >= 4
    finally:
        e.close()


# ---------------------------------------------------------------------- reward terms
def test_traffic_terms_in_infos_and_zero_weights_keep_the_reward() -> None:
    """r5 and r6 are in every agent's infos; weighted 0 the reward is the paper's sum, and
    weighted w they add exactly w·r5 + w·r6 (same seed, same actions, same traffic)."""
    kw = dict(scenario="straight", density=120.0, penetration=0.2, episode_length=5.0)
    weighted = RewardConfig(w_local_speed=0.5, w_follower_comfort=2.0)
    e0, e1 = parallel_env(**kw), parallel_env(**kw, reward=weighted)
    try:
        e0.reset(seed=4)
        e1.reset(seed=4)
        n = 0
        for _ in range(20):
            _, r0, _, _, i0 = e0.step(follow_all(e0))
            _, r1, _, _, i1 = e1.step(follow_all(e1))
            for a, info in i0.items():
                t = info["reward_terms"]
                if not t:
                    continue
                assert set(t) == set(TERM_NAMES) and set(TRAFFIC_TERMS) <= set(t)
                paper = (0.9 * (t["r1_ttc"] + t["r1_lane"] + t["r1_terminal"])
                         + 0.8 * (t["r2_speed"] + t["r2_lane_change"]) + 0.6 * t["r3_comfort"]
                         + 0.2 * t["r4_impact"])  # fmt: skip
                assert r0[a] == pytest.approx(paper, abs=1e-12)
                assert i1[a]["reward_terms"] == t
                extra = 0.5 * t["r5_local_speed"] + 2.0 * t["r6_follower_comfort"]
                assert r1[a] == pytest.approx(r0[a] + extra, abs=1e-12)
                assert 0.0 <= t["r5_local_speed"] < 1.5 and t["r6_follower_comfort"] <= 0.0
                n += 1
        assert n > 50
    finally:
        e0.close()
        e1.close()


def test_ring_terms_are_the_whole_ring_and_sumos_followers() -> None:
    """On a one-lane ring r5 is every vehicle's mean speed over the limit, r8 the RMS distance
    of every speed to the ring's uniform-flow speed (at which IDM neither speeds up nor slows
    down), and r6 the mean squared acceleration (/ acc_thr²) of the k vehicles SUMO names as
    followers one by one."""
    k = 4
    e = parallel_env(scenario="ring", penetration=0.1, episode_length=20.0,
                     reward=RewardConfig(followers=k, local_upstream=1000.0))  # fmt: skip
    try:
        e.reset(seed=5)
        _, _, _, _, infos = run(e, 40)
        api = e._backend._api.vehicle
        lanes = e._backend._api.lane
        speeds = np.array([api.getSpeed(v) for v in api.getIDList()])
        limit = lanes.getMaxSpeed(api.getLaneID(e.agents[0]))
        star, h = e._desired[e.hdmap.lane_row[api.getLaneID(e.agents[0])]], e.config.human
        gap = e.ring_length / len(speeds) - e.config.vehicle.length
        idm = 1 - (star / limit) ** h.delta - ((h.min_gap + star * h.headway) / gap) ** 2
        assert 0 < star < limit and abs(idm) < 1e-3
        rms = np.sqrt(np.mean((speeds - star) ** 2))
        for a in e.agents:
            t = infos[a]["reward_terms"]
            assert t["r5_local_speed"] == pytest.approx(speeds.mean() / limit, rel=1e-9)
            assert t["r8_uniform_flow"] == pytest.approx(max(0.0, 1 - rms / star), rel=1e-9)
            chain, v = [], a
            for _ in range(k):
                v = api.getFollower(v, 300.0)[0]
                chain.append(v)
            sq = [(api.getAcceleration(f) / 3.0) ** 2 for f in chain]
            assert t["r6_follower_comfort"] == pytest.approx(-np.mean(sq), rel=1e-9, abs=1e-12)
    finally:
        e.close()


def test_local_speed_falls_when_the_traffic_around_slows() -> None:
    """r5 of an agent falls when the vehicles within its window ahead slow down (same seed,
    same actions, the slowed run against the plain one)."""
    kw = dict(scenario="straight", density=60.0, penetration=0.1, episode_length=20.0)
    values = []
    for slow in (False, True):
        e = parallel_env(**kw)
        try:
            e.reset(seed=2)
            run(e, 5)
            a = e.agents[0]
            rows, pairs = pairs_now(e, 200.0, 200.0)
            near = pairs.vehicle[(pairs.agent == rows.ids.index(a)) & (pairs.distance > 30.0)]
            if slow:
                for v in near.tolist():
                    e._backend._api.vehicle.setSpeed(e._snap.ids[v], 3.0)
            _, _, _, _, infos = run(e, 40)
            values.append(infos[a]["reward_terms"]["r5_local_speed"])
        finally:
            e.close()
    assert values[1] < values[0] - 0.05


def test_the_feed_changes_no_other_observation() -> None:
    """The feed draws its noise from its own generator: with it on, the sensors' noise, the
    other keys, the rewards and the traffic are those of the same seed without it."""
    kw = dict(scenario="straight", density=60.0, penetration=0.2, episode_length=5.0,
              v2x_feed=V2XConfig(probe_share=0.5))  # fmt: skip
    on, off = parallel_env(**kw, v2x=True), parallel_env(**kw)
    try:
        o1, _ = on.reset(seed=7)
        o0, _ = off.reset(seed=7)
        for _ in range(25):
            o1, r1, *_ = on.step(follow_all(on))
            o0, r0, *_ = off.step(follow_all(off))
            assert r1 == r0 and list(o1) == list(o0)
            for a in o0:
                assert set(o1[a]) - set(o0[a]) == {"downstream"}
                assert all(np.array_equal(o1[a][k], o0[a][k]) for k in o0[a])
    finally:
        on.close()
        off.close()
