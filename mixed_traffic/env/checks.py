"""Checks of the env's arguments that name the misuse before any work starts."""

from __future__ import annotations

import os
import warnings
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


def check_step(phase: str, actions: Any, episode_length: float) -> None:
    """Name a ``step()`` call before ``reset()``, after ``close()`` or after the episode ended
    (``phase``), or whose ``actions`` are not a dict."""
    check_phase(phase, episode_length)
    if not isinstance(actions, Mapping):
        raise ValueError(f"step() takes a dict of actions, one per live agent (agent id -> "
                         f"{{'decision', 'params'}}), got {type(actions).__name__}")  # fmt: skip


def check_phase(phase: str, episode_length: float) -> None:
    """Name a step before ``reset()``, after ``close()`` or after the episode ended."""
    if phase == "new":
        raise RuntimeError("step() before reset(): call reset() to start an episode first")
    if phase == "closed":
        raise RuntimeError("step() after close(): call reset() to start a new episode")
    if phase == "ended":
        raise RuntimeError(f"step() after the episode ended at episode_length="
                           f"{episode_length} s: call reset()")  # fmt: skip


def check_warmup(warmup: float, episode_length: float) -> None:
    """Raise ``ValueError`` unless 0 <= ``warmup`` < ``episode_length`` [s]."""
    if not 0 <= warmup < episode_length:
        raise ValueError(f"warmup={warmup} s must be in [0, episode_length={episode_length}) s")


COARSE_STEP = 0.5
"""Longest step [s] at which the AVs' control holds up: ACC-LC was checked at 0.05-0.5 s."""


def warn_coarse_step(step_length: float) -> None:
    """Warn about steps longer than ``COARSE_STEP`` (a .sumocfg may set 1 s, SUMO's default):
    the bicycle model takes one step at a time and junction turns pass in one or two."""
    if step_length > COARSE_STEP + 1e-9:
        warnings.warn(
            f"step_length={step_length:g} s is longer than {COARSE_STEP} s: the AVs' kinematic "
            "control cannot follow junction turns at this step (ACC-LC left the road 27 times "
            "in 90 s of urban at 1 s); use a step of at most 0.5 s",
            stacklevel=3,
        )


def check_config_args(config: Any, kwargs: dict[str, Any]) -> None:
    """The env takes ``config=EnvConfig(...)`` or keyword fields, not both."""
    if config is not None and kwargs:
        raise ValueError(
            f"pass either config=EnvConfig(...) or keyword fields, not both: {sorted(kwargs)}"
        )


def check_render_mode(mode: str | None, modes: list[str]) -> None:
    """A known render mode, and for ``human`` a display and sumo-gui."""
    if mode not in (None, *modes):
        raise ValueError(f"render_mode={mode!r} is not one of {modes}")
    if mode == "human":
        check_gui()


def no_agent_message(seed: int, cfg: Any, waited: bool) -> str:
    """Why reset(seed) found no agent: none entered within ``reset_wait`` (``waited``) or
    during the whole episode."""
    within = (f"within reset_wait={cfg.reset_wait} s" if waited
              else f"during the {cfg.episode_length} s episode")  # fmt: skip
    return (f"reset(seed={seed}): no AV entered the network {within}; raise the penetration, the "
            "density or reset_wait, or pass options={'allow_no_agents': True} to run the episode "
            "all human")  # fmt: skip


def check_gui() -> None:
    """Name a missing display before sumo-gui is started (``render_mode='human'``)."""
    if not os.environ.get("DISPLAY"):
        raise ValueError("render_mode='human' needs sumo-gui and a display (DISPLAY is not set); "
                         "use render_mode='rgb_array' for headless rendering")  # fmt: skip
    binary("sumo-gui")
