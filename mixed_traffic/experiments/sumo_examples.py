"""Every SUMO network (or configuration) that ships with the ``eclipse-sumo`` wheel, driven by a
policy: one episode each through the episode runner, a table of terminal events per AV trip,
and one JSON line per file and seed (issue 24's check on networks the project was not built on)::

    python -m mixed_traffic.experiments.sumo_examples --policy acc-lc --out examples.jsonl

Issue 42's check: SUMO's game configurations (``--games``) at 50 % AVs among the files' own
vehicles, over several seeds, against the bound on terminal events per AV trip of the policy
(``BOUNDS``: ACC-LC 1 %, AUTO 2 %); exit status 1 if it is exceeded::

    python -m mixed_traffic.experiments.sumo_examples --games --seeds 7 8 9 --penetration 0.5 \
        --episode-length 300 --policy acc-lc --out games.jsonl

With ``--out`` every episode's row is appended atomically as it finishes, and a rerun skips the
episodes already there (same file, seed, policy, penetration, length and code): an interrupted
check resumes. A file without anything for the AVs (no car lane; a configuration whose vehicles
are only trains, or persons riding a taxi) or that SUMO itself cannot load is listed with its
one-line error. Any other error is listed too and makes the exit status 1.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

from tqdm import tqdm

from mixed_traffic.config import EnvConfig
from mixed_traffic.experiments.cli import policy_arg
from mixed_traffic.experiments.runner import run_episode
from mixed_traffic.experiments.safety_matrix import terminal_events
from mixed_traffic.provenance import (
    check_writable,
    current_code_key,
    read_records,
    write_record_atomic,
)
from mixed_traffic.world.demand import av_count
from mixed_traffic.world.registry import load_scenario

EXPECTED = {
    "has no lane that passenger cars may use": "no car lane",
    "define no vehicle on roads the AVs may use": "no AV vehicle",
    "Could not load configuration": "sumo rejects it",
}
"""Named errors that are expected outcomes -> status: files with nothing the AVs could be or
use, and configurations that SUMO itself cannot load (options of a GUI build: ``osg-view``)."""
GAMES = ("A10KW", "corridor", "cross", "grid6", "racing/racing", "ramp", "square")
"""SUMO's game configurations with road traffic the AVs can join (``tools/game/<name>.sumocfg``;
issue 42). The wheel's other ones are demos, or have only trains, taxis or persons, or need a
3D build of SUMO."""
BOUNDS = {"acc-lc": 1.0, "auto": 2.0}
"""Issue 42's bound on terminal events per AV trip [%] on the games, per policy."""
JOB_KEYS = ("file", "seed", "policy", "penetration", "seconds", "code")
"""What makes two rows the same episode (a rerun with ``--out`` skips it)."""


def sumo_examples(kind: str = "net") -> list[Path]:
    """The wheel's ``*.net.xml[.gz]`` (``kind`` "net") or ``*.sumocfg`` files under its
    ``tools`` folder, sorted."""
    import sumo  # the eclipse-sumo wheel

    tools = Path(sumo.SUMO_HOME) / "tools"
    patterns = ("*.net.xml", "*.net.xml.gz") if kind == "net" else ("*.sumocfg",)
    return sorted(p for pat in patterns for p in tools.rglob(pat))


def sumo_games() -> list[Path]:
    """The wheel's game configurations of ``GAMES``."""
    import sumo  # the eclipse-sumo wheel

    return [Path(sumo.SUMO_HOME) / "tools" / "game" / f"{g}.sumocfg" for g in GAMES]


def file_name(path: Path) -> str:
    """``path`` relative to the wheel's ``tools`` folder (``game/ramp.sumocfg``)."""
    import sumo  # the eclipse-sumo wheel

    return path.relative_to(Path(sumo.SUMO_HOME) / "tools").as_posix()


def run_one(path: Path, policy: str, penetration: float, seconds: float, seed: int) -> dict:
    """One episode of ``path``: its terminal events, trips, collisions, agents and wall time
    per simulated second, or its error; with the keys of ``JOB_KEYS`` but the code."""
    job = {"file": file_name(path), "seed": seed, "policy": policy, "penetration": penetration,
           "seconds": seconds}  # fmt: skip
    return {**job, **_episode(path, policy, penetration, seconds, seed)}


