"""The paper's parameterized action (§IV-D): a lane decision plus (steering, accel_brake) per decision.

Per agent::

    Dict(decision=Discrete(3), params=Box(-1, 1, (3, 2), float32))

* ``decision``: 0 = left lane change, 1 = lane following, 2 = right lane change.
* ``params[p] = (steering, accel_brake)`` for decision ``p``; only the row ``params[decision]`` is
  executed (the others are the actor's proposals for the other decisions, kept for the critic).

Sign conventions (the one place they are defined; control and tests follow them):

* **steering > 0 steers LEFT** (counter-clockwise, the ENU/right-hand convention also used by the
  snapshot's headings and SUMO's lateral offsets, positive = left). The paper (§III-A) uses the
  opposite sign (negative = left); a policy trained with the paper's sign maps with
  ``steering = -deg_paper / 60``. ``steering = ±1`` is ``±VehicleConfig.max_steer_deg`` (60°),
  linear in between.
* **accel_brake > 0 is throttle**, ``a = accel_brake · max_accel`` (+1 → +3 m/s²);
  **accel_brake < 0 is brake**, ``a = accel_brake · max_decel`` (−1 → −6 m/s²); 0 is coasting at
  constant speed (no rolling resistance is modelled). Speeds never go below 0 (no reversing).

Bad input: ``stack_actions`` raises ``ValueError`` naming the agent and field for a missing
action, a non-finite value, a value outside the space, or an action for an agent that is not
live. The last is a deliberate choice: PettingZoo's ``parallel_api_test`` only ever sends actions
for ``env.agents``, and a stale action for a finished agent is almost always a bookkeeping bug in
the caller, so it is reported rather than silently ignored (``strict_agents=False`` ignores them).

A bare integer is a decision with neutral params (steering 0, accel_brake 0): PettingZoo's tools
sample an index from the observation's ``action_mask``. A decision the mask forbids is replaced
by follow if that is allowed, else by the first allowed one (``allowed_decisions``); the env
reports the replacement in ``infos[agent]["decision_replaced"]``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from gymnasium import spaces

from mixed_traffic import compiled
from mixed_traffic.config import VehicleConfig
from mixed_traffic.env import control_kernel

LEFT, FOLLOW, RIGHT = 0, 1, 2
DECISIONS = ("left_change", "follow", "right_change")
N_DECISIONS = 3
N_PARAMS = 2  # (steering, accel_brake)


class ParameterizedActionSpace(spaces.Dict):
    """``Dict(decision, params)`` whose ``sample(mask=...)`` also takes the observation's
    ``action_mask`` (3,) directly, the PettingZoo convention, and then samples only allowed
    decisions (params stay uniform)."""

    def sample(self, mask: Any = None, probability: Any = None) -> dict[str, Any]:
        if mask is not None and not isinstance(mask, Mapping):
            mask = {"decision": np.asarray(mask, dtype=np.int8), "params": None}
        return super().sample(mask=mask, probability=probability)


def action_space(seed: int | None = None) -> spaces.Dict:
    """The per-agent parameterized action space (see the module docstring)."""
    space = ParameterizedActionSpace(
        {
            "decision": spaces.Discrete(N_DECISIONS),
            "params": spaces.Box(-1.0, 1.0, (N_DECISIONS, N_PARAMS), np.float32),
        }
    )
    if seed is not None:
        space.seed(seed)
    return space


def _decision_value(agent: str, value: Any) -> int:
    arr = np.asarray(value)
    if arr.size != 1:
        raise ValueError(
            f"action of agent {agent!r}: 'decision' must be one integer, got {value!r}"
        )
    v = arr.reshape(()).item()
    if isinstance(v, float):
        if not np.isfinite(v):
            raise ValueError(f"action of agent {agent!r}: 'decision' is not finite ({v!r})")
        if v != int(v):
            raise ValueError(f"action of agent {agent!r}: 'decision'={v!r} is not an integer")
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f"action of agent {agent!r}: 'decision'={value!r} is not an integer")
    v = int(v)
    if not 0 <= v < N_DECISIONS:
        raise ValueError(
            f"action of agent {agent!r}: 'decision'={v} is outside the space; allowed 0, 1, 2 "
            f"({', '.join(DECISIONS)})"
        )
    return v


def _params_value(agent: str, value: Any, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"action of agent {agent!r}: 'params' is not numeric: {e}") from e
    if arr.shape != (N_DECISIONS, N_PARAMS):
        raise ValueError(
            f"action of agent {agent!r}: 'params' has shape {arr.shape}, expected "
            f"({N_DECISIONS}, {N_PARAMS}) = (decision, (steering, accel_brake))"
        )
    bad = ~np.isfinite(arr)
    if bad.any():
        p, k = np.argwhere(bad)[0]
        raise ValueError(
            f"action of agent {agent!r}: 'params'[{p}, {k}] ({DECISIONS[p]}, "
            f"{('steering', 'accel_brake')[k]}) is not finite ({float(arr[p, k])})"
        )
    out = (arr < low - 1e-6) | (arr > high + 1e-6)
    if out.any():
        p, k = np.argwhere(out)[0]
        raise ValueError(
            f"action of agent {agent!r}: 'params'[{p}, {k}]={float(arr[p, k])} "
            f"({DECISIONS[p]}, {('steering', 'accel_brake')[k]}) is outside the space; "
            f"allowed [{low[p, k]}, {high[p, k]}]"
        )
    return np.clip(arr, low, high)


def stack_actions(
    actions: Mapping[str, Any],
    agents: Sequence[str],
    space: spaces.Dict | None = None,
    *,
    strict_agents: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Validate per-agent dict actions and stack them in ``agents`` order.

    Args:
        actions: agent id -> ``{"decision": int, "params": (3, 2)}``.
        agents: the live agents, in the order of the output rows (A of them).
        space: the action space (default ``action_space()``), for the bounds.
        strict_agents: raise on actions for agents that are not live (default); False ignores them.

    Returns:
        ``decision`` (A,) int64 and ``params`` (A, 3, 2) float64 within the bounds.

    Raises:
        ValueError: naming the agent (and field/value/bounds) for a missing action, a
            non-finite value, a value outside the space, or an action for a non-live agent.
    """
    space = space if space is not None else action_space()
    box = space["params"]
    low, high = box.low.astype(np.float64), box.high.astype(np.float64)
    live = set(agents)
    extra = [a for a in actions if a not in live]
    if extra and strict_agents:
        raise ValueError(
            f"actions given for agents that are not live: {sorted(extra)}; live agents are "
            f"{list(agents)} (finished agents must not receive actions)"
        )
    fast = _stack_fast(actions, agents, low, high)
    if fast is not None:
        return fast
    # slow path: validates agent by agent and raises the error of the first bad one
    n = len(agents)
    decision = np.empty(n, dtype=np.int64)
    params = np.empty((n, N_DECISIONS, N_PARAMS), dtype=np.float64)
    for i, agent in enumerate(agents):
        if agent not in actions:
            raise ValueError(f"no action for live agent {agent!r}; every live agent needs one")
        act = actions[agent]
        if _is_integer(act):  # a bare decision (PettingZoo's masked sampling): neutral params
            act = {"decision": act, "params": np.zeros((N_DECISIONS, N_PARAMS))}
        if not isinstance(act, Mapping) or "decision" not in act or "params" not in act:
            raise ValueError(
                f"action of agent {agent!r} must be a dict with keys 'decision' and 'params' "
                f"(use wrappers.FlatActionWrapper for flat vectors), got {type(act).__name__}"
            )
        decision[i] = _decision_value(agent, act["decision"])
        params[i] = _params_value(agent, act["params"], low, high)
    return decision, params


