"""Action space, validation errors, physical mapping and the flat wrapper."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
import pytest
from gymnasium import spaces
from pettingzoo.utils.env import ParallelEnv

from mixed_traffic.config import VehicleConfig
from mixed_traffic.env.action import action_space, stack_actions, to_physical
from mixed_traffic.wrappers import FlatActionWrapper, dict_to_flat, flat_action_space, flat_to_dict


def act(decision: int = 1, params=None) -> dict:
    return {
        "decision": decision,
        "params": np.zeros((3, 2), np.float32) if params is None else params,
    }


def test_space_shape() -> None:
    space = action_space(seed=0)
    assert space["decision"].n == 3
    assert space["params"].shape == (3, 2) and space["params"].dtype == np.float32
    assert space.contains(space.sample())


def test_stack_orders_by_agents() -> None:
    p = np.arange(6, dtype=np.float32).reshape(3, 2) / 10
    d, params = stack_actions({"b": act(2, p), "a": act(0)}, ["a", "b"])
    np.testing.assert_array_equal(d, [0, 2])
    np.testing.assert_allclose(params[1], p)


def test_missing_agent_is_named() -> None:
    with pytest.raises(ValueError, match="no action for live agent 'av_3'"):
        stack_actions({"av_1": act()}, ["av_1", "av_3"])


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_param_names_agent_and_field(bad) -> None:
    p = np.zeros((3, 2))
    p[2, 1] = bad
    with pytest.raises(
        ValueError, match=r"'av_0'.*'params'\[2, 1\].*right_change, accel_brake.*not finite"
    ):
        stack_actions({"av_0": act(1, p)}, ["av_0"])


def test_nan_decision() -> None:
    with pytest.raises(ValueError, match=r"'av_0'.*'decision' is not finite"):
        stack_actions({"av_0": act(float("nan"))}, ["av_0"])


def test_out_of_range_names_value_and_bounds() -> None:
    p = np.zeros((3, 2))
    p[0, 0] = 1.5
    with pytest.raises(
        ValueError, match=r"'av_0'.*'params'\[0, 0\]=1.5.*steering.*allowed \[-1.0, 1.0\]"
    ):
        stack_actions({"av_0": act(0, p)}, ["av_0"])
    with pytest.raises(ValueError, match="'decision'=3 is outside the space"):
        stack_actions({"av_0": act(3)}, ["av_0"])
    with pytest.raises(ValueError, match=r"shape \(6,\)"):
        stack_actions({"av_0": act(0, np.zeros(6))}, ["av_0"])
    with pytest.raises(ValueError, match="must be a dict"):
        stack_actions({"av_0": np.zeros(9)}, ["av_0"])


def test_actions_for_finished_agents() -> None:
    with pytest.raises(ValueError, match=r"not live: \['av_9'\]"):
        stack_actions({"av_0": act(), "av_9": act()}, ["av_0"])
    d, _ = stack_actions({"av_0": act(), "av_9": act()}, ["av_0"], strict_agents=False)
    assert d.tolist() == [1]


def test_to_physical_mapping() -> None:
    veh = VehicleConfig()
    params = np.zeros((3, 3, 2))
    params[0, 0] = (1.0, 1.0)  # agent 0 executes left row: full left, full throttle
    params[1, 1] = (-0.5, -1.0)  # agent 1 executes follow row: half right, full brake
    params[2, 2] = (0.25, 0.5)
    params[2, 0] = (1.0, 1.0)  # not executed
    steer, accel = to_physical(np.array([0, 1, 2]), params, veh)
    np.testing.assert_allclose(np.rad2deg(steer), [60.0, -30.0, 15.0])
    np.testing.assert_allclose(accel, [3.0, -6.0, 1.5])


# ---------------------------------------------------------------------- flat view
def test_flat_to_dict() -> None:
    flat = np.array([0.1, 0.9, -0.3, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
    out = flat_to_dict(flat)
    assert out["decision"] == 1
    np.testing.assert_allclose(out["params"], [[0.1, 0.2], [0.3, 0.4], [0.5, 0.6]], rtol=1e-6)
    assert action_space().contains(out)
    back = flat_to_dict(dict_to_flat(out))
    assert back["decision"] == 1
    np.testing.assert_allclose(back["params"], out["params"])
    assert flat_to_dict(np.zeros(9))["decision"] == 0  # ties -> lowest index
    with pytest.raises(ValueError, match="shape"):
        flat_to_dict(np.zeros(8), "av_1")
    with pytest.raises(ValueError, match="non-finite"):
        flat_to_dict(np.full(9, np.nan), "av_1")


class _Recorder(ParallelEnv):
    """Minimal ParallelEnv with the parameterized action, recording what it receives."""

    metadata: ClassVar[dict] = {"name": "recorder_v0"}

    def __init__(self) -> None:
        self.possible_agents = ["av_0", "av_1"]
        self.agents = list(self.possible_agents)
        self.received: dict = {}

    def observation_space(self, agent):
        return spaces.Box(-1, 1, (1,))

    def action_space(self, agent):
        return action_space()

    def reset(self, seed=None, options=None):
        self.agents = list(self.possible_agents)
        return {a: np.zeros(1, np.float32) for a in self.agents}, {a: {} for a in self.agents}

    def step(self, actions):
        self.received = actions
        stack_actions(actions, self.agents, action_space())
        z = {a: 0.0 for a in self.agents}
        f = {a: False for a in self.agents}
        return (
            {a: np.zeros(1, np.float32) for a in self.agents},
            z,
            f,
            f,
            {a: {} for a in self.agents},
        )


def test_flat_wrapper_maps_actions() -> None:
    env = FlatActionWrapper(_Recorder())
    env.reset(seed=0)
    assert env.action_space("av_0") == flat_action_space()
    flat = {a: env.action_space(a).sample() for a in env.agents}
    flat["av_1"][:3] = (-1.0, -1.0, 1.0)
    env.step(flat)
    got = env.unwrapped.received
    assert got["av_1"]["decision"] == 2
    np.testing.assert_allclose(got["av_0"]["params"], flat["av_0"][3:].reshape(3, 2))
