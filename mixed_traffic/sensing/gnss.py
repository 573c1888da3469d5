"""GNSS/IMU: the ego's own speed, heading relative to its lane, size and lateral offset."""

from __future__ import annotations

import numpy as np

from mixed_traffic import compiled
from mixed_traffic.sensing import sensing_kernel
from mixed_traffic.sensing.geometry import wrap_angle
from mixed_traffic.world.hdmap import SPACING, HDMap
from mixed_traffic.world.snapshot import TrafficSnapshot

#: Ego feature columns: speed [m/s], heading relative to the lane [rad], length [m], width [m],
#: lateral offset from the centreline, + = left [m].
EGO_FEATURES = ("velocity", "heading_rel_lane", "length", "width", "lateral")


def ego_features(snap: TrafficSnapshot, hdmap: HDMap, rows: np.ndarray) -> np.ndarray:
    """(A, 5) ground-truth ``EGO_FEATURES``; heading is relative to the lane at the front bumper."""
    if compiled.enabled():
        return sensing_kernel.ego_features(
            rows, snap.lane, snap.lane_pos, snap.heading, snap.speed, snap.length, snap.width,
            snap.lateral, hdmap.wp_offset, hdmap.wp_count, hdmap.wp_heading, SPACING,
        )  # fmt: skip
    lane = snap.lane[rows]
    wp = hdmap.waypoint_at(np.maximum(lane, 0), snap.lane_pos[rows])
    rel = np.where(lane >= 0, wrap_angle(snap.heading[rows] - hdmap.wp_heading[wp]), 0.0)
    return np.stack(
        [snap.speed[rows], rel, snap.length[rows], snap.width[rows], snap.lateral[rows]], axis=1
    )
