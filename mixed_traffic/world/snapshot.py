"""TrafficSnapshot: every vehicle's state at one step, as a struct of numpy arrays (SI units)."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np


@dataclass(frozen=True)
class Collision:
    """One collision reported by SUMO in the last step."""

    collider: str
    victim: str
    kind: str
    """SUMO's collision type, e.g. ``collision`` or ``frontal``."""
    lane: str


@dataclass
class TrafficSnapshot:
    """State of all N vehicles in the network after a simulation step.

    Angles are radians in the ENU convention (0 = east, counter-clockwise); SUMO's heading
    (degrees, 0 = north, clockwise) is converted in exactly one place, ``sumo_angle_to_rad``.
    Lane indices count from the rightmost lane (0), as SUMO does.
    """

    time: float
    """Simulation time after the step [s]."""
    ids: list[str]
    """(N,) vehicle ids."""
    is_av: np.ndarray
    """(N,) bool, True for AVs (ids ``av_*``)."""
    x: np.ndarray
    """(N,) position of the front bumper centre [m]."""
    y: np.ndarray
    """(N,) [m]."""
    z: np.ndarray
    """(N,) altitude [m]."""
    heading: np.ndarray
    """(N,) heading [rad], ENU."""
    speed: np.ndarray
    """(N,) speed along the lane [m/s]."""
    accel: np.ndarray
    """(N,) acceleration of the last step [m/s^2]."""
    lane: np.ndarray
    """(N,) int32 row in the network's lane table (``HDMap.lane_ids``), -1 if unknown."""
    lane_index: np.ndarray
    """(N,) int16 lane index within the edge, 0 = rightmost."""
    lane_pos: np.ndarray
    """(N,) distance of the front bumper from the lane start [m]."""
    lateral: np.ndarray
    """(N,) lateral offset from the lane centreline, positive = left [m]."""
    length: np.ndarray
    """(N,) vehicle length [m]."""
    width: np.ndarray
    """(N,) vehicle width [m]."""
    edge: np.ndarray
    """(N,) int32 row in the network's edge table (``HDMap.edge_ids``), -1 on junctions."""
    route_index: np.ndarray
    """(N,) int32 index of the current (or last normal) edge within the vehicle's route."""
    route_length: np.ndarray
    """(N,) int32 number of edges in the vehicle's route."""
    fuel: np.ndarray | None = None
    """(N,) fuel consumption in the last step [ml/s], from each vehicle's emission class in
    SUMO's emission models (SUMO converts mass to volume at the fuel's density: 742 g/l petrol,
    836 g/l diesel); None where not read (hand-built snapshots)."""
    departed: list[str] = field(default_factory=list)
    """Vehicles that entered the network in the last step."""
    arrived: list[str] = field(default_factory=list)
    """Vehicles that reached the end of their route in the last step (not those removed by a
    collision, which SUMO also reports as arrived)."""
    collisions: list[Collision] = field(default_factory=list)
    """Collisions of the last step (colliding vehicles are removed by SUMO)."""
    teleports: list[str] = field(default_factory=list)
    """Vehicles that started a teleport in the last step (should stay empty: teleports are off)."""

    @property
    def n(self) -> int:
        return len(self.ids)

    @property
    def left(self) -> list[str]:
        """Vehicles that left the road in the last step, each once: arrived, or removed by a
        collision (a vehicle may be in several)."""
        crashed = (v for c in self.collisions for v in (c.collider, c.victim))
        return list(dict.fromkeys([*self.arrived, *crashed]))

    @property
    def route_progress(self) -> np.ndarray:
        """(N,) fraction of the route's edges completed, in [0, 1]."""
        return self.route_index / np.maximum(self.route_length - 1, 1)

    def index_of(self) -> dict[str, int]:
        """Vehicle id -> row (built once per snapshot; do not mutate the returned dict)."""
        return self._index

    @cached_property
    def _index(self) -> dict[str, int]:
        # several stages look vehicles up by id every step: build the map once per snapshot
        return {vid: i for i, vid in enumerate(self.ids)}


def sumo_angle_to_rad(angle_deg: np.ndarray) -> np.ndarray:
    """SUMO heading (deg, 0 = north, clockwise) -> ENU heading (rad, 0 = east, CCW) in (-pi, pi]."""
    rad = np.deg2rad(90.0 - np.asarray(angle_deg, dtype=np.float64))
    return np.pi - np.mod(np.pi - rad, 2 * np.pi)


def rad_to_sumo_angle(heading: np.ndarray) -> np.ndarray:
    """Inverse of ``sumo_angle_to_rad``, in [0, 360)."""
    return np.mod(90.0 - np.rad2deg(heading), 360.0)
