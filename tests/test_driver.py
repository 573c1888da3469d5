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
