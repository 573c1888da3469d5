"""Gap, time to collision and angles: the small kinematics the sensors and rewards share."""

from __future__ import annotations

import numpy as np


def bumper_gap(distance: np.ndarray, len_ego: np.ndarray, len_other: np.ndarray) -> np.ndarray:
    """Bumper gap as in the paper's TTC: |front-bumper distance| - (len_ego + len_other) / 2 [m].

    Shapes broadcast; an infinite distance gives an infinite gap.
    """
    return np.abs(distance) - 0.5 * (np.asarray(len_ego) + np.asarray(len_other))


def ttc(gap: np.ndarray, closing_speed: np.ndarray) -> np.ndarray:
    """Time to collision [s] = gap / closing speed where closing (> 0), else +inf.

    Args:
        gap: bumper gap [m] (``bumper_gap``); a gap <= 0 with closing speed > 0 gives 0.
        closing_speed: v_follower - v_leader [m/s].
    """
    gap = np.asarray(gap, dtype=np.float64)
    v = np.asarray(closing_speed, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(v > 0, np.maximum(gap, 0.0) / np.where(v > 0, v, 1.0), np.inf)
    return np.where(np.isnan(t), np.inf, t)


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angle wrapped to (-pi, pi] [rad]."""
    return np.pi - np.mod(np.pi - np.asarray(a), 2 * np.pi)
