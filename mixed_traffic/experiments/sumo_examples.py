"""Every SUMO network (or configuration) that ships with the ``eclipse-sumo`` wheel, driven by a
policy: one episode each through the episode runner, a table of terminal events per AV trip,
and one JSON line per file (issue 24's check on networks the project was not built on)::

    python -m mixed_traffic.experiments.sumo_examples --policy acc-lc --out examples.jsonl

A network without car lanes is listed with its one-line error; any other error fails the run.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from tqdm import tqdm

from mixed_traffic.config import EnvConfig
from mixed_traffic.experiments.runner import run_episode
from mixed_traffic.experiments.safety_matrix import terminal_events
from mixed_traffic.provenance import check_writable, rewrite_records
from mixed_traffic.schema import POLICIES

NO_CAR_LANE = "has no lane that passenger cars may use"
"""The named error of a network without car lanes (rail, racing), an expected outcome."""


def sumo_examples(kind: str = "net") -> list[Path]:
    """The wheel's ``*.net.xml[.gz]`` (``kind`` "net") or ``*.sumocfg`` files under its
    ``tools`` folder, sorted."""
    import sumo  # the eclipse-sumo wheel

    tools = Path(sumo.SUMO_HOME) / "tools"
    patterns = ("*.net.xml", "*.net.xml.gz") if kind == "net" else ("*.sumocfg",)
    return sorted(p for pat in patterns for p in tools.rglob(pat))


def run_one(path: Path, policy: str, penetration: float, seconds: float, seed: int) -> dict:
    """One episode of ``path``: its terminal events, trips and collisions, or its error."""
    name = str(path.relative_to(path.parents[2]))
    try:
        config = EnvConfig(scenario=str(path), penetration=penetration,
                           episode_length=seconds, seed=seed)  # fmt: skip
        record = run_episode(config, policy, warmup=0.0)
    except ValueError as e:
        if NO_CAR_LANE not in str(e):
            raise
        return {"file": name, "status": "no car lane", "error": str(e)}
    m = record["metrics"]
    events = terminal_events(m)
    trips = int(m.get("av_trips") or 0)
    return {"file": name, "status": "ok", "av_trips": trips, "terminal": events,
            "collisions": int(m.get("collisions") or 0), "teleports": int(m.get("teleports") or 0),
            "sm_share": m.get("sm_share"), "record": record}  # fmt: skip


def summary(rows: Sequence[dict[str, Any]]) -> str:
    """The table: per file its AV trips and terminal events, then the share over all."""
    lines = [f"{'file':58s} {'trips':>5s} {'terminal':>8s}  events"]
    total = trips = 0
    for r in rows:
        if r["status"] != "ok":
            lines.append(f"{r['file']:58s} {'-':>5s} {'-':>8s}  {r['status']}")
            continue
        n = sum(r["terminal"].values())
        total, trips = total + n, trips + r["av_trips"]
        ev = ",".join(f"{k}:{v}" for k, v in sorted(r["terminal"].items())) or "-"
        lines.append(f"{r['file']:58s} {r['av_trips']:5d} {n:8d}  {ev}")
    share = 100.0 * total / max(trips, 1)
    lines.append(f"all: {total} terminal events in {trips} AV trips = {share:.1f} % per trip")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    """The command-line options of :func:`main`."""
    p = argparse.ArgumentParser(
        prog="python -m mixed_traffic.experiments.sumo_examples",
        description="Drive the AVs of every network (or .sumocfg) shipped with the eclipse-sumo "
        "wheel for one episode and print terminal events per AV trip.",
    )
    p.add_argument("--kind", choices=("net", "sumocfg"), default="net",
                   help="networks or configurations (default: net)")  # fmt: skip
    p.add_argument("--policy", choices=POLICIES, default="acc-lc",
                   help="policy driving the AVs (default: acc-lc)")  # fmt: skip
    p.add_argument("--penetration", type=float, default=1.0, help="AV share (default: 1.0)")
    p.add_argument("--seconds", type=float, default=90.0,
                   help="simulated time per episode [s] (default: 90)")  # fmt: skip
    p.add_argument("--seed", type=int, default=0, help="env seed (default: 0)")
    p.add_argument("--workers", type=int, default=2, help="processes (default: 2)")
    p.add_argument("--out", type=Path, help="write one JSON line per file here")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Run every example and print the table; exit 0 unless an episode failed."""
    args = build_parser().parse_args(argv)
    if args.workers < 1:
        raise SystemExit("error: --workers must be at least 1")
    EnvConfig(penetration=args.penetration, episode_length=args.seconds, seed=args.seed)
    if args.out:
        check_writable(args.out)
    files = sumo_examples(args.kind)
    jobs = [(f, args.policy, args.penetration, args.seconds, args.seed) for f in files]
    with ProcessPoolExecutor(args.workers) as pool:
        futures = [pool.submit(run_one, *j) for j in jobs]
        rows = [f.result() for f in tqdm(futures, desc="examples", unit="file")]
    print(summary(rows))
    if args.out:
        rewrite_records(args.out, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
