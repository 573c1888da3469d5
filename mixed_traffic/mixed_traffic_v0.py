"""The versioned entry point, in the PettingZoo manner (``pistonball_v6``)::

    from mixed_traffic import mixed_traffic_v0

    env = mixed_traffic_v0.parallel_env(scenario="straight", density=120, penetration=0.5)
    aec = mixed_traffic_v0.env(scenario="straight")

The version changes when the observation, action, reward or termination of the env change in
a way that makes old results incomparable.
"""

from mixed_traffic.env.parallel import MixedTrafficEnv, env, parallel_env

raw_env = MixedTrafficEnv

__all__ = ["env", "parallel_env", "raw_env"]
