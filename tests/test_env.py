"""The PettingZoo env on real SUMO: API compliance, seeding, lifecycle, physics, bad input."""

from __future__ import annotations

import subprocess
import warnings

import numpy as np
import pytest
from pettingzoo.test import api_test, parallel_api_test, parallel_seed_test

import mixed_traffic
from mixed_traffic.config import EnvConfig, SensorConfig
from mixed_traffic.env import MixedTrafficEnv, NoAgentError, env, parallel_env
from mixed_traffic.env.reward import TERM_NAMES
from mixed_traffic.schema import TERMINAL_REASONS
from mixed_traffic.world.backend import binary
from mixed_traffic.world.registry import list_scenarios

SHORT = dict(density=60.0, penetration=0.3, episode_length=8.0)


def _family_defaults() -> list[str]:
    return [
        f
        for f in ("straight", "highway", "bottleneck", "merge", "ring", "urban")
        if f in list_scenarios()
    ]


def _follow(env_: MixedTrafficEnv, accel_brake: float = 0.0, steer: float = 0.0) -> dict:
    acts = {}
    for a in env_.agents:
        params = np.zeros((3, 2), np.float32)
        params[1] = (steer, accel_brake)
        acts[a] = {"decision": 1, "params": params}
    return acts


@pytest.mark.parametrize("scenario", _family_defaults())
def test_parallel_api(scenario: str) -> None:
    e = parallel_env(scenario=scenario, **SHORT)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            parallel_api_test(e, num_cycles=80)
        # possible_agents lists every AV of the demand, also those still queued upstream when
        # the episode is truncated, so "not all possible_agents ... truncated" is expected
        api_warnings = [
            str(w.message)
            for w in caught
            if "agent" in str(w.message).lower() and "not all possible_agents" not in str(w.message)
        ]
        assert not api_warnings, api_warnings  # e.g. "Live agent was not given reward"
    finally:
        e.close()


@pytest.mark.parametrize("scenario", _family_defaults())
def test_aec_api(scenario: str) -> None:
    e = env(scenario=scenario, **SHORT)
    try:
        api_test(e, num_cycles=20)
    finally:
        e.close()


@pytest.mark.parametrize("scenario", _family_defaults())
def test_parallel_seed(scenario: str) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the 2nd env falls back to TraCI
        parallel_seed_test(lambda: parallel_env(scenario=scenario, **SHORT), num_cycles=30)


def test_same_seed_same_trajectories_across_resets() -> None:
    e = parallel_env(**SHORT)
    try:
        runs = []
        for _ in range(2):
            obs, _ = e.reset(seed=7)
            e.action_space("av_0").seed(3)
            trace = []
            for _ in range(30):
                acts = {a: e.action_space(a).sample(mask=obs[a]["action_mask"]) for a in e.agents}
                obs, rew, *_ = e.step(acts)
                trace.append(sorted((a, round(r, 9)) for a, r in rew.items()))
            snap = e._snap
            runs.append((trace, snap.ids, snap.x.copy(), snap.speed.copy()))
        assert runs[0][0] == runs[1][0]
        assert runs[0][1] == runs[1][1]
        np.testing.assert_array_equal(runs[0][2], runs[1][2])
        obs_other, _ = e.reset(seed=8)
        assert e._snap.ids != runs[0][1] or not np.array_equal(e._snap.x, runs[0][2])
    finally:
        e.close()


def test_agents_enter_leave_and_report_terms() -> None:
    e = parallel_env(density=60.0, penetration=0.3, episode_length=60.0)
    try:
        obs, _ = e.reset(seed=1)
        first = set(e.agents)
        seen, events = set(first), {}
        while e.agents:
            obs, rew, term, trunc, info = e.step(_follow(e))
            _assert_batch_is_stacked(e, obs)
            seen |= set(e.agents)
            if e.agents:  # memory stays flat: finished agents leave no observation or history
                assert set(e._batches.last) <= set(e.agents) >= set(e._builder._slot)
            for a, i in info.items():
                assert set(i["reward_terms"]) <= set(TERM_NAMES)
                if i["event"]:
                    events[a] = i["event"]
                if a in rew and i["reward_terms"] and i["event"] in ("", "arrived"):
                    assert rew[a] == pytest.approx(rew[a])  # finite
        assert seen - first, "AVs entering upstream must become agents"
        assert "arrived" in events.values(), "AVs at 60 veh/km cross 1.6 km within 60 s"
        assert "entered" in events.values()
        assert set(seen) <= set(e.possible_agents)
        metrics = e.episode_metrics()
        ends = sum(metrics[f"terminal_{r}"] for r in TERMINAL_REASONS)
        arrivals = sum(1 for ev in events.values() if ev == "arrived")
        assert metrics["av_trips"] == ends + arrivals  # every ended trip is counted once
        assert metrics["route_completion"] == pytest.approx(100.0 * arrivals / metrics["av_trips"])
        assert 50 < metrics["measured_density"] < 70
    finally:
        e.close()


