"""Atomic, validated checkpoints of an :class:`agents.learning.rbpdqn.RBPDQN` learner.

File content (``torch.save`` of a plain dict, loadable with ``weights_only=True``):
``{"format": FORMAT, "learner": learner.state_dict(), "meta": {...}}`` where ``meta`` holds at
least ``lca`` (LCAConfig fields incl. z, m), ``learner_cfg`` and ``obs_shapes``; callers add
their own keys (command, git revision, env steps, ...).
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

from agents.driver import Driver
from agents.learning.rbpdqn import RBPDQN, LearnerConfig, Policy
from agents.learning.variants import make_learner
from agents.nets.lca import LCAConfig
from mixed_traffic.provenance import atomic_write

FORMAT = "mixed_traffic.rbpdqn/1"
_REQUIRED = ("format", "learner", "meta")


def save_checkpoint(
    path: str | os.PathLike, learner: RBPDQN, meta: dict[str, Any] | None = None
) -> Path:
    """Write atomically: temp file in the same directory, fsync, then ``os.replace``.

    A crash mid-write leaves the previous checkpoint intact (no torn files).
    """
    path = Path(path)
    payload = checkpoint_payload(learner, meta)
    atomic_write(path, lambda f: torch.save(payload, f))
    return path


def checkpoint_payload(learner: RBPDQN, meta: dict[str, Any] | None = None) -> dict[str, Any]:
    """What a checkpoint file holds: ``learner``'s state and ``meta`` plus its shapes."""
    full_meta = dict(meta or {})
    full_meta.update(
        lca=learner.lca_cfg.to_dict(),
        learner_cfg=learner.cfg.to_dict(),
        obs_shapes={k: list(v) for k, v in learner.lca_cfg.obs_shapes().items()},
    )
    return {"format": FORMAT, "learner": learner.state_dict(), "meta": full_meta}


