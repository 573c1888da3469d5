"""A PPO policy trained by ``python -m mixed_traffic.benchmark.ppo`` (Stable-Baselines3), as a
batch policy of the one episode runner: ``--policy ppo-ring`` (the shipped ring policy) or
``--policy ppo --checkpoint model.zip``.

A checkpoint is SB3's ``.zip`` (weights and optimiser) with a ``.json`` beside it naming the
task, the interface (:class:`agents.longitudinal.LongitudinalConfig`), the training seed,
steps, time and code revision. Each agent decides every ``hold`` env steps from the compact
features and holds its acceleration in between; inference is one batched call for the agents
that decide.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from agents.longitudinal import LongitudinalConfig, LongitudinalInterface


def meta_path(checkpoint: str | Path) -> Path:
    """The ``.json`` beside a checkpoint ``.zip``."""
    return Path(checkpoint).with_suffix(".json")


def read_meta(checkpoint: str | Path) -> dict[str, Any]:
    """The checkpoint's metadata; ``ValueError`` naming the file if it is missing or bad."""
    path = Path(checkpoint)
    if path.suffix != ".zip" or not path.is_file():
        raise ValueError(f"PPO checkpoint {str(path)!r} is not a readable .zip file")
    try:
        meta = json.loads(meta_path(path).read_text())
        LongitudinalConfig(**meta["interface"])
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"PPO checkpoint {str(path)!r}: its {meta_path(path).name} is missing "
                         f"or unreadable ({type(e).__name__}: {e})") from None  # fmt: skip
    return meta


def load_model(checkpoint: str | Path) -> Any:
    """SB3's PPO from ``checkpoint`` on the CPU; ``ValueError`` if SB3 is missing or the
    file is not a PPO checkpoint."""
    try:
        from stable_baselines3 import PPO
    except ImportError:
        raise ValueError("PPO policies need Stable-Baselines3: pip install "
                         "'mixed-traffic[ppo]'") from None  # fmt: skip
    try:
        return PPO.load(str(checkpoint), device="cpu")
    except Exception as e:  # SB3 raises zipfile, pickle and key errors for a bad file
        raise ValueError(f"PPO checkpoint {str(checkpoint)!r} is unreadable "
                         f"({type(e).__name__}: {e})") from None  # fmt: skip


def check_ppo_checkpoint(checkpoint: str | Path) -> None:
    """``ValueError`` (one line) unless ``checkpoint`` loads as a PPO policy."""
    read_meta(checkpoint)
    load_model(checkpoint)


class PpoPolicy:
    """Greedy (mean) actions of a trained PPO policy over the longitudinal interface."""

    def __init__(self, checkpoint: str | Path, dt: float = 0.1, name: str = "ppo") -> None:
        self.name = name
        meta = read_meta(checkpoint)
        config = LongitudinalConfig(**meta["interface"])
        if abs(config.dt - dt) > 1e-9:
            raise ValueError(f"PPO checkpoint {str(checkpoint)!r} was trained with a "
                             f"{config.dt} s step, the env steps {dt} s")  # fmt: skip
        self.model = load_model(checkpoint)
        self.interface = LongitudinalInterface(config)
        self.checkpoint = str(checkpoint)
        self.params = {"task": meta.get("task"), "seed": meta.get("seed"),
                       "timesteps": meta.get("timesteps")}  # fmt: skip
        self._held: dict[str, float] = {}
        self._age: dict[str, int] = {}

    def act(
        self, obs: Mapping[str, np.ndarray], agents: Sequence[str] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Batched (A, ...) observations of ``agents`` -> (decision (A,), params (A, 3, 2))."""
        n = len(obs["action_mask"])
        agents = list(agents) if agents is not None else [str(i) for i in range(n)]
        feats = self.interface.observe(obs, agents)
        hold = self.interface.c.hold
        for a in [a for a in self._held if a not in set(agents)]:  # agents that left
            del self._held[a], self._age[a]
        due = [i for i, a in enumerate(agents) if self._age.get(a, hold) >= hold]
        if due:
            x, _ = self.model.predict(feats[due], deterministic=True)
            for i, value in zip(due, np.asarray(x).reshape(len(due), -1)[:, 0]):
                self._held[agents[i]], self._age[agents[i]] = float(value), 0
        for a in agents:
            self._age[a] += 1
        return self.interface.command(np.array([self._held[a] for a in agents]))
