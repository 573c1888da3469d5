"""Atomic, validated checkpoints of an :class:`agents.learners.rbpdqn.RBPDQN` learner.

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
from agents.learners.rbpdqn import RBPDQN, LearnerConfig, Policy, build_nets
from agents.learners.variants import make_learner
from agents.nets.lca import LCAConfig
from agents.nets.networks import Actor, Critic
from agents.rules.obs_batch import EXTRA_KEYS
from agents.rules.tuned import teacher_rule
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
    lca, lcfg = _configs(path, data["meta"])
    want = learner.lca_cfg if learner is not None else _requested(lca, z, m)
    if widen and learner is not None and want == replace(lca, ego_fusion=True) != lca:
        data["learner"] = _widen(path, data["learner"], lca, lcfg, learner)
        lca = want
    _check_fits(path, lca, want)
    out = learner if learner is not None else make_learner(lca, lcfg)
    _load_state(path, out.load_state_dict, data["learner"])
    return out, data["meta"]


def load_nets(
    path: str | os.PathLike, z: int | None = None, m: int | None = None
) -> tuple[Actor, Critic, LearnerConfig]:
    """The (actor, critic) of ``path`` in eval mode and its learner config, for inference only:
    no target networks and no optimisers (building Adam costs seconds of torch imports)."""
    return _nets(path, read_checkpoint(path), z, m)


def _nets(
    path: str | os.PathLike, data: dict[str, Any], z: int | None, m: int | None
) -> tuple[Actor, Critic, LearnerConfig]:
    """:func:`load_nets` from the checkpoint's content ``data``."""
    lca, lcfg = _configs(path, data["meta"])
    _check_fits(path, lca, _requested(lca, z, m))
    actor, critic = build_nets(lca, lcfg)

    def fill(sd: dict) -> None:
        actor.load_state_dict(sd["actor"])
        critic.load_state_dict(sd["critic"])

    _load_state(path, fill, data["learner"])
    return actor.eval(), critic.eval(), lcfg


def _configs(path: str | os.PathLike, meta: dict[str, Any]) -> tuple[LCAConfig, LearnerConfig]:
    try:
        return LCAConfig.from_dict(meta["lca"]), LearnerConfig(**meta["learner_cfg"])
    except (KeyError, TypeError) as exc:
        raise ValueError(f"checkpoint {path}: invalid meta ({exc})") from exc


def _requested(lca: LCAConfig, z: int | None, m: int | None) -> LCAConfig:
    """``lca`` with the caller's history and waypoint counts (None keeps the stored one)."""
    return replace(lca, z=lca.z if z is None else z, m=lca.m if m is None else m)


def _check_fits(path: str | os.PathLike, lca: LCAConfig, want: LCAConfig) -> None:
    """ValueError listing every shape and flag where the stored ``lca`` differs from ``want``."""
    if want == lca:
        return
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


def _load_state(path: str | os.PathLike, load: Any, state: dict) -> None:
    try:
        load(state)
    except (KeyError, RuntimeError, ValueError) as exc:
        raise ValueError(
            f"checkpoint {path}: state does not fit the model ({_reason(exc)})"
        ) from exc


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


def with_hold_gate(learner: RBPDQN) -> RBPDQN:
    """``learner`` with a hold gate added, closed (score 0: the same policy), or ``learner``
    itself if it has one (``LearnerConfig.hold_gate``)."""
    if learner.cfg.hold_gate:
        return learner
    out = make_learner(learner.lca_cfg, replace(learner.cfg, hold_gate=True))
    sd = learner.state_dict()
    for net in ("actor", "actor_targ"):  # the gate's zeros, every other tensor as it was
        sd[net] = {**getattr(out, net).state_dict(), **sd[net]}
    out.load_state_dict(sd)
    out.steps = learner.steps
    return out


def load_policy(
    path: str | os.PathLike, z: int | None = None, m: int | None = None, **policy_kw: Any
) -> Policy:
    """Checkpoint → batched inference :class:`Policy` (eval mode); kwargs go to ``Policy``."""
    actor, critic, _, keys = _load_inference(path, z, m)
    return Policy(actor, critic, extra_keys=keys, **policy_kw)


def load_driver(
    path: str | os.PathLike,
    dt: float,
    z: int | None = None,
    m: int | None = None,
    family: str | None = None,
) -> Driver:
    """Checkpoint → its :class:`agents.driver.Driver` (one thread, the checkpoint's form and
    decision interval, correcting its teacher rule as tuned for scenario ``family``) for an env
    stepping ``dt`` [s]."""
    actor, critic, cfg, keys = _load_inference(path, z, m)
    teacher = teacher_rule(cfg.teacher, family, dt)
    return Driver(Policy(actor, critic, threads=1, extra_keys=keys), cfg, dt, teacher)


def _load_inference(
    path: str | os.PathLike, z: int | None, m: int | None
) -> tuple[Actor, Critic, LearnerConfig, tuple[str, ...]]:
    """:func:`load_nets` plus the opt-in observation keys the checkpoint was trained on."""
    data = read_checkpoint(path)
    return (*_nets(path, data, z, m), trained_extra_keys(data["meta"]))


def trained_extra_keys(meta: dict[str, Any]) -> tuple[str, ...]:
    """The opt-in observation keys (``EXTRA_KEYS``) of the env a checkpoint was trained in,
    from its ``env_base`` (``sensors.memory``, ``v2x``); all of them when it has none (older
    checkpoints: the policy then reads every opt-in key the env gives)."""
    base = meta.get("env_base")
    if not isinstance(base, dict):
        return EXTRA_KEYS
    on = {"memory": bool((base.get("sensors") or {}).get("memory")),
          "downstream": bool(base.get("v2x"))}  # fmt: skip
    return tuple(k for k in EXTRA_KEYS if on[k])