def no_actions() -> tuple[np.ndarray, np.ndarray]:
    """The stacked actions of no agent (a step nobody acts in)."""
    return np.zeros(0, np.int64), np.zeros((0, N_DECISIONS, N_PARAMS))


def stack_batch(
    decision: Any, params: Any, agents: Sequence[str], space: spaces.Dict | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`stack_actions` for actions already stacked in ``agents`` order: ``decision``
    (A,) integers and ``params`` (A, 3, 2); the same arrays, and the same errors naming the
    agent (a shape or dtype that is not that names the arrays)."""
    space = space if space is not None else action_space()
    n = len(agents)
    dec, par = np.asarray(decision), np.asarray(params, dtype=np.float64)
    if dec.shape != (n,) or par.shape != (n, N_DECISIONS, N_PARAMS) or dec.dtype.kind not in "iu":
        raise ValueError(f"step_batch takes decision ({n},) integers and params ({n}, 3, 2) for "
                         f"the {n} live agents in env.agents order, got decision {dec.shape} "
                         f"{dec.dtype} and params {par.shape}")  # fmt: skip
    low, high = (b.astype(np.float64) for b in (space["params"].low, space["params"].high))
    in_range = ((dec >= 0) & (dec < N_DECISIONS)).all() and np.isfinite(par).all()
    if in_range and (par >= low - 1e-6).all() and (par <= high + 1e-6).all():
        return dec.astype(np.int64), np.clip(par, low, high)
    # the per-agent path names the first bad agent
    return stack_actions({a: {"decision": int(d), "params": p} for a, d, p in zip(agents, dec, par)},
                         agents, space)  # fmt: skip


_INT_TYPES = (int, np.int64, np.int32, np.int16, np.int8, np.uint64, np.uint32, np.uint16, np.uint8)


def _is_integer(value: Any) -> bool:
    return type(value) in _INT_TYPES


def allowed_decisions(decision: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The executed decisions (A,) under the action masks (A, 3): a forbidden decision is
    replaced by follow if that is allowed, else by the first allowed one; and which (A,) bool
    were replaced."""
    if compiled.enabled():
        m = mask if isinstance(mask, np.ndarray) and mask.dtype == np.int8 else None
        m = np.asarray(mask, bool).view(np.int8) if m is None else m
        dec = np.ascontiguousarray(decision, np.int64)
        return control_kernel.allowed(dec, np.ascontiguousarray(m))
    mask = np.asarray(mask, bool)
    forbidden = ~mask[np.arange(len(decision)), decision]
    fallback = np.where(mask[:, 1], 1, np.argmax(mask, axis=1))
    return np.where(forbidden, fallback, decision), forbidden


def _stack_fast(
    actions: Mapping[str, Any], agents: Sequence[str], low: np.ndarray, high: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """``stack_actions`` for the common case, vectorised over agents: every action a dict with
    an integer decision in range and finite in-bounds (3, 2) params. ``None`` when anything is
    off, so the per-agent path produces the error (identical results otherwise)."""
    try:
        acts = [actions[a] for a in agents]
        if not all(type(x) is dict and "decision" in x and "params" in x for x in acts):
            return None
        dec = [x["decision"] for x in acts]
        if not all(type(d) in _INT_TYPES for d in dec):  # excludes bool, floats, arrays
            return None
        decision = np.array(dec, dtype=np.int64)
        params = np.array([x["params"] for x in acts], dtype=np.float64)
    except (KeyError, TypeError, ValueError, OverflowError):
        return None
    n = len(agents)
    if n == 0:
        return decision.reshape(0), np.empty((0, N_DECISIONS, N_PARAMS))
    if params.shape != (n, N_DECISIONS, N_PARAMS):
        return None
    if ((decision < 0) | (decision >= N_DECISIONS)).any():
        return None
    if not np.isfinite(params).all() or (params < low - 1e-6).any() or (params > high + 1e-6).any():
        return None
    return decision, np.clip(params, low, high)


def chosen_params(decision: np.ndarray, params: np.ndarray) -> np.ndarray:
    """(A, 2) the executed row ``params[a, decision[a]]`` = (steering, accel_brake)."""
    return params[np.arange(len(decision)), decision]


def to_physical(
    decision: np.ndarray, params: np.ndarray, vehicle: VehicleConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Executed normalised command -> physical command.

    Args:
        decision: (A,) int in {0, 1, 2}.
        params: (A, 3, 2) normalised (steering, accel_brake) in [-1, 1].
        vehicle: limits (``max_steer_deg``, ``max_accel``, ``max_decel``).

    Returns:
        ``steer`` (A,) front-wheel angle [rad], positive = left, ``±1 -> ±max_steer_deg``;
        ``accel`` (A,) [m/s²], ``accel_brake·max_accel`` if > 0 else ``accel_brake·max_decel``.
    """
    if compiled.enabled():
        return control_kernel.physical(
            np.ascontiguousarray(decision, np.int64), np.ascontiguousarray(params, np.float64),
            float(np.deg2rad(vehicle.max_steer_deg)), float(vehicle.max_accel),
            float(vehicle.max_decel),
        )  # fmt: skip
    row = chosen_params(np.asarray(decision, dtype=np.int64), np.asarray(params, np.float64))
    steer = row[:, 0] * np.deg2rad(vehicle.max_steer_deg)
    ab = row[:, 1]
    accel = np.where(ab > 0, ab * vehicle.max_accel, ab * vehicle.max_decel)
    return steer, accel


def to_accel_brake(accel: np.ndarray, vehicle: VehicleConfig) -> np.ndarray:
    """Inverse of ``to_physical``'s acceleration: (A,) [m/s²] -> accel_brake in [-1, 1]."""
    accel = np.asarray(accel, np.float64)
    ab = np.where(accel > 0, accel / vehicle.max_accel, accel / vehicle.max_decel)
    return np.clip(ab, -1.0, 1.0)
