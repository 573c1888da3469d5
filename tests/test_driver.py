"""The decision interval and the residual form (agents.driver) on real SUMO."""

from __future__ import annotations

import numpy as np
import pytest

from agents.driver import Driver, lane_switched, steps_per_decision
from agents.learning.rbpdqn import RBPDQN, LearnerConfig, Policy
from agents.nets.lca import LCAConfig
from agents.policies import stack_obs, to_actions
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
    assert set(gaps) == {steps_per_decision(interval, 0.1) - 1}


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


def test_an_eager_residual_speeds_without_the_governor_and_not_with_it(tmp_path) -> None:
    """u ≈ +1 on every accel row (+0.75 m/s² over ACC-LC) in free flow on straight-4lane."""
    import dataclasses

    from agents.checkpoint import save_checkpoint
    from agents.learning.fleet_search import get_theta, set_theta
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