def read_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """Load and structurally validate; ValueError naming the file on any problem."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"checkpoint {path}: file not found")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # truncated zip, garbage bytes, unsafe pickle, ...
        raise ValueError(
            f"checkpoint {path}: corrupt or unreadable ({type(exc).__name__}: {_reason(exc)})"
        ) from exc
    if not isinstance(data, dict) or any(k not in data for k in _REQUIRED):
        keys = sorted(data) if isinstance(data, dict) else type(data).__name__
        raise ValueError(
            f"checkpoint {path}: not an RBP-DQN checkpoint (expected keys {_REQUIRED}, got {keys})"
        )
    if data["format"] != FORMAT:
        raise ValueError(f"checkpoint {path}: format {data['format']!r}, expected {FORMAT!r}")
    bad = [k for k in ("learner", "meta") if not isinstance(data[k], dict)]
    if bad:
        raise ValueError(f"checkpoint {path}: {bad[0]!r} is a {type(data[bad[0]]).__name__}, "
                         "expected a dict")  # fmt: skip
    return data


def _reason(exc: Exception) -> str:
    """One line of what ``torch.load`` or ``load_state_dict`` found wrong: the weights-only
    refusal spans several lines of advice around the reason (e.g. "Unsupported operand 110"),
    a shape mismatch one line per tensor."""
    text = str(exc)
    if "WeightsUnpickler error:" in text:
        text = text.split("WeightsUnpickler error:", 1)[1].strip().split("\n\n")[0]
        text = text.split(". ")[0]
    lines = [" ".join(line.split()) for line in text.splitlines() if line.strip()]
    more = f" (+{len(lines) - 2} more)" if len(lines) > 2 else ""  # e.g. size mismatches
    return " ".join(lines[:2]) + more if lines else "empty or truncated file"


def load_checkpoint(
    path: str | os.PathLike,
    z: int | None = None,
    m: int | None = None,
    learner: RBPDQN | None = None,
    widen: bool = False,
) -> tuple[RBPDQN, dict[str, Any]]:
    """Rebuild (or fill ``learner``) from ``path`` → (learner, meta).

    ``z``/``m`` are the observation config the caller will feed; a mismatch with the stored
    shapes raises ValueError listing both. With ``learner`` given, its LCA config must match,
    except that ``widen`` lets paper-form weights (``ego_fusion=False``) fill an ego-fusion
    learner (:func:`_widen`).
    """
    data = read_checkpoint(path)
    meta = data["meta"]
    try:
        lca = LCAConfig.from_dict(meta["lca"])
        lcfg = LearnerConfig(**meta["learner_cfg"])
    except (KeyError, TypeError) as exc:
        raise ValueError(f"checkpoint {path}: invalid meta ({exc})") from exc
    want = LCAConfig(
        **{**lca.to_dict(), "z": lca.z if z is None else z, "m": lca.m if m is None else m}
    )
    if learner is not None:
        want = learner.lca_cfg
        if widen and not lca.ego_fusion and want == replace(lca, ego_fusion=True):
            data["learner"] = _widen(path, data["learner"], lca, lcfg, learner)
            lca = want
    if want != lca:
        shapes = [
            f"{k}: checkpoint {tuple(a)} vs requested {tuple(want.obs_shapes()[k])}"
            for k, a in lca.obs_shapes().items()
            if tuple(a) != tuple(want.obs_shapes()[k])
        ]
        flags = [
            f"{k}: checkpoint {v} vs requested {getattr(want, k)}"
            for k, v in lca.to_dict().items()
            if k not in ("z", "m", "d") and v != getattr(want, k)
        ]
        raise ValueError(
            f"checkpoint {path}: observation/model config mismatch "
            f"(checkpoint z={lca.z}, m={lca.m}, d={lca.d}; requested z={want.z}, m={want.m}, "
            f"d={want.d})" + "".join(f"; {x}" for x in shapes + flags)
        )
    out = learner if learner is not None else make_learner(lca, lcfg)
    try:
        out.load_state_dict(data["learner"])
    except (KeyError, RuntimeError, ValueError) as exc:
        raise ValueError(
            f"checkpoint {path}: state does not fit the model ({_reason(exc)})"
        ) from exc
    return out, meta


def _widen(
    path: str | os.PathLike, sd: dict, lca: LCAConfig, lcfg: LearnerConfig, learner: RBPDQN
) -> dict:
    """Paper-form learner state → the state of ``learner`` (ego fusion) computing the same
    function: the fusion layers' new h_A input columns start at zero, their Adam first moments
    too, and their second moments at the row's mean over the old columns (zero would make the
    first updates of the new weights several times the learning rate)."""
    old = RBPDQN(lca, lcfg)
    try:
        old.load_state_dict(sd)
    except (KeyError, RuntimeError, ValueError) as exc:
        raise ValueError(f"checkpoint {path}: state does not fit the model ({exc})") from exc
    sd, like = old.state_dict(), learner.state_dict()
    for net in ("actor", "critic", "actor_targ", "critic_targ"):
        sd[net] = {k: _zero_pad(v, like[net][k].shape) for k, v in sd[net].items()}
    for opt, net in (("actor_opt", learner.actor), ("critic_opt", learner.critic)):
        shapes = [p.shape for p in net.parameters()]  # the optimiser's state is keyed by index
        for i, state in sd[opt]["state"].items():
            sd[opt]["state"][i] = {
                k: _zero_pad(v, shapes[i], row_mean=k == "exp_avg_sq") if v.ndim else v
                for k, v in state.items()
            }
    return sd


def _zero_pad(t: torch.Tensor, shape: torch.Size, row_mean: bool = False) -> torch.Tensor:
    """``t`` in the leading corner of zeros of ``shape`` (``t`` itself if the shape is equal);
    ``row_mean`` fills the new columns with the mean of each row of ``t`` instead."""
    if t.shape == shape:
        return t
    fill = t.mean(dim=-1, keepdim=True) if row_mean else t.new_zeros(())
    out = fill.expand(shape).clone()
    out[tuple(slice(0, n) for n in t.shape)] = t
    return out


def load_policy(
    path: str | os.PathLike, z: int | None = None, m: int | None = None, **policy_kw: Any
) -> Policy:
    """Checkpoint → batched inference :class:`Policy` (eval mode); kwargs go to ``Policy``."""
    return _policy(load_checkpoint(path, z=z, m=m)[0], **policy_kw)


def load_driver(
    path: str | os.PathLike, dt: float, z: int | None = None, m: int | None = None
) -> Driver:
    """Checkpoint → its :class:`agents.driver.Driver` (one thread, the checkpoint's form and
    decision interval) for an env stepping ``dt`` [s]."""
    learner, _ = load_checkpoint(path, z=z, m=m)
    return Driver(_policy(learner, threads=1), learner.cfg, dt)


def _policy(learner: RBPDQN, **policy_kw: Any) -> Policy:
    return Policy(learner.actor.eval(), learner.critic.eval(), **policy_kw)
