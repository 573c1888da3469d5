"""Slow summaries of an AV's own drive: the opt-in observation key ``memory``.

A frame of the history (``SensorConfig.history``, 0.5 s by default) cannot show a stop-and-go
wave, which takes about 30 s to pass on a ring, nor the traffic's mean speed that a damping
controller holds (FollowerStopper's U, the CIRCLES controllers' set speeds). With
``SensorConfig.memory`` each agent carries, from what it perceives itself:

========= =========================================================================
columns   feature (value / constant, then clipped to [-1, 1])
========= =========================================================================
0 .. T-1  own speed, exponential mean over each time constant τ of
          ``SensorConfig.memory_taus`` / 40 m/s
T .. 2T-1 own speed, exponential spread (standard deviation) over each τ / 10 m/s
2T .. 3T-1 leader's speed (the front vehicle in its lane), mean over each τ / 40 m/s
3T .. 4T-1 leader's speed, spread over each τ / 10 m/s
4T .. 4T+2 its last command's decision, one-hot (left, follow, right)
4T+3      its last command's accel_brake in the chosen row [action units]
========= =========================================================================

A new agent starts at its own speed with no spread; without a leader the leader's summaries
hold their last values (as FollowerStopper's memory does). The exponential means move by
step / τ each step: a 40 s mean keeps about 1 / e of what it saw 40 s ago.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from mixed_traffic.config import EnvConfig
from mixed_traffic.sensing.lane_graph import CURRENT

SPEED_SCALE = 40.0
"""Scale of the means [m/s] (the observation's speed scale)."""
SPREAD_SCALE = 10.0
"""Scale of the spreads [m/s]."""
_REL_SPEED, _WIDTH = 1, 4  # columns of ``PerceptionFrame.vehicles`` (lidar.VEHICLE_FEATURES)


def memory_width(config: EnvConfig) -> int:
    """M: columns of the ``memory`` key (4 per time constant, 4 for the last command)."""
    return 4 * len(config.sensors.memory_taus) + 4


def memory_space(config: EnvConfig) -> gym.spaces.Box:
    """``Box(-1, 1, (M,), float32)`` of the key ``memory``."""
    return gym.spaces.Box(-1.0, 1.0, (memory_width(config),), np.float32)


class SlowMemory:
    """The ``memory`` key of every agent slot (vectorised over agents).

    Args:
        config: the env config (``sensors.memory``, ``sensors.memory_taus``, step length).
        n_agents: number of possible agents (slots).
    """

    def __init__(self, config: EnvConfig, n_agents: int) -> None:
        self.on = config.sensors.memory
        taus = np.asarray(config.sensors.memory_taus, np.float64)
        self.alpha = np.minimum(1.0, config.step_length / taus)  # (T,)
        self._mean = np.zeros((n_agents, 2, len(taus)))  # own, leader [m/s]
        self._var = np.zeros((n_agents, 2, len(taus)))  # [m²/s²]
        self._fresh = np.ones(n_agents, bool)
        self._command = np.zeros((n_agents, 4), np.float32)

    def reset(self) -> None:
        """A new episode: every slot starts afresh."""
        self.drop(np.arange(len(self._fresh)))

    def drop(self, slots: np.ndarray) -> None:
        """Forget what ``slots`` remembered (a new trip starts afresh)."""
        slots = np.asarray(slots, np.int64)
        self._fresh[slots] = True
        self._command[slots] = 0.0

    def command(self, slots: np.ndarray, decision: np.ndarray, params: np.ndarray) -> None:
        """Remember the command the agents at ``slots`` (A,) execute this step: ``decision``
        (A,) and ``params`` (A, 3, 2) [action units]."""
        rows = np.arange(len(slots))
        self._command[slots, :3] = np.eye(3, dtype=np.float32)[decision]
        self._command[slots, 3] = params[rows, decision, 1]

    def keys(self, slots: np.ndarray, ego: np.ndarray, vehicles: np.ndarray) -> dict:
        """``{"memory": (A, M)}`` of the agents at ``slots`` (A,) after this step's perceived
        ``ego`` (A, 5) and ``vehicles`` (A, 3, 2, 6) (``PerceptionFrame``); ``{}`` when off."""
        if not self.on:
            return {}
        slots = np.asarray(slots, np.int64)
        v = ego[:, 0]
        lead = vehicles[:, CURRENT, 0, _WIDTH] > 0
        speeds = np.stack([v, v + vehicles[:, CURRENT, 0, _REL_SPEED]], axis=1)  # (A, 2)
        self._update(slots, speeds, lead)
        mean, spread = self._mean[slots], np.sqrt(self._var[slots])
        out = np.concatenate([mean[:, 0] / SPEED_SCALE, spread[:, 0] / SPREAD_SCALE,
                              mean[:, 1] / SPEED_SCALE, spread[:, 1] / SPREAD_SCALE,
                              self._command[slots]], axis=1)  # fmt: skip
        return {"memory": np.clip(out, -1.0, 1.0).astype(np.float32)}

    def _update(self, slots: np.ndarray, speeds: np.ndarray, lead: np.ndarray) -> None:
        """Move the means and variances of ``slots`` one step towards ``speeds`` (A, 2) [m/s]
        (own, leader); the leader's only where one is seen (``lead`` (A,))."""
        fresh = self._fresh[slots]
        mean, var = self._mean[slots], self._var[slots]  # (A, 2, T) copies
        mean[fresh] = speeds[fresh, :1, None]  # a new agent: everything at its own speed
        var[fresh] = 0.0
        seen = np.stack([np.ones_like(lead), lead], axis=1)[..., None]  # (A, 2, 1)
        dev = speeds[..., None] - mean
        a = self.alpha
        mean = np.where(seen, mean + a * dev, mean)
        var = np.where(seen, (1 - a) * (var + a * dev**2), var)  # West's exponential variance
        self._mean[slots], self._var[slots] = mean, var
        self._fresh[slots] = False
