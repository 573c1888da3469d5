"""LiDAR: the features of the detected front and rear vehicles on each lane."""

from __future__ import annotations

import numpy as np

from mixed_traffic import compiled
from mixed_traffic.sensing import sensing_kernel
from mixed_traffic.sensing.geometry import wrap_angle
from mixed_traffic.sensing.lane_graph import CURRENT
from mixed_traffic.sensing.neighbours import Neighbours
from mixed_traffic.world.snapshot import TrafficSnapshot

#: Vehicle feature columns (physical units): distance [m], relative velocity v_other - v_ego
#: [m/s], relative heading [rad], length [m], width [m], lateral offset of the other vehicle from
#: its lane centre, + = left [m].
VEHICLE_FEATURES = ("distance", "rel_velocity", "rel_heading", "length", "width", "lateral")


def vehicle_features(snap: TrafficSnapshot, rows: np.ndarray, nb: Neighbours) -> np.ndarray:
    """(A, 3, 2, 6) ground-truth ``VEHICLE_FEATURES`` of the neighbours, 0 where missing."""
    if compiled.enabled():
        on_path, geom = nb.on_path, nb.path_geometry
        if on_path is None:
            on_path, geom = np.zeros(len(rows), bool), np.zeros((len(rows), 4))
        return sensing_kernel.vehicle_features(
            rows, nb.vehicle, nb.distance, on_path, geom, snap.speed, snap.heading, snap.length,
            snap.width, snap.lateral,
        )  # fmt: skip
    v = nb.vehicle
    ok = v >= 0
    o = np.maximum(v, 0)
    ego = rows[:, None, None]
    feats = np.stack(
        [
            np.where(ok, nb.distance, 0.0),
            snap.speed[o] - snap.speed[ego],
            wrap_angle(snap.heading[o] - snap.heading[ego]),
            snap.length[o],
            snap.width[o],
            snap.lateral[o],
        ],
        axis=-1,
    )
    if nb.on_path is not None and nb.on_path.any():
        # a vehicle across the path: speed along the path, extents along / across it, offset
        # from it (``PATH_GEOMETRY``)
        g = nb.path_geometry
        path = np.stack([g[:, 0] - snap.speed[rows], g[:, 1], g[:, 2], g[:, 3]], axis=1)
        cols = [1, 3, 4, 5]
        feats[:, CURRENT, 0, cols] = np.where(nb.on_path[:, None], path, feats[:, CURRENT, 0, cols])
    return np.where(ok[..., None], feats, 0.0)