def _assert_batch_is_stacked(e: MixedTrafficEnv, obs: dict) -> None:
    """``observation_batch`` equals the step's per-agent observations stacked (in the live
    agents' order and reversed; agents that finished or entered this step included)."""
    for order in (e.agents, e.agents[::-1]):
        batch = e.observation_batch(order)
        for key, x in batch.items():
            ref = np.stack([obs[a][key] for a in order]) if order else x
            assert x.dtype == ref.dtype and np.array_equal(x, ref), key
            assert len(x) == len(order)


def test_fixed_fleet_keeps_a_constant_agent_set() -> None:
    e = parallel_env(fixed_fleet=True, **SHORT)
    try:
        obs, _ = e.reset(seed=0)
        agents = list(e.agents)
        assert agents == e.possible_agents and len(agents) > 0
        for _ in range(40):
            obs, rew, term, trunc, info = e.step(_follow(e))
            if not e.agents:
                break
            assert e.agents == agents
            assert set(obs) == set(agents) and not any(term.values())
            _assert_batch_is_stacked(e, obs)
    finally:
        e.close()


def test_accel_brake_changes_speed() -> None:
    e = parallel_env(density=60.0, penetration=0.3, episode_length=20.0)
    try:
        e.reset(seed=2)
        a = e.agents[0]
        speed = lambda: e._snap.speed[e._snap.ids.index(a)]  # noqa: E731
        v0 = speed()
        for _ in range(10):
            e.step(_follow(e, accel_brake=-1.0))
        v_brake = speed()
        assert v_brake < v0 - 4.0  # 1 s at -6 m/s^2
        for _ in range(10):
            e.step(_follow(e, accel_brake=1.0))
        assert speed() > v_brake + 2.0  # 1 s at +3 m/s^2
    finally:
        e.close()


def test_speeding_terminates_and_removes_the_vehicle() -> None:
    e = parallel_env(density=60.0, penetration=0.3, episode_length=30.0)
    try:
        e.reset(seed=3)
        a = e.agents[0]
        for _ in range(200):
            acts = _follow(e)
            if a not in acts:
                break
            acts[a]["params"][1, 1] = 1.0
            obs, rew, term, trunc, info = e.step(acts)
            if term.get(a):
                break
        assert info[a]["event"] in ("speed_limit", "collision")
        assert info[a]["reward_terms"]["r1_terminal"] == -20.0
        assert a not in e.agents and a not in e._backend.read().ids
    finally:
        e.close()


def test_noise_free_observation_matches_ground_truth() -> None:
    cfg = EnvConfig(sensors=SensorConfig(noise=False), weather="fog", **SHORT)
    e = parallel_env(config=cfg)
    try:
        obs, _ = e.reset(seed=0)
        snap = e._snap
        for a, o in obs.items():
            i = snap.ids.index(a)
            assert o["ego"][-1, 0] == pytest.approx(snap.speed[i] / 40.0, abs=1e-6)
            assert o["ego"][-1, 4] == pytest.approx(np.clip(snap.lateral[i] / 2.0, -1, 1), abs=1e-6)
    finally:
        e.close()


def test_bad_actions_get_clear_errors() -> None:
    e = parallel_env(**SHORT)
    try:
        e.reset(seed=0)
        a = e.agents[0]
        acts = _follow(e)
        acts[a]["params"][1, 0] = np.nan
        with pytest.raises(ValueError, match=a):
            e.step(acts)
        acts = _follow(e)
        del acts[a]
        with pytest.raises(ValueError, match=a):
            e.step(acts)
        acts = _follow(e)
        acts["av_99999"] = acts[a]
        with pytest.raises(ValueError, match="av_99999"):
            e.step(acts)
        e.step(_follow(e))  # the env is still usable after rejected actions
    finally:
        e.close()


def test_bad_config_fails_before_sumo_starts() -> None:
    with pytest.raises(ValueError, match="penetration"):
        parallel_env(penetration=1.5)
    with pytest.raises(ValueError, match="density"):
        parallel_env(density=5000.0)
    with pytest.raises(ValueError, match="unknown scenario"):
        parallel_env(scenario="no_such_scenario")
    with pytest.raises(ValueError, match="either config"):
        MixedTrafficEnv(config=EnvConfig(), density=60.0)


