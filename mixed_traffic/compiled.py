"""Compiled kernels: numba's ``njit`` with its on-disk cache, so a machine compiles each kernel
once (later processes, sweep cells and workers load it from ``__pycache__``).

A stage that has a kernel keeps its numpy version as the reference (tests check the two
equal on real SUMO states). The numpy stages run instead when numba is not installed or
``MIXED_TRAFFIC_KERNELS=numpy`` is set when a process starts.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

try:
    import numba
except ImportError:  # the numpy reference stages run
    numba = None

#: The environment variable that selects the numpy stages (``numpy``) over the kernels.
SWITCH = "MIXED_TRAFFIC_KERNELS"


ENABLED = numba is not None and os.environ.get(SWITCH, "numba") != "numpy"
"""Whether the kernels run: numba present and ``SWITCH`` not ``numpy`` when this module was
imported (a process's start; tests set it directly). Read once: a stage asks per call, and
reading the environment cost 3 µs a time, 22 times a step."""


def enabled() -> bool:
    """True when the compiled kernels run (``ENABLED``)."""
    return ENABLED


def njit(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` compiled on first call and cached on disk (no fastmath: results equal numpy's
    bit for bit); ``fn`` itself without numba."""
    if numba is None:
        return fn
    return numba.njit(cache=True, nogil=True)(fn)


def inline(fn: Callable[..., Any]) -> Callable[..., Any]:
    """A kernel's helper, inlined into its callers: a process then loads one compiled kernel
    from the cache, not one per helper (each costs about 0.1 s at a process's first call)."""
    if numba is None:
        return fn
    return numba.njit(inline="always")(fn)


@inline
def minimum(a: float, b: float) -> float:
    """``np.minimum`` of two floats in a kernel: the NaN where either is NaN (Python's ``min``
    drops it), ``b`` on a tie (as numpy: ``minimum(0.0, -0.0)`` is -0.0). (numba caches a
    kernel by its own file: edit this and clear the cache, ``__pycache__`` or
    ``NUMBA_CACHE_DIR``.)"""
    return a if (a < b or a != a) else b


@inline
def maximum(a: float, b: float) -> float:
    """``np.maximum`` of two floats in a kernel: the NaN where either is NaN, ``b`` on a tie."""
    return a if (a > b or a != a) else b


@inline
def clip(x: float, lo: float, hi: float) -> float:
    """``np.clip`` of one float in a kernel: the maximum with ``lo``, then the minimum with
    ``hi`` (``hi`` when ``lo`` > ``hi``); a NaN stays NaN, and ``x`` on a tie
    (``clip(-0.0, 0.0, 1.0)`` is -0.0, as numpy's)."""
    y = lo if x < lo else x
    return hi if y > hi else y
