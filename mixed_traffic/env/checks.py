"""Checks of the env's arguments that name the misuse before any work starts."""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from mixed_traffic.world.backend import binary


def check_reset_args(seed: Any, options: Any) -> None:
    """Name a seed that is not an integer >= 0 (or None) and options that are not a dict."""
    if seed is not None and (
        not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0
    ):
        raise ValueError(f"reset(seed={seed!r}): seed must be an integer >= 0 or None")
    if options is not None and not isinstance(options, Mapping):
        raise ValueError(f"reset(options={options!r}): options must be a dict or None")


def check_warmup(warmup: float, episode_length: float) -> None:
    """Raise ``ValueError`` unless 0 <= ``warmup`` < ``episode_length`` [s]."""
    if not 0 <= warmup < episode_length:
        raise ValueError(f"warmup={warmup} s must be in [0, episode_length={episode_length}) s")


def check_gui() -> None:
    """Name a missing display before sumo-gui is started (``render_mode='human'``)."""
    if not os.environ.get("DISPLAY"):
        raise ValueError("render_mode='human' needs sumo-gui and a display (DISPLAY is not set); "
                         "use render_mode='rgb_array' for headless rendering")  # fmt: skip
    binary("sumo-gui")
