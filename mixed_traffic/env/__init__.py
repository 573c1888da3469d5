"""The env stage: the PettingZoo ``ParallelEnv`` and what it is made of.

- ``parallel``: ``MixedTrafficEnv``, the step template (action -> control -> SUMO -> perception
  -> termination -> reward -> metrics -> observation), ``parallel_env`` and ``env`` (AEC).
- ``agent_table``: agent ids, slots and their alignment with the snapshot.
- ``checks``: argument checks that name a misuse before any work starts.
- ``action``, ``control``, ``reward``, ``metrics``, ``render``, ``wrappers``.
- ``api``: what policies may use (observation scales, action conversion, vehicle model).

``mixed_traffic.env`` is both this package and, PettingZoo-style, the AEC constructor:
``mixed_traffic.env(scenario=...)`` calls :func:`env`.
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import Any

__all__ = ["MixedTrafficEnv", "NoAgentError", "env", "parallel_env"]


def __getattr__(name: str) -> Any:
    # lazy: policies import ``mixed_traffic.env.api`` without building the whole env stage
    if name in __all__:
        return getattr(importlib.import_module("mixed_traffic.env.parallel"), name)
    raise AttributeError(f"module 'mixed_traffic.env' has no attribute {name!r}")


class _CallableModule(types.ModuleType):
    """Forwards ``mixed_traffic.env(**kwargs)`` to :func:`mixed_traffic.env.parallel.env`."""

    def __call__(self, **kwargs: Any):
        return importlib.import_module("mixed_traffic.env.parallel").env(**kwargs)


sys.modules[__name__].__class__ = _CallableModule
