"""Fleet-return search: evolution strategies on the actor's accel outputs (issue 22).

Why: a shared policy's gain is a *fleet* effect. When half the AVs drive more eagerly the
others gain as much as they do (docs/results.md, "the credit problem"), so a per-agent critic
cannot see it. Here the shared actor is judged by what the whole traffic does in an episode.

Method (Salimans et al. 2017, antithetic ES with Adam): θ are either the accel_brake rows of
the actor's last layer (target ``accel``: 3 × (d + 1) numbers; steering's 0.3° bound makes its
fleet effect smaller than the noise) or the hold gate (target ``gate``: d + 2 numbers, see
``agents.nets.networks.Actor``). Per iteration, ``pairs`` noise vectors ε are drawn; θ + σε
and θ − σε drive the AVs of one sampled episode config each (same config and seed for both:
common random numbers). An episode's score is ln(mean speed of all vehicles in the
measurement segment) minus ``unsafe_penalty`` per collision or AV terminal event; the pair's
difference d is divided by the iteration's RMS of d, clipped, and the gradient estimate
Σ dε / (n σ) moves θ through Adam. All of this is pure numpy;
:mod:`mixed_traffic.experiments.fleet` runs the episodes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from agents.nets.networks import N_PARAMS
from mixed_traffic.schema import TERMINAL_REASONS

ACCEL = 1
"""Index of accel_brake among a decision's parameters."""
TARGETS = ("accel", "gate")
"""What the search moves: the actor's accel_brake outputs or its hold gate."""


@dataclass(frozen=True)
class SearchConfig:
    """Settings of the evolution-strategies step."""

    sigma: float = 0.3
    """Noise std on θ [weight units]. The hidden features have |h| ≈ 0.7, so this moves u by
    about 0.3 (0.08 accel_brake units, 0.2-0.5 m/s² after the residual bound)."""
    lr: float = 0.05
    """Adam step size on θ [weight units per iteration]."""
    pairs: int = 4
    """Antithetic pairs (2 episodes each) per iteration."""
    clip: float = 3.0
    """Pair differences are clipped at this many RMS [-]."""
    unsafe_penalty: float = 1.0
    """Score lost per collision or AV terminal event [ln(m/s) units: 1 = the mean speed / e]."""
    spread_weight: float = 0.0
    """Score lost per unit of the speed spread of all vehicles, speed std / mean speed
    [ln(m/s) units]; 0 scores speed alone. Stop-and-go waves cost fuel and comfort that the
    mean speed does not show."""

    def __post_init__(self) -> None:
        for name in ("sigma", "lr", "clip", "unsafe_penalty"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name}={value!r} must be a positive finite number")
        if not (math.isfinite(self.spread_weight) and self.spread_weight >= 0):
            raise ValueError(f"spread_weight={self.spread_weight!r} must be finite and >= 0")
        if self.pairs < 1:
            raise ValueError(f"pairs={self.pairs!r} must be at least 1")


def accel_rows(actor: torch.nn.Module) -> list[int]:
    """Output indices of the actor's last layer that are accel_brake (one per decision)."""
    out = actor.head[-1].out_features
    return list(range(ACCEL, out, N_PARAMS))


def _searched(actor: torch.nn.Module, target: str) -> tuple[torch.nn.Linear, list[int]]:
    """(layer, its output rows) that ``target`` searches."""
    if target not in TARGETS:
        raise ValueError(f"target={target!r}: choose from {TARGETS}")
    if target == "gate":
        if actor.gate is None:
            raise ValueError("the actor has no hold gate (LearnerConfig.hold_gate=False)")
        return actor.gate, [0]
    return actor.head[-1], accel_rows(actor)


def get_theta(actor: torch.nn.Module, target: str = "accel") -> np.ndarray:
    """θ (rows·(d + 1),) float64: the searched rows' weights then their biases."""
    layer, rows = _searched(actor, target)
    w = layer.weight.detach()[rows].double().numpy().ravel()
    b = layer.bias.detach()[rows].double().numpy()
    return np.concatenate([w, b])


