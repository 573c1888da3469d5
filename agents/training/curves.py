"""Learning curves of a training run: the :class:`Window` that aggregates chunks and losses
between two rows, ``curves.csv`` I/O, and the optional TensorBoard writer and progress bar."""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from agents.collection.workers import Chunk
from mixed_traffic.provenance import atomic_write

CURVE_COLUMNS = (
    "env_steps", "wall_time", "episodes", "updates", "replay_size", "mean_episode_reward",
    "mean_reward_per_action", "terminal_rate", "collision_rate", "critic_loss", "actor_loss",
    "demo_fraction",
)  # fmt: skip
"""curves.csv columns: terminal/collision rates are per AV trip ended in the row's window (all
transitions, demonstrator included: see demo_fraction); mean_episode_reward is the return per
AV of policy-driven episodes that ended in the window (NaN if none)."""


class Window:
    """Aggregates chunks/episodes/losses between two learning-curve rows."""

    def __init__(self) -> None:
        self.ep_returns: list[float] = []
        self.trips = self.terminals = self.collisions = 0.0
        self.reward_sum = 0.0
        self.transitions = self.demo = 0
        self.c_loss: list[float] = []
        self.a_loss: list[float] = []

    def add_chunk(self, chunk: Chunk) -> None:
        """Count a chunk's transitions, rewards, trips and the returns of its episodes."""
        self.reward_sum += float(chunk["reward"].sum())
        self.transitions += len(chunk["decision"])
        self.demo += int(chunk["demo"])
        self.trips += chunk["trips"]
        self.terminals += chunk["terminals"]
        self.collisions += chunk["collisions"]
        for ep in chunk["episodes"]:
            if not ep["demo"]:  # returns of the learning policy, not of the demonstrator
                self.ep_returns.append(ep["return_per_av"])

    def row(self) -> dict[str, float]:
        """The window's columns of a curves row (NaN where nothing was counted)."""

        def mean(x: list[float]) -> float:  # Q-PAMDP's idle network logs NaN losses
            x = [v for v in x if not math.isnan(v)]
            return float(np.mean(x)) if x else math.nan

        trips = self.trips if self.trips > 0 else math.nan
        return {
            "mean_episode_reward": mean(self.ep_returns),
            "mean_reward_per_action": self.reward_sum / self.transitions
            if self.transitions else math.nan,
            "terminal_rate": self.terminals / trips,
            "collision_rate": self.collisions / trips,
            "critic_loss": mean(self.c_loss),
            "actor_loss": mean(self.a_loss),
            "demo_fraction": self.demo / self.transitions if self.transitions else math.nan,
        }  # fmt: skip


def write_curves(path: Path, rows: list[dict], columns: Sequence[str] = CURVE_COLUMNS) -> None:
    """Append ``rows`` to the curves file ``path``, with the header when the file is new."""
    new = not path.exists()
    with path.open("a", newline="") as f:
        w = csv.DictWriter(f, fieldnames=columns)
        if new:
            w.writeheader()
        w.writerows(rows)


def trim_curves(path: Path, last: float, columns: Sequence[str] = CURVE_COLUMNS,
                key: str = "env_steps") -> None:  # fmt: skip
    """Keep the rows of the curves file ``path`` whose ``key`` is at most ``last`` (the last
    commit: a resumed run redoes the rest), dropping a row torn by a kill; atomic."""
    if not path.is_file():
        return
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    keep = [r for r in rows if None not in r.values() and _number(r, key) <= last]
    if len(keep) != len(rows):
        text = io.StringIO()
        w = csv.DictWriter(text, fieldnames=columns)
        w.writeheader()
        w.writerows(keep)
        atomic_write(path, lambda f: f.write(text.getvalue().encode()))


def _number(row: dict[str, str], key: str) -> float:
    """A curves row's ``key`` (inf when unreadable, so that trimming drops it)."""
    try:
        return float(row[key])
    except ValueError:
        return math.inf


def tensorboard(out: Path) -> Any:
    """A SummaryWriter under ``out/tb`` when torch.utils.tensorboard + tensorboard import."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(str(out / "tb"))


def progress(total: int, initial: int, enabled: bool) -> Any:
    """A tqdm bar over ``total`` transitions (0 = unknown) from ``initial``."""
    from tqdm import tqdm

    return tqdm(total=total or None, initial=initial, unit="tr", desc="train",
                disable=not enabled, dynamic_ncols=True, smoothing=0.05)  # fmt: skip
