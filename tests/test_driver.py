"""The decision interval and the residual form (agents.driver) on real SUMO."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.driver import Driver, held_accel, lane_switched, steps_per_decision, track_leader
from agents.learners.rbpdqn import RBPDQN, LearnerConfig, Policy
from agents.nets.lca import LCAConfig
from agents.nets.networks import LEAD_SPREAD
from agents.policies import make_policy, stack_obs, to_actions
from mixed_traffic.config import EnvConfig
from mixed_traffic.env import parallel_env
from mixed_traffic.env.api import EGO_SCALE


def test_steps_per_decision_rounds_to_whole_steps() -> None:
    assert steps_per_decision(0.5, 0.1) == 5
    assert steps_per_decision(0.5, 0.2) == 2  # 2.5 -> 2 (round half to even)
    assert steps_per_decision(0.5, 1.0) == 1  # never less than one step
    assert steps_per_decision(0.1, 0.1) == 1


def test_lane_switch_is_a_jump_of_the_offset() -> None:
    ego = np.zeros((3, 5, 5), np.float32)
    ego[:, :, 2] = 1.0  # observed frames
    ego[0, -2:, 4] = np.array([1.7, -1.7]) / EGO_SCALE[4]  # crossed into the left lane
    ego[1, -2:, 4] = np.array([0.5, 0.7]) / EGO_SCALE[4]  # drifting
    ego[2, -2:, 4] = np.array([1.7, -1.7]) / EGO_SCALE[4]
    ego[2, -2, 2] = 0.0  # previous frame unobserved (just entered)
    assert lane_switched(ego).tolist() == [True, False, False]


@pytest.mark.parametrize("interval", [0.1, 0.5])
def test_zero_residual_drives_as_acc_lc_and_decides_every_interval(interval: float) -> None:
    """An untrained residual network (u = 0, Q = 0) executes exactly ACC-LC's parameters and
    decisions, and each agent decides when it enters and then every k steps."""
    cfg = LearnerConfig(residual=True, decision_interval=interval, teacher_bonus=0.05)
    learner = RBPDQN(LCAConfig(z=5, m=10), cfg)
    driver = Driver(Policy(learner.actor, learner.critic, threads=1), cfg, 0.1)
    env = parallel_env(scenario="merge", density=120, penetration=0.5, episode_length=20, seed=3)
    obs, _ = env.reset(seed=3)
    since: dict[str, int] = {}
    gaps, changes = [], 0
    try:
        for _ in range(199):
            agents = list(env.agents)
            if agents:
                cmd = driver.act(stack_obs(obs, agents), agents)
                np.testing.assert_array_equal(cmd.params, cmd.teacher_params)
                np.testing.assert_array_equal(cmd.decision, cmd.teacher_decision)
                changes += int((cmd.decision != 1).sum())
                for a, due in zip(agents, cmd.due.tolist()):
                    if due and a in since:
                        gaps.append(since[a])
                    since[a] = 0 if due else since.get(a, 0) + 1
            obs, *_ = env.step(to_actions(agents, cmd.decision, cmd.params) if agents else {})
    finally:
        env.close()
    assert changes > 0  # the merge makes ACC-LC change lanes
    assert driver.hold_share == 0.0  # no gate: never held
    assert set(gaps) == {steps_per_decision(interval, 0.1) - 1}


@pytest.mark.parametrize("hold", [1, 3])
def test_exploration_noise_is_held_for_its_decisions(hold: int) -> None:
    """An untrained residual network (u = 0) explores with u = its noise: each agent keeps one
    draw for ``hold`` decisions, and agents draw apart."""
    cfg = LearnerConfig(residual=True, decision_interval=0.1)
    learner = RBPDQN(LCAConfig(z=5, m=10), cfg)
    policy = Policy(learner.actor, learner.critic, noise_std=0.3, epsilon=0.0, threads=1)
    driver = Driver(policy, cfg, 0.1, noise_hold=hold)
    env = parallel_env(scenario="straight-3lane", density=60, penetration=0.5, episode_length=3,
                       seed=1)  # fmt: skip
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=1)
    us: dict[str, list[np.ndarray]] = {}
    try:
        while env.agents:
            agents = list(env.agents)
            cmd = driver.act(stack_obs(obs, agents), agents, "explore", rng)
            for a, u in zip(agents, cmd.u):
                us.setdefault(a, []).append(u.copy())
            obs, *_ = env.step(to_actions(agents, cmd.decision, cmd.params))
    finally:
        env.close()
    runs = [u for u in us.values() if len(u) >= 6]
    assert len(runs) >= 2
    for u in runs:  # a new draw exactly every ``hold`` decisions
        changed = [not np.array_equal(a, b) for a, b in zip(u, u[1:])]
        assert changed == [(i + 1) % hold == 0 for i in range(len(changed))]
    assert not np.array_equal(runs[0][0], runs[1][0])
    with pytest.raises(ValueError, match="noise_hold=0 must be >= 1"):
        Driver(policy, cfg, 0.1, noise_hold=0)


def _set_speed_ring(u: float | None, seed: int = 0) -> dict:
    """One 300 s episode of the 230 m ring with one AV whose set-speed parameter is ``u``
    (``None``: all human); its metrics, and per step the driver's check of the form."""
    from agents.rules.acc_lc_longitudinal import to_ab

    cfg = EnvConfig(scenario="ring", ring_vehicles=22, ring_length=(230.0,), penetration=1 / 22,
                    episode_length=300.0, seed=seed)  # fmt: skip
    env = parallel_env(config=cfg, sumo_drives_avs=u is None)
    lc = LearnerConfig(residual=True, set_speed=True)
    learner = RBPDQN(LCAConfig(), lc)
    with torch.no_grad():  # the follow row's set-speed output: tanh(bias) = u
        learner.actor.head[2].bias.view(3, 2)[1, 0] = float(
            np.arctanh(np.clip(u or 0.0, -0.999, 0.999))
        )
    driver = Driver(Policy(learner.actor, learner.critic, threads=1), lc, 0.1)
    obs, _ = env.reset(seed=seed)
    bound = 0
    try:
        while env.sim_time < 299.95:
            agents = list(env.agents)
            if u is None or not agents:
                obs, *_ = env.step({})
                continue
            cmd = driver.act(stack_obs(obs, agents), agents)
            ref = np.array([driver._ref[a][0] for a in agents])
            v = driver.plan.features["v"]
            track = to_ab(
                lc.hold_gain * (ref + lc.set_speed_span * (1 + cmd.u[:, 1, 0]) - v),
                driver.teacher.c,
            )
            follow = np.minimum(cmd.teacher_params[:, 1, 1], track)
            seen = driver.plan.features["present"][:, 1, 0]
            np.testing.assert_allclose(cmd.params[seen, 1, 1], follow[seen], atol=1e-6)
            bound += int((track[seen] < cmd.teacher_params[seen, 1, 1]).sum())
            obs, *_ = env.step(to_actions(agents, cmd.decision, cmd.params))
        return {**env.episode_metrics(), "bound": bound}
    finally:
        env.close()


