"""Training curves of a run (``OUT/curves.csv``) as one PNG (no SUMO, no torch).

    python -m analysis.training_curves runs/auto/curves.csv docs/training/auto.png

Panels over transitions received: reward per decision (scaled, as stored), terminal events per
AV trip, critic loss and actor loss. Legs of one lineage can be given in order: their
transitions are laid end to end.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

from analysis.figures import new_figure, save_figure

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


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m analysis.training_curves", description=__doc__)
    p.add_argument("curves", nargs="+", type=Path, help="curves.csv of each leg, in order")
    p.add_argument("out", type=Path, help="PNG to write")
    p.add_argument("--title", default="AUTO training", help="figure title")
    args = p.parse_args(argv)
    try:
        df = load_legs(args.curves)
    except (OSError, ValueError) as e:
        p.error(str(e))
    print(plot(df, args.out, args.title))
    return 0


if __name__ == "__main__":
    sys.exit(main())
