"""Batched worlds (issue 60): copies of a scenario in one SUMO network, on real SUMO."""

from __future__ import annotations

import numpy as np
import pytest

from mixed_traffic.config import EnvConfig
from mixed_traffic.env.action import FOLLOW
from mixed_traffic.env.parallel import MixedTrafficEnv
from mixed_traffic.paths import cache_dir
from mixed_traffic.world.copies import GAP, copy_of_id, make_batch, vehicle_copy
from mixed_traffic.world.registry import load_scenario


def test_copies_are_the_network_again_far_apart() -> None:
    sc = load_scenario("merge")
    batch = make_batch((sc,) * 3)
    hd, one = batch.views[0].hdmap, sc.hdmap
    assert len(hd.lane_ids) == 3 * len(one.lane_ids)
    assert np.bincount(batch.lane_copy).tolist() == [len(one.lane_ids)] * 3
    for i, view in enumerate(batch.views):  # a copy's routes and segment are its own
        assert all(copy_of_id(e) == i for r in view.routes for e in r.edges)
        assert [copy_of_id(e) for e in view.measurement] == [i] * len(sc.measurement)
    length = dict(zip(one.lane_ids, one.lane_length))
    for lane, copy, metres in zip(hd.lane_ids, batch.lane_copy, hd.lane_length):
        assert metres == length[lane.replace(f"c{copy}_", "", 1)]  # the same lanes
    y = hd.wp_xyz[:, 1]
    spans = [(y[batch.lane_copy[hd.wp_lane] == c].min(), y[batch.lane_copy[hd.wp_lane] == c].max())
             for c in range(3)]  # fmt: skip
    assert all(spans[c + 1][0] - spans[c][1] >= GAP - 1.0 for c in range(2))


def _run(env: MixedTrafficEnv, seed: int, check=None) -> list[np.ndarray]:
    """Drive an episode with every agent following at zero acceleration; (N, 2) positions of
    every vehicle per step, sorted by id."""
    env.reset(seed=seed)
    out = []
    while env.agents:
        n = len(env.agents)
        out_step = env.step_batch(np.full(n, FOLLOW), np.zeros((n, 3, 2)))
        snap = env._snap
        if check is not None:
            check(snap, out_step)
        order = np.argsort(snap.ids)
        out.append(np.stack([snap.x[order], snap.y[order]], axis=1))
    return out


@pytest.mark.parametrize("scenario", ["merge", "ring"])
def test_no_vehicle_leaves_its_copy_and_agents_carry_theirs(scenario: str) -> None:
    env = MixedTrafficEnv(scenario=scenario, copies=3, penetration=0.2, episode_length=40.0)
    per_copy = len(env.possible_agents) // 3
    lane_copy = make_batch((env._bundled,) * 3).lane_copy
    seen = set()

    def check(snap, step) -> None:
        on = snap.lane >= 0
        ids = np.array(snap.ids, dtype=object)[on]
        want = [vehicle_copy(v, per_copy) for v in ids]
        assert lane_copy[snap.lane[on]].tolist() == want
        assert step.copy.tolist() == [int(a[3:]) // per_copy for a in step.agents]
        seen.update(want)

    try:
        assert env.agent_copy.tolist() == [int(a[3:]) // per_copy for a in env.possible_agents]
        env.reset(seed=4)
        act = {a: {"decision": 1, "params": np.zeros((3, 2))} for a in env.agents}
        infos = env.step(act)[4]
        assert infos and all(i["copy"] == int(a[3:]) // per_copy for a, i in infos.items())
        _run(env, 4, check)
    finally:
        env.close()
    assert seen == {0, 1, 2}, "every copy had vehicles"


def test_the_same_seed_and_copies_drive_the_same_trajectories() -> None:
    config = EnvConfig(scenario="ring", ring_length=(220.0, 270.0), ring_vehicles=22,
                       penetration=1 / 22, copies=2, episode_length=20.0)  # fmt: skip
    runs = []
    for _ in range(2):
        env = MixedTrafficEnv(config=config)
        try:
            runs.append(_run(env, 7))
            lengths = env.ring_lengths
        finally:
            env.close()
    assert all(np.array_equal(a, b) for a, b in zip(*runs))
    assert len(lengths) == 2 and all(220.0 <= x <= 270.0 for x in lengths)


def test_each_copy_has_its_own_record() -> None:
    env = MixedTrafficEnv(scenario="straight", density=60.0, penetration=0.2, copies=2,
                          episode_length=30.0, warmup=5.0)  # fmt: skip
    try:
        _run(env, 1)
        one, two = env.episode_metrics(0), env.episode_metrics(1)
    finally:
        env.close()
    for m in (one, two):
        assert 50.0 < m["measured_density"] < 70.0  # each copy at its own density
        assert m["av_trips"] is not None and m["mean_speed"] > 10.0
    assert one["mean_speed"] != two["mean_speed"], "copies draw their own demand"


@pytest.mark.parametrize(("kw", "needle"), [
    ({"copies": 0}, "EnvConfig.copies=0 is out of range"),
    ({"copies": 2, "scenario": "urban"}, "copies=2: 'urban' is the urban family"),
    ({"copies": 1024, "density": 400.0}, r"copies=1024: \d+ vehicles need about .* GiB, more "),
])  # fmt: skip
def test_bad_copies_are_named_before_any_work(kw: dict, needle: str) -> None:
    nets = set(cache_dir("nets").glob("copies*"))
    with pytest.raises(ValueError, match=needle):
        MixedTrafficEnv(**kw)
    assert set(cache_dir("nets").glob("copies*")) == nets, "no network was joined"