def test_the_set_speed_form_reaches_follower_stopper_like_damping() -> None:
    """Issue 43 item 3: the follow row's parameter sets a speed; at u = -1 (hold the leader's
    40 s mean) one AV damps the ring's waves to under half the all-human speed spread and
    drives faster; the tracking binds only where it is below ACC-LC's acceleration."""
    human, held = _set_speed_ring(None), _set_speed_ring(-1.0)
    assert held["bound"] > 100  # the set speed did drive
    assert held["speed_std"] < 0.5 * human["speed_std"]
    assert held["mean_speed"] > human["mean_speed"]


def test_the_governor_caps_only_the_correction_that_lifts_the_acceleration() -> None:
    cfg = LearnerConfig(residual=True, speed_governor=True, accel_delta=0.25)
    driver = Driver(None, cfg, 0.1)
    t_par = np.zeros((3, 3, 2), np.float32)
    t_par[:, :, 1] = [[0.2, 0.2, 0.2], [0.5, 0.5, 0.5], [0.2, 0.2, 0.2]]
    u = np.zeros((3, 3, 2), np.float32)
    u[:2, :, 1], u[2, :, 1] = 1.0, -1.0
    out = driver._execute(u, t_par, cap=np.full((3, 3), 0.3))
    np.testing.assert_allclose(out[0, :, 1], 0.3)  # 0.45 capped at the governor's 0.3
    np.testing.assert_allclose(out[1, :, 1], 0.5)  # ACC-LC's own 0.5 is above the cap: kept
    np.testing.assert_allclose(out[2, :, 1], -0.05)  # braking corrections are free


