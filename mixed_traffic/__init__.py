"""mixed_traffic: a PettingZoo environment over SUMO for autonomous vehicles in mixed traffic.

Stages, each a folder (docs/architecture.md): ``world`` (SUMO, scenarios, demand) ->
``sensing`` (perception, observation) -> ``env`` (the ParallelEnv) -> ``experiments``
(runner, CLIs); the AUTO agent lives in the top-level ``agents`` package and the report in
``analysis``.

``parallel_env``, ``env`` and ``mixed_traffic_v0`` are imported lazily, so that ``analysis``
(and ``schema``) import without SUMO.
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = ["EnvConfig", "env", "list_scenarios", "mixed_traffic_v0", "parallel_env"]
__version__ = "0.1.0"

_LAZY = {
    "parallel_env": ("mixed_traffic.env.parallel", "parallel_env"),
    "MixedTrafficEnv": ("mixed_traffic.env.parallel", "MixedTrafficEnv"),
    "list_scenarios": ("mixed_traffic.world.registry", "list_scenarios"),
    "EnvConfig": ("mixed_traffic.config", "EnvConfig"),
}


def __getattr__(name: str) -> Any:
    # importlib, not "from mixed_traffic import env": that would re-enter this hook
    if name in ("env", "mixed_traffic_v0"):
        return importlib.import_module(f"mixed_traffic.{name}")  # env: a callable package
    if name in _LAZY:
        module, attr = _LAZY[name]
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'mixed_traffic' has no attribute {name!r}")