def test_render_rgb_array_and_human_without_display(monkeypatch) -> None:
    e = parallel_env(render_mode="rgb_array", **SHORT)
    try:
        e.reset(seed=0)
        img = e.render()
        assert img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8
        assert (img == np.array([220, 40, 40], np.uint8)).all(axis=2).any()  # an AV is drawn red
    finally:
        e.close()
    monkeypatch.delenv("DISPLAY", raising=False)
    with pytest.raises(ValueError, match="display"):
        parallel_env(render_mode="human", **SHORT)


def test_package_level_constructors() -> None:
    e = mixed_traffic.parallel_env(**SHORT)
    try:
        assert isinstance(e, MixedTrafficEnv)
        assert e.possible_agents[0] == "av_0"
    finally:
        e.close()


def test_a_refused_placement_never_appears_mid_road(monkeypatch) -> None:
    # two vehicles placed on the same spot: SUMO inserts one and keeps retrying the other, which
    # would appear wherever a gap opens later; reset drops it instead
    import dataclasses

    import mixed_traffic.world.copies as demand_module

    make_demand, refused = demand_module.make_demand, []

    def clashing(scenario, config, rng):
        demand = make_demand(scenario, config, rng)
        first, second = demand.vehicles[:2]
        refused.append(second.vid)
        second = dataclasses.replace(
            second, depart_pos=first.depart_pos, depart_lane=first.depart_lane
        )
        return dataclasses.replace(demand, vehicles=(first, second, *demand.vehicles[2:]))

    monkeypatch.setattr(demand_module, "make_demand", clashing)
    e = parallel_env(**SHORT)
    try:
        e.reset(seed=0)
        seen = set(e._snap.ids)
        for _ in range(70):  # the vehicle in front of it leaves the spot within a few steps
            e.step(_follow(e))
            seen |= set(e._snap.ids)
        assert refused[-1] not in seen
        assert e._backend.pending() == ()
    finally:
        e.close()


def test_vehicles_waiting_at_an_entry_are_not_dropped(tmp_path) -> None:
    # six of a user's vehicles depart together at a 3-lane entry: the others wait and follow
    import shutil

    from mixed_traffic.world.registry import load_scenario

    shutil.copy(load_scenario("straight").net_file, tmp_path / "road.net.xml")
    cars = "".join(f'<vehicle id="c{i}" depart="0" route="main"/>' for i in range(6))
    (tmp_path / "r.rou.xml").write_text(
        f'<routes><route id="main" edges="warmup meas exit"/>{cars}</routes>'
    )
    (tmp_path / "run.sumocfg").write_text(
        '<configuration><input><net-file value="road.net.xml"/>'
        '<route-files value="r.rou.xml"/></input></configuration>'
    )
    e = parallel_env(scenario=str(tmp_path / "run.sumocfg"), penetration=0.0, episode_length=8.0)
    try:
        e.reset(seed=0)
        seen = set(e._snap.ids)
        for _ in range(50):
            e.step({})
            seen |= set(e._snap.ids)
        assert seen == {f"c{i}" for i in range(6)}
    finally:
        e.close()


SPARSE = dict(scenario="straight", density=30.0, penetration=0.02, episode_length=120.0)


def test_reset_waits_for_the_first_av_and_pettingzoo_accepts_a_sparse_env() -> None:
    """30 veh/km with 2 % AVs: no AV is on the road at t = 0, so reset() lets the simulation run
    until one enters; then PettingZoo's four test functions pass (the AEC wrapper used to
    divide by zero, and performance_benchmark's masked integer actions used to be refused)."""
    from pettingzoo.test import performance_benchmark

    e = parallel_env(**SPARSE)
    try:
        obs, infos = e.reset(seed=1)  # seed 1: the first AV enters at 0.4 s
        assert e.agents and list(obs) == e.agents and e.sim_time > 0.3
    finally:
        e.close()
    parallel_api_test(parallel_env(**SPARSE), num_cycles=40)
    api_test(mixed_traffic.env(**SPARSE), num_cycles=15)
    parallel_seed_test(lambda: parallel_env(**SPARSE), num_cycles=15)
    performance_benchmark(mixed_traffic.env(**SPARSE))


def _grid_sumocfg(tmp_path, begin: float = 5.0, end: float = 100.0, turn: bool = True) -> str:
    """A netgenerate 3x3 grid (100 m blocks) and a .sumocfg whose two flows run from
    ``begin`` to ``end`` [s], turning at a corner or (``turn`` False) straight across."""
    net = tmp_path / "grid.net.xml"
    subprocess.run([binary("netgenerate"), "--grid", "--grid.number", "3", "--grid.length", "100",
                    "-L", "2", "--tls.guess", "-o", str(net)], check=True, capture_output=True)  # fmt: skip
    (tmp_path / "r.rou.xml").write_text(
        f'<routes><flow id="ac" begin="{begin}" end="{end}" period="3" from="A0A1" '
        f'to="{"C1C2" if turn else "A1A2"}"/><flow id="ca" begin="{begin + 1}" end="{end}" '
        f'period="4" from="C2C1" to="{"A1A0" if turn else "C1C0"}"/></routes>'
    )
    cfg = tmp_path / "run.sumocfg"
    cfg.write_text('<configuration><input><net-file value="grid.net.xml"/>'
                   '<route-files value="r.rou.xml"/></input></configuration>')  # fmt: skip
    return str(cfg)


