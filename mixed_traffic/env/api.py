"""The env's public interface for policies: what an observation means and how an action moves
the vehicle. ``agents`` (ACC-LC, the safety module, learned policies) import from here and
from ``mixed_traffic.config`` only, never from the env's internals.

- Observation layout and scales (``docs/env.md``): features are divided by these constants;
  ``observation_space`` gives a config's per-agent space (with its opt-in keys).
- Action conversion: normalised ``(steering, accel_brake)`` <-> physical [rad, m/s²].
- Vehicle model: the kinematic bicycle step the env integrates, and the curvature window its
  lane-following feed-forward uses.
- Termination rules a policy must respect: the dead-end distance.
"""

from mixed_traffic.env.action import N_DECISIONS, N_PARAMS, to_accel_brake, to_physical
from mixed_traffic.env.control import CURVATURE_WINDOW, bicycle_frenet_step, bicycle_rollout
from mixed_traffic.env.termination import DEAD_END_DISTANCE
from mixed_traffic.sensing.observation import (
    EGO_SCALE,
    SPEED_SCALE,
    WAYPOINT_SCALE,
    observation_space,
)

__all__ = [
    "CURVATURE_WINDOW",
    "DEAD_END_DISTANCE",
    "EGO_SCALE",
    "N_DECISIONS",
    "N_PARAMS",
    "SPEED_SCALE",
    "WAYPOINT_SCALE",
    "bicycle_frenet_step",
    "bicycle_rollout",
    "observation_space",
    "to_accel_brake",
    "to_physical",
]
