"""Responsibility-sensitive safety (RSS, Shalev-Shwartz et al. 2017), longitudinal rule.

The highest acceleration that keeps an RSS-safe distance behind a leader: held for the
response time and followed by braking at the ego's sure deceleration, the ego still stops
``min_gap`` behind where the leader stops at its hardest braking. The safety module checks
learned actions with it, and AUTO's governor (``LearnerConfig.rss_governor``) bounds its
residual correction by it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from agents.rules import acc_lc_kernel
from agents.rules.acc_lc_config import AccLcConfig
from agents.rules.acc_lc_longitudinal import leader_inputs
from mixed_traffic import compiled


@dataclass(frozen=True)
class RssConfig:
    """The RSS rule's assumptions."""

    response: float = 0.5
    """Time the ego holds its acceleration before it brakes [s] (the decision interval)."""
    ego_decel: float = 5.0
    """Deceleration the ego is sure to reach after the response time [m/s²] (below the AV's
    6 m/s²)."""
    lead_decel: float = 6.0
    """Hardest braking assumed of a leader [m/s²] (human drivers brake at 2 m/s²
    comfortably; SUMO's 9 m/s² emergency braking is a collision's last resort)."""
    min_gap: float = 2.0
    """Bumper gap kept after both have stopped [m]."""

    def __post_init__(self) -> None:
        for name in ("response", "ego_decel", "lead_decel"):
            if not getattr(self, name) > 0:
                raise ValueError(f"RssConfig.{name}={getattr(self, name)} must be > 0")
        if not self.min_gap >= 0:
            raise ValueError(f"RssConfig.min_gap={self.min_gap} must be >= 0")


def rss_accel(v: np.ndarray, gap: np.ndarray, v_lead: np.ndarray, c: RssConfig) -> np.ndarray:
    """Highest RSS-safe acceleration [m/s²], any shape: ``v`` ego speed, ``gap`` bumper gap
    [m], ``v_lead`` leader speed [m/s]; -inf where even braking now is not enough."""
    rho, b = c.response, c.ego_decel
    # room: gap + leader's stopping distance - min gap >= (v + x) rho / 2 + x^2 / (2 b), with
    # x = v + a rho the speed after the response; the largest such x, then a
    room = gap - c.min_gap + np.maximum(v_lead, 0.0) ** 2 / (2 * c.lead_decel)
    disc = rho**2 / 4 + 2 * (room - v * rho / 2) / b
    with np.errstate(invalid="ignore"):
        x = b * (-rho / 2 + np.sqrt(disc))
    return np.where(disc >= 0, (np.maximum(x, 0.0) - v) / rho, -np.inf)


def rss_caps(f: Mapping[str, np.ndarray], acc: AccLcConfig, c: RssConfig) -> np.ndarray:
    """(A, 3) highest RSS-safe acceleration [m/s²] per lane column (left, current, right;
    the decision index) behind the leaders ACC-LC sees when driving there (every history
    frame; the virtual vehicle at a lane's end is a stopped leader); inf = none. Compiled
    (``acc_lc_kernel.rss_caps``) unless ``compiled.enabled()`` is off."""
    if compiled.enabled() and len(f["v"]):
        keys = ("v", "d", "exists", "wid", "h_dist", "h_len", "h_lat", "h_rel", "h_wid")
        return acc_lc_kernel.rss_caps(
            *(f[k] for k in keys), acc.lane_width_min, acc.signal_min, acc.yield_decel,
            acc.hv_s0, c.response, c.response**2 / 4, c.ego_decel, 2 * c.lead_decel, c.min_gap,
        )  # fmt: skip
    return _rss_caps_reference(f, acc, c)


def _rss_caps_reference(f: Mapping[str, np.ndarray], acc: AccLcConfig, c: RssConfig) -> np.ndarray:
    """The numpy reference of :func:`rss_caps`."""
    v = f["v"][:, None]
    caps = []
    for lane in range(3):
        gap, closing, _, leader = leader_inputs(f, acc, lane, 1, f["d"], None)
        caps.append(np.where(leader, rss_accel(v, gap, v - closing, c), np.inf).min(axis=1))
    return np.stack(caps, axis=1)