def _episode(path: Path, policy: str, penetration: float, seconds: float, seed: int) -> dict:
    """The row of :func:`run_one` without its job keys."""
    try:
        config = EnvConfig(scenario=str(path), penetration=penetration,
                           episode_length=seconds, seed=seed)  # fmt: skip
        scenario = load_scenario(config.scenario)
        agents = av_count(scenario, scenario.configure(config))
        record = run_episode(config, policy, warmup=0.0)
    except Exception as e:  # every file gets a row; the exit status tells
        status = next((s for k, s in EXPECTED.items() if k in str(e)), "error")
        return {"status": status, "error": f"{type(e).__name__}: {e}"}
    m = record["metrics"]
    events = terminal_events(m)
    trips = int(m.get("av_trips") or 0)
    simulated = record["diagnostics"]["steps"] * record["config"]["step_length"]
    return {"status": "ok", "av_trips": trips, "terminal": events,
            "collisions": int(m.get("collisions") or 0), "teleports": int(m.get("teleports") or 0),
            "sm_share": m.get("sm_share"), "possible_agents": agents,
            "wall_per_sim_s": record["wall_time"] / max(simulated, 1e-9), "record": record}  # fmt: skip


def summary(rows: Sequence[dict[str, Any]]) -> str:
    """The table: per file (and seed) its agents, AV trips, terminal events and wall time per
    simulated second (or its status), then the terminal events per AV trip over all rows."""
    head = (
        f"{'file':44s} {'seed':>5s} {'agents':>6s} {'trips':>5s} {'terminal':>8s} {'wall/sim':>8s}"
    )
    lines = [f"{head}  events"]
    for r in rows:
        first = f"{r['file']:44s} {r.get('seed', '-')!s:>5s}"
        if r["status"] != "ok":
            lines.append(f"{first} {'-':>6s} {'-':>5s} {'-':>8s} {'-':>8s}  {r['status']}"
                         + (f": {r['error']}" if r["status"] == "error" else ""))  # fmt: skip
            continue
        ev = ",".join(f"{k}:{v}" for k, v in sorted(r["terminal"].items())) or "-"
        lines.append(f"{first} {r['possible_agents']:6d} {r['av_trips']:5d} "
                     f"{sum(r['terminal'].values()):8d} {r['wall_per_sim_s']:8.2f}  {ev}")  # fmt: skip
    total, trips = totals(rows)
    lines.append(f"all: {total} terminal events in {trips} AV trips = {share(rows):.1f} % per trip")
    return "\n".join(lines)


def totals(rows: Sequence[dict[str, Any]]) -> tuple[int, int]:
    """(terminal events, AV trips) summed over the rows that ran."""
    ok = [r for r in rows if r["status"] == "ok"]
    return sum(sum(r["terminal"].values()) for r in ok), sum(r["av_trips"] for r in ok)


def share(rows: Sequence[dict[str, Any]]) -> float:
    """Terminal events per AV trip over all rows [%] (0 without trips)."""
    total, trips = totals(rows)
    return 100.0 * total / max(trips, 1)


