"""SUMO backend: the only package that imports libsumo/traci."""

from mixed_traffic.backend.snapshot import (
    Collision,
    TrafficSnapshot,
    rad_to_sumo_angle,
    sumo_angle_to_rad,
)
from mixed_traffic.backend.sumo import SumoBackend, SumoError, binary, libsumo_busy, sumo_version

__all__ = [
    "Collision",
    "SumoBackend",
    "SumoError",
    "TrafficSnapshot",
    "binary",
    "libsumo_busy",
    "rad_to_sumo_angle",
    "sumo_angle_to_rad",
    "sumo_version",
]
