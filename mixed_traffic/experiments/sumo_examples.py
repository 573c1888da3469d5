"""Every SUMO network (or configuration) that ships with the ``eclipse-sumo`` wheel, driven by a
policy: one episode each through the episode runner, a table of terminal events per AV trip,
and one JSON line per file (issue 24's check on networks the project was not built on)::

    python -m mixed_traffic.experiments.sumo_examples --policy acc-lc --out examples.jsonl

A file without anything for the AVs (no car lane; a configuration whose vehicles are only
trains, or persons riding a taxi) or that SUMO itself cannot load is listed with its one-line
error. Any other error is listed too and makes the exit status 1.
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
from mixed_traffic.experiments.cli import policy_arg
from mixed_traffic.experiments.runner import run_episode
from mixed_traffic.experiments.safety_matrix import terminal_events
from mixed_traffic.provenance import check_writable, rewrite_records
from mixed_traffic.world.demand import av_count
from mixed_traffic.world.registry import load_scenario

EXPECTED = {
    "has no lane that passenger cars may use": "no car lane",
    "define no vehicle on roads the AVs may use": "no AV vehicle",
    "Could not load configuration": "sumo rejects it",
}
"""Named errors that are expected outcomes -> status: files with nothing the AVs could be or
use, and configurations that SUMO itself cannot load (options of a GUI build: ``osg-view``)."""


def sumo_examples(kind: str = "net") -> list[Path]:
    """The wheel's ``*.net.xml[.gz]`` (``kind`` "net") or ``*.sumocfg`` files under its
    ``tools`` folder, sorted."""
    import sumo  # the eclipse-sumo wheel

    tools = Path(sumo.SUMO_HOME) / "tools"
    patterns = ("*.net.xml", "*.net.xml.gz") if kind == "net" else ("*.sumocfg",)
    return sorted(p for pat in patterns for p in tools.rglob(pat))


def run_one(path: Path, policy: str, penetration: float, seconds: float, seed: int) -> dict:
    """One episode of ``path``: its terminal events, trips, collisions, agents and wall time
    per simulated second, or its error."""
    name = str(path.relative_to(path.parents[2]))
    try:
        config = EnvConfig(scenario=str(path), penetration=penetration,
                           episode_length=seconds, seed=seed)  # fmt: skip
        scenario = load_scenario(config.scenario)
        agents = av_count(scenario, scenario.configure(config))
        record = run_episode(config, policy, warmup=0.0)
    except Exception as e:  # every file gets a row; the exit status tells
        status = next((s for k, s in EXPECTED.items() if k in str(e)), "error")
        return {"file": name, "status": status, "error": f"{type(e).__name__}: {e}"}
    m = record["metrics"]
    events = terminal_events(m)
    trips = int(m.get("av_trips") or 0)
    simulated = record["diagnostics"]["steps"] * record["config"]["step_length"]
    return {"file": name, "status": "ok", "av_trips": trips, "terminal": events,
            "collisions": int(m.get("collisions") or 0), "teleports": int(m.get("teleports") or 0),
            "sm_share": m.get("sm_share"), "possible_agents": agents,
            "wall_per_sim_s": record["wall_time"] / max(simulated, 1e-9), "record": record}  # fmt: skip


def summary(rows: Sequence[dict[str, Any]]) -> str:
    """The table: per file its agents, AV trips, terminal events and wall time per simulated
    second (or its status), then the terminal events per AV trip over all files."""
    lines = [f"{'file':50s} {'agents':>6s} {'trips':>5s} {'terminal':>8s} {'wall/sim':>8s}  events"]
    total = trips = 0
    for r in rows:
        if r["status"] != "ok":
            lines.append(f"{r['file']:50s} {'-':>6s} {'-':>5s} {'-':>8s} {'-':>8s}  {r['status']}"
                         + (f": {r['error']}" if r["status"] == "error" else ""))  # fmt: skip
            continue
        n = sum(r["terminal"].values())
        total, trips = total + n, trips + r["av_trips"]
        ev = ",".join(f"{k}:{v}" for k, v in sorted(r["terminal"].items())) or "-"
        lines.append(f"{r['file']:50s} {r['possible_agents']:6d} {r['av_trips']:5d} {n:8d} "
                     f"{r['wall_per_sim_s']:8.2f}  {ev}")  # fmt: skip
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
    p.add_argument("--policy", type=policy_arg, default="acc-lc",
                   help="policy driving the AVs (default: acc-lc)")  # fmt: skip
    p.add_argument("--penetration", type=float, default=1.0, help="AV share (default: 1.0)")
    p.add_argument("--seconds", type=float, default=90.0,
                   help="simulated time per episode [s] (default: 90)")  # fmt: skip
    p.add_argument("--seed", type=int, default=0, help="env seed (default: 0)")
    p.add_argument("--workers", type=int, default=2, help="processes (default: 2)")
    p.add_argument("--out", type=Path, help="write one JSON line per file here")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Run every example and print the table; exit 1 if a file failed with an error other
    than having nothing for the AVs."""
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
    failed = sum(r["status"] == "error" for r in rows)
    if failed:
        print(f"{failed} of {len(rows)} files failed", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