def verdict(rows: Sequence[dict[str, Any]], policy: str, bound: float) -> tuple[bool, str]:
    """Whether the rows keep ``bound`` [% terminal events per AV trip], and the line saying so."""
    ok = share(rows) <= bound
    total, trips = totals(rows)
    seeds = sorted({r["seed"] for r in rows if "seed" in r})
    return ok, (f"{'PASS' if ok else 'FAIL'}: {policy}, {total} terminal events in {trips} AV "
                f"trips = {share(rows):.2f} % per trip (bound {bound:g} %), seeds "
                f"{' '.join(map(str, seeds))}")  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    """The command-line options of :func:`main`."""
    p = argparse.ArgumentParser(
        prog="python -m mixed_traffic.experiments.sumo_examples",
        description="Drive the AVs of every network (or .sumocfg) shipped with the eclipse-sumo "
        "wheel for one episode per seed and print terminal events per AV trip.",
    )
    p.add_argument("--kind", choices=("net", "sumocfg"), default="net",
                   help="networks or configurations (default: net)")  # fmt: skip
    p.add_argument("--games", action="store_true",
                   help=f"only the game configurations {', '.join(GAMES)} (issue 42)")  # fmt: skip
    p.add_argument("--policy", type=policy_arg, default="acc-lc",
                   help="policy driving the AVs (default: acc-lc)")  # fmt: skip
    p.add_argument("--penetration", type=float, default=1.0, help="AV share (default: 1.0)")
    p.add_argument("--seconds", "--episode-length", type=float, default=90.0,
                   help="simulated time per episode [s] (default: 90)")  # fmt: skip
    p.add_argument("--seeds", "--seed", type=int, nargs="+", default=[0],
                   help="env seeds, one episode per file each (default: 0)")  # fmt: skip
    p.add_argument("--bound", type=float,
                   help="pass/fail bound on terminal events per AV trip [%%] (default: "
                   f"{', '.join(f'{k} {v:g}' for k, v in BOUNDS.items())}; none otherwise)")  # fmt: skip
    p.add_argument("--workers", type=int, default=2, help="processes (default: 2)")
    p.add_argument("--out", type=Path,
                   help="append one JSON line per episode here as it ends; episodes already "
                   "there are not run again")  # fmt: skip
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Run every example (per seed) and print the table, and the verdict against the bound;
    exit 1 if a file failed with an error other than having nothing for the AVs, or if the
    bound is exceeded."""
    args = build_parser().parse_args(argv)
    if args.workers < 1:
        raise SystemExit("error: --workers must be at least 1")
    if args.bound is not None and args.bound < 0:
        raise SystemExit(f"error: --bound must be >= 0, got {args.bound}")
    for seed in args.seeds:
        EnvConfig(penetration=args.penetration, episode_length=args.seconds, seed=seed)
    if args.out:
        check_writable(args.out)
    files = sumo_games() if args.games else sumo_examples(args.kind)
    code = current_code_key()
    jobs = [dict(file=file_name(f), seed=s, policy=args.policy, penetration=args.penetration,
                 seconds=args.seconds, code=code, path=f) for f in files for s in args.seeds]  # fmt: skip
    rows = _run(jobs, args.workers, args.out)
    print(summary(rows))
    failed = sum(r["status"] == "error" for r in rows)
    if failed:
        print(f"{failed} of {len(rows)} episodes failed", file=sys.stderr)
    bound = args.bound if args.bound is not None else BOUNDS.get(args.policy.split(":")[0])
    passed = True
    if bound is not None:
        passed, line = verdict(rows, args.policy, bound)
        print(line)
    return 1 if failed or not passed else 0


def _run(jobs: list[dict[str, Any]], workers: int, out: Path | None) -> list[dict[str, Any]]:
    """The rows of ``jobs`` in their order: those already in ``out``, then the others run
    over ``workers`` processes, each appended to ``out`` as it ends."""
    key = lambda r: tuple(r.get(k) for k in JOB_KEYS)  # noqa: E731
    done = {key(r): r for r in read_records(out)} if out and out.exists() else {}
    todo = [j for j in jobs if key(j) not in done]
    if len(todo) < len(jobs):
        print(f"{len(jobs) - len(todo)} of {len(jobs)} episodes already in {out}", file=sys.stderr)
    with ProcessPoolExecutor(workers) as pool:
        futures = {pool.submit(run_one, j["path"], j["policy"], j["penetration"], j["seconds"],
                               j["seed"]): j for j in todo}  # fmt: skip
        for f in tqdm(as_completed(futures), total=len(futures), desc="episodes", unit="ep"):
            row = {**f.result(), "code": futures[f]["code"]}
            done[key(row)] = row
            if out:
                write_record_atomic(out, row)
    return [done[key(j)] for j in jobs]


if __name__ == "__main__":
    sys.exit(main())