def test_the_hold_law_tracks_the_leaders_mean_speed_and_passes_hard_braking() -> None:
    """Pure: the reference starts at the ego's speed, moves by alpha towards the leader's and
    stays without a leader, and so does the leader's variance about it; a held AV accelerates at gain (ref − v) but never above ACC-LC's
    a + brake, and drives ACC-LC's a without a leader."""
    v = np.array([3.0, 3.0, 5.0, 2.0])
    ref, var = track_leader(np.array([np.nan, 4.0, 4.0, 4.0]), np.ones(4), v,
                            np.array([5.0, 2.0, 9.0, 1.0]), np.array([True, True, True, False]),
                            alpha=0.25)  # fmt: skip
    np.testing.assert_allclose(ref, [3.5, 3.5, 5.25, 4.0])
    # the variance about the new reference: a new agent starts at 0; no leader: unchanged
    np.testing.assert_allclose(
        var, [0.25 * 1.5**2, 1 + 0.25 * (1.5**2 - 1), 1 + 0.25 * (3.75**2 - 1), 1]
    )
    a = np.array([1.0, -1.0, -3.0, 0.7])  # ACC-LC's [m/s²]
    out = held_accel(a, v, ref, np.array([True, True, True, False]), gain=0.5, brake=1.5)
    # 0.25 (tracking); 0.25 ≤ −1 + 1.5; −3 + 1.5 (braking beyond 1.5 passes); no leader: a
    np.testing.assert_allclose(out, [0.25, 0.25, -1.5, 0.7])


def test_held_rows_replace_the_follow_row_and_stay_under_the_governor() -> None:
    """``held`` replaces the follow row's accel_brake where it is not NaN; other rows and
    other agents keep the residual; the governor's cap still bounds a held row."""
    cfg = LearnerConfig(residual=True, hold_gate=True, accel_delta=0.25)
    driver = Driver(None, cfg, 0.1)
    t_par = np.zeros((3, 3, 2), np.float32)
    t_par[:, :, 1] = 0.2
    u = np.full((3, 3, 2), 0.4, np.float32)
    held = np.array([0.5, -0.6, np.nan])
    out = driver._execute(u, t_par, cap=np.ones((3, 3)), held=held)
    np.testing.assert_allclose(out[:, 1, 1], [0.5, -0.6, 0.3], atol=1e-6)
    np.testing.assert_allclose(out[:, [0, 2], 1], 0.3, atol=1e-6)
    capped = driver._execute(u, t_par, cap=np.full((3, 3), 0.1), held=held)
    np.testing.assert_allclose(capped[:, 1, 1], [0.2, -0.6, 0.2], atol=1e-6)  # ACC-LC's 0.2


