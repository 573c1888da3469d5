"""What the agents perceive at one step, as arrays over agents (``PerceptionFrame``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mixed_traffic.sensing.neighbours import Neighbours


@dataclass
class PerceptionFrame:
    """What the agents perceive at one step (physical units). A agents, 3 lanes, 2 slots."""

    neighbours: Neighbours
    """Detected neighbours (rows -1 where not detected); distances possibly noisy."""
    vehicles: np.ndarray
    """(A, 3, 2, 6) features ``VEHICLE_FEATURES`` of front/rear vehicles; 0 where missing."""
    ego: np.ndarray
    """(A, 5) features ``EGO_FEATURES`` (GNSS/IMU)."""
    light_state: np.ndarray
    """(A, 3) int8 RED / YELLOW / GREEN of the next signal on each lane, NO_LIGHT if none."""
    light_dist: np.ndarray
    """(A, 3) distance from the front bumper to the stop line [m], +inf where no light."""
    give_way: np.ndarray
    """(A,) bool: the current lane's line is a give-way line (right of way as SUMO rules it,
    ``camera.give_way``), not a signal."""
