"""mixed_traffic: a PettingZoo environment over SUMO for autonomous vehicles in mixed traffic.

``parallel_env`` and ``env`` are imported lazily so that ``analysis`` (and ``schema``) work
without SUMO.
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = ["EnvConfig", "env", "list_scenarios", "parallel_env"]
__version__ = "0.1.0"


def __getattr__(name: str) -> Any:
    # importlib, not "from mixed_traffic import env": that would re-enter this hook
    if name in ("parallel_env", "env", "MixedTrafficEnv"):
        module = importlib.import_module("mixed_traffic.env")
        globals().update(parallel_env=module.parallel_env, MixedTrafficEnv=module.MixedTrafficEnv)
        # the submodule is callable like the env() function it contains (see env.py's end)
        return module if name == "env" else globals()[name]
    if name == "list_scenarios":
        return importlib.import_module("mixed_traffic.scenario").list_scenarios
    if name == "EnvConfig":
        return importlib.import_module("mixed_traffic.config").EnvConfig
    raise AttributeError(f"module 'mixed_traffic' has no attribute {name!r}")
