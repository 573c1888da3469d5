"""Batching between the env's per-agent dicts and batched policies (re-exported by
:mod:`agents.policies`): one observation batch per step in, one action dict per agent out.

It lives below every policy (ACC-LC's :meth:`~agents.rules.acc_lc.AccLcPolicy.actions`
uses it too), so no policy module needs :mod:`agents.policies`, which builds policies by name.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

OBS_KEYS = (
    "ego",
    "lanes",
    "vehicles",
    "lights",
    "limits",
    "signals",
    "give_way",
    "node_mask",
    "action_mask",
)


EXTRA_KEYS = ("memory", "downstream")
"""The env's opt-in keys (``SensorConfig.memory``, ``EnvConfig.v2x``), in the order they
join the ``extra`` vector."""
EXTRA = "extra"
"""(A, X) the opt-in keys present, flattened and concatenated (absent without any)."""


def stack_obs(
    obs: Mapping[str, Mapping[str, np.ndarray]], agents: list[str]
) -> dict[str, np.ndarray]:
    """{agent: {key: x}} -> {key: (A, ...)} in the order of ``agents``, plus ``EXTRA`` where
    the observations hold opt-in keys."""
    first = obs[agents[0]] if agents else {}
    keys = (*OBS_KEYS, *(k for k in EXTRA_KEYS if k in first))
    return with_extra({k: np.stack([obs[a][k] for a in agents]) for k in keys})


def with_extra(
    batch: Mapping[str, np.ndarray], keys: Sequence[str] = EXTRA_KEYS
) -> dict[str, np.ndarray]:
    """``batch`` {key: (A, ...)} with its ``EXTRA`` vector: the opt-in ``keys`` it holds,
    flattened and concatenated in ``EXTRA_KEYS`` order (none without them)."""
    out = dict(batch)
    parts = [np.reshape(out[k], (len(out[k]), -1)) for k in EXTRA_KEYS if k in out and k in keys]
    if parts and EXTRA not in out:
        out[EXTRA] = np.concatenate(parts, axis=1).astype(np.float32)
    return out


def for_policy(batch: Mapping[str, np.ndarray], keys: Sequence[str]) -> dict[str, np.ndarray]:
    """``batch`` with the ``EXTRA`` vector a policy trained on the opt-in ``keys`` reads: built
    from those keys alone (the env may give more), none for ``keys=()``; a batch that holds
    ``EXTRA`` but no opt-in key (e.g. replay samples) keeps it."""
    if not keys:
        return {k: v for k, v in batch.items() if k != EXTRA}
    if not any(k in batch for k in EXTRA_KEYS):
        return dict(batch)
    return with_extra({k: v for k, v in batch.items() if k != EXTRA}, keys)


def extra_width(space_shapes: Mapping[str, tuple[int, ...]]) -> int:
    """X: the width of ``EXTRA`` for observations of the given per-key shapes (0: none)."""
    return sum(int(np.prod(space_shapes[k])) for k in EXTRA_KEYS if k in space_shapes)


def to_actions(
    agents: list[str], decision: np.ndarray, params: np.ndarray
) -> dict[str, dict[str, Any]]:
    """Batched policy output -> the env's per-agent action dicts."""
    params = np.asarray(params, dtype=np.float32)
    return {a: {"decision": int(decision[i]), "params": params[i]} for i, a in enumerate(agents)}
