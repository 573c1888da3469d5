"""Training curves of a run (``OUT/curves.csv``) as one PNG (no SUMO, no torch).

    python -m analysis.training_curves runs/auto/curves.csv docs/training/auto.png

Panels over transitions received: reward per decision (scaled, as stored), terminal events per
AV trip, critic loss and actor loss. Legs of one lineage can be given in order: their
transitions are laid end to end. A fleet-search ``curves.csv`` (``mixed_traffic.experiments.fleet``,
an ``iteration`` column) gets its own panels over iterations: the current policy's fleet score
against ACC-LC's with a running mean and its 95 % t-interval, the size of the ES step's pair
differences, and the accel outputs' biases.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from analysis.figures import new_figure, save_figure
from analysis.stats import t_quantile_975

PANELS = (
    ("mean_reward_per_action", "reward per decision [-]"),
    ("terminal_rate", "terminal events per AV trip [-]"),
    ("critic_loss", "critic loss [-]"),
    ("actor_loss", "actor loss [-]"),
)


def load_legs(paths: list[Path]) -> pd.DataFrame:
    """The curves of ``paths`` in order, ``env_steps`` continued across legs, with a ``leg``
    column (1-based)."""
    frames, offset = [], 0
    for i, path in enumerate(paths, start=1):
        df = pd.read_csv(path)
        if "env_steps" not in df:
            raise ValueError(f"{path}: not a training curves.csv (no env_steps column)")
        frames.append(df.assign(env_steps=df["env_steps"] + offset, leg=i))
        offset = int(frames[-1]["env_steps"].max())
    return pd.concat(frames, ignore_index=True)


def plot(df: pd.DataFrame, out: Path, title: str) -> Path:
    """Write the four panels of ``df`` (:func:`load_legs`) to ``out``."""
    fig, axes = new_figure(10, 6, ncols=2, nrows=2)
    for ax, (col, label) in zip(axes, PANELS, strict=True):
        for leg, part in df.groupby("leg"):
            ax.plot(part["env_steps"] / 1e6, part[col], label=f"leg {leg}")
        ax.set_xlabel("transitions received [millions]")
        ax.set_ylabel(label)
    if df["leg"].nunique() > 1:
        axes[0].legend()
    fig.suptitle(title)
    return save_figure(fig, out)


FLEET_WINDOW = 10
"""Iterations in the running mean of the fleet-search gain."""


def plot_fleet(df: pd.DataFrame, out: Path, title: str) -> Path:
    """Write the fleet-search panels of ``df`` (a fleet ``curves.csv``) to ``out``."""
    fig, axes = new_figure(12, 3.6, ncols=3)
    it = df["iteration"]
    roll = df["gain"].rolling(FLEET_WINDOW, min_periods=2)
    n = roll.count()
    half = roll.std() / np.sqrt(n) * n.map(lambda k: t_quantile_975(k - 1) if k >= 2 else np.nan)
    ax = axes[0]
    ax.plot(it, df["gain"], ".", alpha=0.5, label="one config")
    ax.plot(it, roll.mean(), label=f"mean of last {FLEET_WINDOW}")
    ax.fill_between(it, roll.mean() - half, roll.mean() + half, alpha=0.2, label="95 % CI")
    ax.axhline(0, color="grey", lw=0.8)
    ax.set_ylabel("fleet score − ACC-LC's [ln(m/s)]")
    ax.legend()
    axes[1].plot(it, df["mean_d"])
    axes[1].set_ylabel("mean |pair difference| [ln(m/s)]")
    for col in ("bias_left", "bias_follow", "bias_right"):
        axes[2].plot(it, df[col], label=col.removeprefix("bias_"))
    axes[2].set_ylabel("accel output bias [-]")
    axes[2].legend()
    for ax in axes:
        ax.set_xlabel("iteration")
    fig.suptitle(title)
    return save_figure(fig, out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m analysis.training_curves", description=__doc__)
    p.add_argument("curves", nargs="+", type=Path, help="curves.csv of each leg, in order")
    p.add_argument("out", type=Path, help="PNG to write")
    p.add_argument("--title", default="AUTO training", help="figure title")
    args = p.parse_args(argv)
    try:
        fleet = "iteration" in pd.read_csv(args.curves[0], nrows=0).columns
        df = pd.read_csv(args.curves[0]) if fleet else load_legs(args.curves)
    except (OSError, ValueError) as e:
        p.error(str(e))
    print((plot_fleet if fleet else plot)(df, args.out, args.title))
    return 0


if __name__ == "__main__":
    sys.exit(main())
