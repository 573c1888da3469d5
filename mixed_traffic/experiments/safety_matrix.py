"""Safety table of a policy (ACC-LC by default): one episode per scenario x density x
penetration through the episode runner, with its terminal events, collisions, AV trips, route
completion and mean AV speed::

    python -m mixed_traffic.experiments.safety_matrix --scenarios merge-eval --densities 120
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any

from mixed_traffic.config import WEATHERS, EnvConfig
from mixed_traffic.experiments.cli import policy_arg
from mixed_traffic.experiments.runner import run_episode
from mixed_traffic.schema import TERMINAL_REASONS

SCENARIOS = (
    "straight", "straight-eval", "highway", "highway-eval", "bottleneck",
    "bottleneck-eval", "merge", "merge-eval", "urban", "urban-eval",
)  # fmt: skip
DENSITIES = (60, 120, 180)
PENETRATIONS = (0.2, 0.5, 1.0)


def terminal_events(metrics: dict[str, Any]) -> dict[str, int]:
    """Terminal events of an episode's metrics by reason (reasons with none left out)."""
    counts = {r: int(metrics.get(f"terminal_{r}") or 0) for r in TERMINAL_REASONS}
    return {r: n for r, n in counts.items() if n}


def safety_matrix(
    scenarios: Sequence[str] = SCENARIOS,
    densities: Sequence[int] = DENSITIES,
    penetrations: Sequence[float] = PENETRATIONS,
    seconds: float = 120.0,
    seed: int = 0,
    weather: str = "normal",
    policy: str = "acc-lc",
) -> list[dict]:
    """Run ``policy`` over scenarios x densities x penetrations and print a safety table."""
    rows = []
    hdr = (
        f"{'scenario':16s} {'dens':>4s} {'pen':>4s} {'coll':>4s} {'events':24s} {'trips':>5s} "
        f"{'rc':>5s} {'vel_A':>6s}"
    )
    print(hdr, flush=True)
    for sc in scenarios:
        for dn in densities:
            for p in penetrations:
                config = EnvConfig(scenario=sc, density=dn, penetration=p, weather=weather,
                                   episode_length=seconds, seed=seed)  # fmt: skip
                m = run_episode(config, policy, warmup=0.0)["metrics"]
                ev = terminal_events(m)
                rows.append({"scenario": sc, "density": dn, "penetration": p, "events": ev, **m})
                evs = ",".join(f"{k}:{v}" for k, v in sorted(ev.items())) or "-"
                print(
                    f"{sc:16s} {dn:4d} {p:4.1f} {int(m.get('collisions') or 0):4d} {evs:24s} "
                    f"{int(m.get('av_trips') or 0):5d} {_fmt(m.get('route_completion'))} "
                    f"{_fmt(m.get('avg_vel_a'))}",
                    flush=True,
                )
    return rows


def _fmt(x: Any) -> str:
    """A table cell: a number as ``6.2f``, anything else (None) as ``-``."""
    return f"{x:6.2f}" if isinstance(x, (int, float)) else f"{'-':>6s}"


def build_parser() -> argparse.ArgumentParser:
    """The command-line options of :func:`main`."""
    p = argparse.ArgumentParser(
        prog="python -m mixed_traffic.experiments.safety_matrix",
        description="Drive every AV with a policy for one episode per scenario x density x "
        "penetration and print a safety table (terminal events, collisions, AV trips, route "
        "completion, mean AV speed).",
    )
    p.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), metavar="NAME",
                   help=f"scenarios (default: {' '.join(SCENARIOS)})")  # fmt: skip
    p.add_argument("--densities", type=int, nargs="+", default=list(DENSITIES), metavar="K",
                   help="densities [veh/km, all lanes] (default: 60 120 180)")  # fmt: skip
    p.add_argument("--penetrations", type=float, nargs="+", default=list(PENETRATIONS),
                   metavar="P", help="AV penetrations [0-1] (default: 0.2 0.5 1.0)")  # fmt: skip
    p.add_argument("--seconds", type=float, default=120.0,
                   help="simulated time per episode [s] (default: 120)")  # fmt: skip
    p.add_argument("--seed", type=int, default=0, help="env seed of every episode (default: 0)")
    p.add_argument("--weather", choices=WEATHERS, default="normal",
                   help="weather preset (default: normal)")  # fmt: skip
    p.add_argument("--policy", type=policy_arg, default="acc-lc",
                   help="policy driving the AVs (default: acc-lc)")  # fmt: skip
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Parse the options and print the table."""
    args = build_parser().parse_args(argv)
    safety_matrix(args.scenarios, args.densities, args.penetrations, args.seconds, args.seed,
                  args.weather, args.policy)  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