def test_pettingzoo_accepts_a_user_sumocfg_whose_vehicles_depart_later(tmp_path) -> None:
    """A netgenerate grid and a .sumocfg whose flows start at 5 s: reset() waits for the
    first AV, then all four PettingZoo test functions pass."""
    from pettingzoo.test import performance_benchmark

    kw = dict(scenario=_grid_sumocfg(tmp_path), penetration=0.3, episode_length=30.0)
    e = parallel_env(**kw)
    try:
        e.reset(seed=0)
        assert e.agents and e.sim_time > 5.0
    finally:
        e.close()
    parallel_api_test(parallel_env(**kw), num_cycles=30)
    api_test(mixed_traffic.env(**kw), num_cycles=10)
    parallel_seed_test(lambda: parallel_env(**kw), num_cycles=10)
    performance_benchmark(mixed_traffic.env(**kw))


def test_a_fixed_fleet_drives_a_sumocfgs_av_trips_in_turn(tmp_path) -> None:
    """fixed_fleet on a .sumocfg: a pool of agents bounded by how many AV trips overlap
    drives all of them, each agent trip after trip under its own id; PettingZoo's test passes
    (issue 24: a slot pool instead of one agent per trip)."""
    from agents.rules.acc_lc import AccLcPolicy

    grid = _grid_sumocfg(tmp_path, 0.0, 200.0, turn=False)
    kw = dict(scenario=grid, penetration=0.5, episode_length=200.0)
    per_trip = parallel_env(**kw).possible_agents  # one agent per AV trip of the episode
    e = parallel_env(**kw, fixed_fleet=True)
    fleet = list(e.possible_agents)
    assert 0 < len(fleet) < len(per_trip)
    policy, entries = AccLcPolicy(), dict.fromkeys(fleet, 0)
    try:
        obs, _ = e.reset(seed=0)
        while e.agents:
            assert e.agents == fleet
            obs, _, term, _, infos = e.step(policy.actions({a: obs[a] for a in e.agents}))
            assert not any(term.values())
            for a, info in infos.items():
                entries[a] += info["event"] == "entered"
        served = e.flow_diagnostics()
    finally:
        e.close()
    assert max(entries.values()) >= 3, "agents drive trip after trip"
    # every AV trip due was served or still waits; the first ones entered during reset
    assert served["fleet_trips"] >= sum(entries.values()) > len(fleet)
    assert served["fleet_trips"] + served["fleet_unserved"] >= len(per_trip) - 2
    parallel_api_test(parallel_env(**kw, fixed_fleet=True), num_cycles=60)


def test_reset_names_a_wait_that_runs_out() -> None:
    e = parallel_env(**{**SPARSE, "reset_wait": 30.0})
    try:
        with pytest.raises(NoAgentError, match="no AV entered the network within reset_wait=30"):
            e.reset(seed=2)  # seed 2: no AV enters in the whole episode
    finally:
        e.close()


def test_an_episode_without_any_av_is_an_error_or_on_request_all_human() -> None:
    e = parallel_env(**SPARSE)
    try:
        with pytest.raises(NoAgentError, match=r"during the 120.0 s episode.*allow_no_agents"):
            e.reset(seed=2)
        obs, _ = e.reset(seed=2, options={"allow_no_agents": True})
        assert obs == {} and e.agents == []
        e.step({})  # the last step of the episode
        assert e.sim_time == pytest.approx(SPARSE["episode_length"])
        with pytest.raises(RuntimeError, match="call reset"):
            e.step({})
    finally:
        e.close()


def test_a_forbidden_decision_is_replaced_and_reported() -> None:
    e = parallel_env(scenario="straight", density=60.0, penetration=0.3, episode_length=5.0)
    try:
        obs, _ = e.reset(seed=0)
        a = next(a for a in e.agents if not obs[a]["action_mask"][2])  # rightmost lane
        actions = {b: 1 for b in e.agents}  # bare integer decisions: follow
        actions[a] = 2  # right change out of the rightmost lane
        _, _, _, _, infos = e.step(actions)
        assert infos[a].get("decision_replaced") is True
        assert not any(infos[b].get("decision_replaced") for b in e.agents if b != a)
    finally:
        e.close()