def test_a_closed_gate_is_the_same_policy_and_is_not_trained(tmp_path) -> None:
    """with_hold_gate adds a gate that changes nothing until it is set, survives a checkpoint
    round trip and stays out of the actor's optimiser; the fused path scores it as the
    reference does."""
    import torch

    from agents.bench_inference import random_obs
    from agents.checkpoint import load_checkpoint, save_checkpoint, with_hold_gate
    from agents.training.fleet_search import get_theta, set_theta

    lca = LCAConfig(z=5, m=10)
    learner = RBPDQN(lca, LearnerConfig(residual=True))
    theta = get_theta(learner.actor)
    set_theta(learner.actor, theta + 0.1)
    gated = with_hold_gate(learner)
    assert gated.cfg.hold_gate and learner.actor.gate is None
    obs = random_obs(9, lca, np.random.default_rng(0))
    before = Policy(learner.actor, learner.critic).choose(obs, explore=False)
    after = Policy(gated.actor, gated.critic).choose(obs, explore=False)
    np.testing.assert_array_equal(after.params, before.params)
    assert not after.hold.any() and not before.hold.any()
    gate = set(gated.actor.gate.parameters())
    assert not gate.intersection(p for g in gated.actor_opt.param_groups for p in g["params"])
    g = get_theta(gated.actor, "gate")
    assert not g.any()
    t = {k: torch.from_numpy(v) for k, v in obs.items()}
    g = np.append(np.linspace(-1, 1, len(g) - 1), 0.0)
    set_theta(gated.actor, g, "gate")
    with torch.no_grad():
        g[-1] = -float(gated.actor.hold_score(t).median())  # open for some agents only
    set_theta(gated.actor, g, "gate")
    g_spread = g[-2]
    loaded, _ = load_checkpoint(save_checkpoint(tmp_path / "g.pt", gated))
    np.testing.assert_allclose(get_theta(loaded.actor, "gate"), g, atol=1e-6)
    fused = Policy(loaded.actor, loaded.critic).q_and_params(t)[2]
    with torch.no_grad():
        ref = loaded.actor.hold_score(t)
    torch.testing.assert_close(fused, ref, atol=1e-5, rtol=1e-4)
    assert 0 < int((ref > 0).sum()) < 9
    # the leader's speed spread is the gate's last input: a positive weight opens it
    t[LEAD_SPREAD] = torch.linspace(0.0, 2.0, 9)
    before = loaded.actor.hold_score(t)
    g[-2] = 1.0
    set_theta(loaded.actor, g, "gate")
    policy = Policy(loaded.actor, loaded.critic)
    fused = policy.q_and_params(t)[2]
    with torch.no_grad():
        ref = loaded.actor.hold_score(t)
    torch.testing.assert_close(fused, ref, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(
        ref - before, t[LEAD_SPREAD] * (1.0 - g_spread), atol=1e-5, rtol=1e-4
    )
    chosen = policy.choose({**obs, LEAD_SPREAD: t[LEAD_SPREAD].numpy()}, explore=False)
    np.testing.assert_array_equal(chosen.hold, (ref > 0).numpy())
    with pytest.raises(ValueError, match="no hold gate"):
        get_theta(learner.actor, "gate")


def test_an_eager_residual_speeds_without_the_governor_and_not_with_it(tmp_path) -> None:
    """u ≈ +1 on every accel row (+0.75 m/s² over ACC-LC) in free flow on straight-4lane."""
    import dataclasses

    from agents.checkpoint import save_checkpoint
    from agents.training.fleet_search import get_theta, set_theta
    from mixed_traffic.config import EnvConfig
    from mixed_traffic.experiments.runner import run_episode

    sensors = EnvConfig().sensors
    learner = RBPDQN(LCAConfig(z=sensors.history, m=sensors.waypoints),
                     LearnerConfig(residual=True, decision_interval=0.5, teacher_bonus=0.02))  # fmt: skip
    theta = get_theta(learner.actor)
    theta[-3:] = 3.0
    set_theta(learner.actor, theta)
    config = EnvConfig(scenario="straight-4lane", density=60.0, penetration=0.5, seed=3,
                       episode_length=90.0)  # fmt: skip
    speeding = {}
    for governor in (False, True):
        learner.cfg = dataclasses.replace(learner.cfg, speed_governor=governor)
        path = save_checkpoint(tmp_path / f"{governor}.pt", learner)
        m = run_episode(config, "auto-raw", 30.0, checkpoint=path)["metrics"]
        speeding[governor] = m["terminal_speed_limit"]
        assert m["collisions"] == 0
    assert speeding[False] > 0 and speeding[True] == 0


@pytest.fixture(scope="module")
def open_gate(tmp_path_factory) -> Path:
    """The shipped AUTO with its hold gate forced open (bias only: it holds in every state)."""
    from agents.checkpoint import load_checkpoint, save_checkpoint, with_hold_gate
    from agents.policies import SHIPPED_CHECKPOINT
    from agents.training.fleet_search import get_theta, set_theta

    learner, meta = load_checkpoint(SHIPPED_CHECKPOINT)
    gated = with_hold_gate(learner)
    g = get_theta(gated.actor, "gate")
    g[-1] = 1.0
    set_theta(gated.actor, g, "gate")
    return save_checkpoint(tmp_path_factory.mktemp("gate") / "open.pt", gated, meta)


def test_one_held_av_halves_the_rings_speed_spread(open_gate: Path) -> None:
    """One held AV on the 260 m ring (22 vehicles) at least halves the all-human speed std
    (Stern et al. 2018), and it holds the whole time."""
    from mixed_traffic.config import EnvConfig
    from mixed_traffic.experiments.runner import run_episode

    config = EnvConfig(scenario="ring", density=85.0, penetration=0.05, seed=0,
                       episode_length=150.0)  # fmt: skip
    human = run_episode(config, "idm", 60.0)["metrics"]
    held = run_episode(config, "auto", 60.0, checkpoint=open_gate)
    assert held["diagnostics"]["hold_share"] == 100.0
    assert held["metrics"]["collisions"] == 0
    assert held["metrics"]["speed_std"] <= 0.5 * human["speed_std"]


def test_held_avs_do_not_ratchet_the_flow_down_in_rain(open_gate: Path) -> None:
    """Half the vehicles held on ring-270m in rain keep at least 85 % of ACC-LC's mean speed
    (the dead band of a hold of their own speed kept a third: a braked AV never sped up)."""
    from mixed_traffic.config import EnvConfig
    from mixed_traffic.experiments.runner import run_episode

    config = EnvConfig(scenario="ring-270m", density=85.0, penetration=0.5, seed=0,
                       weather="rain", episode_length=150.0)  # fmt: skip
    acc = run_episode(config, "acc-lc", 60.0)["metrics"]
    held = run_episode(config, "auto", 60.0, checkpoint=open_gate)["metrics"]
    assert held["collisions"] == 0
    assert held["mean_speed"] >= 0.85 * acc["mean_speed"]


def test_auto_mean_holds_the_mean_of_autos_parameters(tmp_path, monkeypatch) -> None:
    """``auto-mean`` (issue 43): AUTO's decisions with its continuous parameters replaced by
    their mean over the reference states; the mean is AUTO's own over those episodes' decisions,
    computed once per checkpoint and cached."""
    from mixed_traffic.experiments import runner

    monkeypatch.setenv("MIXED_TRAFFIC_CACHE", str(tmp_path))
    short = (
        EnvConfig(scenario="straight", density=120.0, penetration=0.5, episode_length=3.0, seed=1),
        EnvConfig(scenario="merge", penetration=0.5, episode_length=3.0),
    )  # its own density
    monkeypatch.setattr(runner, "REFERENCE_STATES", short)
    u = runner.reference_u(None)
    runs = [runner.run_episode(c, "auto", 0.0)["diagnostics"] for c in short]
    n = np.array([r["u_decisions"] for r in runs], float)
    np.testing.assert_allclose(u.ravel(), n @ np.array([r["u_mean"] for r in runs]) / n.sum(),
                               atol=1e-6)  # fmt: skip
    own = runs[0]
    assert (
        own["u_decisions"] > 0 and max(own["u_std"]) > 0
    )  # the shipped u varies by state and len(list((tmp_path / "auto_mean").glob("*.json"))) == 1
    record = runner.run_episode(replace(short[0], seed=2), "auto-mean", 0.0)
    assert record["status"] == "ok" and record["cell"]["policy"] == "auto-mean"
    # the driver executes the fixed u at every decision, whatever its network says
    policy = make_policy("auto-mean")
    policy.driver.fixed_u = u
    env = parallel_env(config=replace(short[0], seed=2))
    try:
        obs, _ = env.reset(seed=2)
        for _ in range(10):
            agents = list(env.agents)
            cmd = policy.driver.act(stack_obs(obs, agents), agents)
            np.testing.assert_allclose(cmd.u, np.broadcast_to(u, cmd.u.shape), atol=1e-6)
            obs, *_ = env.step(to_actions(agents, cmd.decision, cmd.params))
    finally:
        env.close()
    assert not np.allclose(policy.driver.u_mean, u)  # the network's own u differed


def test_the_shipped_auto_ring_reads_its_memory_and_holds() -> None:
    """``auto-ring`` (RBP-DQN on the ring family, set-speed form, the ``memory`` key): the runner
    switches its key on, and on a ring it holds its leader's mean (u = -1 on the set speed)."""
    from mixed_traffic.experiments.runner import run_episode

    cfg = EnvConfig(scenario="ring", ring_vehicles=22, ring_length=(210.0,), penetration=1 / 22,
                    episode_length=20.0, seed=0)  # fmt: skip
    record = run_episode(cfg, "auto-ring", 0.0)
    assert record["status"] == "ok" and record["config"]["sensors"]["memory"]
    assert record["checkpoint"].endswith("auto_ring.pt")
    u = np.array(record["diagnostics"]["u_mean"]).reshape(3, 2)
    assert u[1, 0] < -0.9  # the follow row's set speed: hold


@pytest.mark.parametrize("family", ["straight", "merge"])
def test_a_zero_residual_on_the_tuned_rule_drives_as_acc_lc_tuned(tmp_path, family: str) -> None:
    """With teacher acc-lc-tuned, u = 0 executes the family's tuned ACC-LC (not the default),
    loaded from a checkpoint through make_policy, as an evaluation builds it."""
    from agents.checkpoint import save_checkpoint

    sensors = EnvConfig().sensors
    cfg = LearnerConfig(
        residual=True, decision_interval=0.5, teacher_bonus=0.02, teacher="acc-lc-tuned"
    )
    path = save_checkpoint(tmp_path / "tuned.pt", RBPDQN(LCAConfig(z=sensors.history,
                                                                  m=sensors.waypoints), cfg))  # fmt: skip
    auto = make_policy("auto-raw", checkpoint=path, family=family)
    tuned, default = (make_policy(n, family=family) for n in ("acc-lc-tuned", "acc-lc"))
    assert auto.driver.teacher.c == tuned.c != default.c
    env = parallel_env(scenario=family, density=120, penetration=0.5, episode_length=8, seed=2)
    obs, _ = env.reset(seed=2)
    acted = 0
    try:
        while env.agents:
            agents = list(env.agents)
            batch = stack_obs(obs, agents)
            got, want = auto.act(batch, agents), tuned.act(batch, agents)
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_allclose(got[1], want[1], atol=1e-6)
            acted += len(agents)
            obs, *_ = env.step(to_actions(agents, *got))
    finally:
        env.close()
    assert acted > 100
