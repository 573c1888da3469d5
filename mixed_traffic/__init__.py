"""mixed_traffic: a PettingZoo environment over SUMO for autonomous vehicles in mixed traffic.

``parallel_env`` and ``env`` are imported lazily so that ``analysis`` (and ``schema``) work
without SUMO.
"""

from __future__ import annotations

from typing import Any

__all__ = ["EnvConfig", "env", "list_scenarios", "parallel_env"]
__version__ = "0.1.0"


def __getattr__(name: str) -> Any:
    if name in ("parallel_env", "env", "MixedTrafficEnv"):
        from mixed_traffic import env as _env_module

        return getattr(_env_module, name)
    if name == "list_scenarios":
        from mixed_traffic.scenario import list_scenarios

        return list_scenarios
    if name == "EnvConfig":
        from mixed_traffic.config import EnvConfig

        return EnvConfig
    raise AttributeError(f"module 'mixed_traffic' has no attribute {name!r}")
