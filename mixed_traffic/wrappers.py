"""Kept for the documented import path; the wrappers live in :mod:`mixed_traffic.env.wrappers`."""

from mixed_traffic.env.wrappers import (
    FLAT_SIZE,
    FlatActionWrapper,
    FlatObservationWrapper,
    dict_to_flat,
    flat_action_space,
    flat_to_dict,
)

__all__ = [
    "FLAT_SIZE",
    "FlatActionWrapper",
    "FlatObservationWrapper",
    "dict_to_flat",
    "flat_action_space",
    "flat_to_dict",
]