def set_theta(actor: torch.nn.Module, theta: np.ndarray, target: str = "accel") -> None:
    """Write θ (as from :func:`get_theta`) into the actor."""
    layer, rows = _searched(actor, target)
    n_w = len(rows) * layer.in_features
    if theta.shape != (n_w + len(rows),) or not np.isfinite(theta).all():
        raise ValueError(f"theta must be {n_w + len(rows)} finite numbers, got {theta.shape}")
    with torch.no_grad():
        w = torch.as_tensor(theta[:n_w], dtype=layer.weight.dtype).view(len(rows), -1)
        layer.weight[rows] = w
        layer.bias[rows] = torch.as_tensor(theta[n_w:], dtype=layer.bias.dtype)


def unsafe_events(metrics: dict[str, Any]) -> int:
    """Collisions plus AV terminal events of other kinds (a collision's terminal is the same
    event)."""
    others = sum(metrics.get(f"terminal_{r}") or 0 for r in TERMINAL_REASONS if r != "collision")
    return int((metrics.get("collisions") or 0) + others)


def episode_score(metrics: dict[str, Any], penalty: float, spread_weight: float = 0.0) -> float:
    """ln(mean speed of all vehicles [m/s]) − ``penalty`` per :func:`unsafe_events` −
    ``spread_weight`` × speed std / mean speed; −inf when the episode measured no speed."""
    speed = metrics.get("mean_speed")
    if speed is None or not speed > 0:
        return -math.inf
    spread = (metrics.get("speed_std") or 0.0) / speed
    return math.log(speed) - penalty * unsafe_events(metrics) - spread_weight * spread


def normalised(d: np.ndarray, clip: float) -> np.ndarray:
    """Pair differences (n,) divided by their RMS and clipped to ±``clip`` (all zeros stay 0)."""
    rms = float(np.sqrt(np.mean(d**2))) if len(d) else 0.0
    return np.zeros_like(d) if rms == 0 else np.clip(d / rms, -clip, clip)


class Adam:
    """Adam ascent on a flat parameter vector; its state is plain lists (JSON-able)."""

    def __init__(self, dim: int, lr: float, state: dict[str, Any] | None = None) -> None:
        self.lr = lr
        state = state or {"t": 0, "m": [0.0] * dim, "v": [0.0] * dim}
        self.t, self.m, self.v = int(state["t"]), np.array(state["m"]), np.array(state["v"])
        if self.m.shape != (dim,) or self.v.shape != (dim,):
            raise ValueError(f"Adam state has {self.m.shape} moments for {dim} parameters")

    def step(self, theta: np.ndarray, grad: np.ndarray) -> np.ndarray:
        """θ moved *up* ``grad``."""
        b1, b2 = 0.9, 0.999
        self.t += 1
        self.m = b1 * self.m + (1 - b1) * grad
        self.v = b2 * self.v + (1 - b2) * grad**2
        m_hat, v_hat = self.m / (1 - b1**self.t), self.v / (1 - b2**self.t)
        return theta + self.lr * m_hat / (np.sqrt(v_hat) + 1e-8)

    def state(self) -> dict[str, Any]:
        return {"t": self.t, "m": self.m.tolist(), "v": self.v.tolist()}


def es_gradient(eps: np.ndarray, d: np.ndarray, sigma: float, clip: float) -> np.ndarray:
    """Antithetic estimate of ∇ E[score]: eps (n, dim), d (n,) = score(θ+σε) − score(θ−σε).
    Pairs with a non-finite d (a failed episode) are left out."""
    ok = np.isfinite(d)
    if not ok.any():
        return np.zeros(eps.shape[1])
    return (normalised(d[ok], clip) @ eps[ok]) / (2 * ok.sum() * sigma)
