"""The benchmark table: every task's eval configs x controllers x seeds, and their scores.

    python -m mixed_traffic.benchmark                      # every task, the bundled controllers
    python -m mixed_traffic.benchmark --tasks ring-v2 --policies idm follower-stopper

Each episode (task, eval config, policy, seed) runs through the one episode runner and is
appended atomically to ``out`` as it ends, tagged ``benchmark``; the scores, the table
(``table.md``) and the report go beside it (``--update-reference``: the table into
docs/benchmark.md and the report over reports/benchmark.pdf); a re-run skips the episodes
the same code already recorded (also after kill -9). ``idm`` (all human) is always run: it is
the score's 0. The score of a policy on a seed is the mean over the task's eval configs of
``(v - v_human) / (v_ref - v_human)`` on its metric (the fleet's mean speed), with ``v_ref``
the ring's uniform flow or, elsewhere, the free flow of the measured road
(:mod:`mixed_traffic.benchmark.score`); the table gives its mean over seeds with a 95 %
t-interval, next to the mean speed, speed std, fuel, DT-TF and terminal events.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from analysis.benchmark_report import TABLE_BEGIN, build, markdown, update_table
from analysis.results import mean_ci, nonneg_mean_ci
from mixed_traffic.benchmark import TASKS, Task, get_task, task_config
from mixed_traffic.benchmark.score import free_flow_speed, normalised, uniform_flow_speed
from mixed_traffic.experiments.cli import add_config_args, config_from_args
from mixed_traffic.experiments.runner import check_policy, run_copies
from mixed_traffic.experiments.safety_matrix import terminal_events
from mixed_traffic.paths import RESULTS, reference
from mixed_traffic.provenance import (
    atomic_write,
    check_writable,
    current_code_key,
    file_digest,
    read_records,
    sumo_version,
    write_record_atomic,
)

#: The committed PPO runs, whose training curves the report shows.
PPO_RUNS = Path(__file__).resolve().parents[2] / "agents" / "checkpoints" / "ppo"
#: The committed references that ``--update-reference`` rewrites (relative to the checkout).
REPORT, TABLE_DOC = "reports/benchmark.pdf", "docs/benchmark.md"

#: Columns next to the score: record metrics averaged over eval configs and seeds.
COLUMNS = ("mean_speed", "speed_std", "fuel", "dt_tf")


@dataclass(frozen=True)
class BenchmarkConfig:
    """What the table runs. The CLI is built from it."""

    tasks: tuple[str, ...] = ()
    """Task ids (default: every task of ``TASKS``)."""
    policies: tuple[str, ...] = ("acc-lc-tuned", "follower-stopper", "pi-saturation", "auto",
                                 "ppo-ring", "auto-ring")  # fmt: skip
    """Controllers scored (``idm``, all human, always runs as the score's 0)."""
    seeds: tuple[int, ...] = (0, 1, 2)
    """Root seeds, one episode per eval config each."""
    copies: int = 1
    """Copies of each eval config in one simulation (batched worlds): each copy is a replicate
    of its own, next to the seeds (a seed's copy i pairs with the same copy of the others)."""
    episode_length: float = 0.0
    """Simulated time per episode [s]; 0 = each task's horizon."""
    workers: int = 2
    """Parallel worker processes."""
    out: Path = RESULTS / "benchmark" / "records.jsonl"
    """Records (one JSON line per episode); the scores go next to it as ``scores.json``, the
    table as ``table.md``."""
    report: Path | None = None
    """The PDF report, its PNGs beside it (default: benchmark.pdf beside the records)."""
    update_reference: bool = False
    """Write the committed references: the table into docs/benchmark.md (between its markers)
    and the report over reports/benchmark.pdf."""
    runs: tuple[Path, ...] = ()
    """PPO run folders whose training curves the report shows (default: the committed runs,
    every folder of agents/checkpoints/ppo)."""

    def __post_init__(self) -> None:
        names = tuple(get_task(t).name for t in self.tasks) or tuple(TASKS)
        object.__setattr__(self, "tasks", names)
        policies = tuple(dict.fromkeys(("idm", *map(check_policy, self.policies))))
        object.__setattr__(self, "policies", policies)
        if not self.seeds or any(s < 0 for s in self.seeds):
            raise ValueError(f"--seeds={list(self.seeds)}: give seeds >= 0")
        if self.episode_length < 0 or self.workers < 1 or self.copies < 1:
            raise ValueError("--episode-length must be >= 0, --workers and --copies >= 1")
        check_writable(self.out)
        if self.update_reference and self.report is not None:
            raise ValueError("--update-reference writes the reference report: drop --report")
        if self.update_reference and TABLE_BEGIN not in reference(TABLE_DOC).read_text():
            raise ValueError(f"--update-reference: {TABLE_DOC} has lost its table markers")
        if self.report is None:
            pdf = (
                reference(REPORT) if self.update_reference else self.out.with_name("benchmark.pdf")
            )
            object.__setattr__(self, "report", pdf)
        if not self.runs:
            object.__setattr__(
                self, "runs", tuple(sorted(p for p in PPO_RUNS.glob("*") if p.is_dir()))
            )


def _key(task: str, index: int, policy: str, seed: int, length: float, copy: int = 0,
         copies: int = 1) -> tuple:  # fmt: skip
    return (task, index, policy, seed, length, copy, copies)


def jobs(cfg: BenchmarkConfig) -> list[tuple]:
    """Every (task, eval index, policy, seed, episode length, copy 0, copies) of the table:
    one simulation each."""
    out = []
    for name in cfg.tasks:
        for index in range(len(TASKS[name].eval)):
            out += [_key(name, index, p, s, cfg.episode_length, 0, cfg.copies)
                    for p in cfg.policies for s in cfg.seeds]  # fmt: skip
    return out


def _copies_of(job: tuple) -> list[tuple]:
    """The keys of a job's records, one per copy."""
    return [(*job[:5], c, job[6]) for c in range(job[6])]


def run_job(job: tuple) -> list[dict[str, Any]]:
    """The records of one simulation (one per copy), each tagged with its key."""
    name, index, policy, seed, length, _, copies = job
    extra = {"episode_length": length} if length else {}
    config = task_config(name, "eval", index, seed=seed, copies=copies, **extra)
    records = run_copies(config, policy, TASKS[name].warmup)
    for c, record in enumerate(records):
        record["benchmark"] = {"task": name, "index": index, "policy": policy, "seed": seed,
                               "episode_length": length, "copy": c, "copies": copies}  # fmt: skip
    return records


def _current(record: dict[str, Any], digests: dict[str, str]) -> bool:
    """The record ran this code and, for a learned policy, the weights now at its checkpoint
    path (a retrained ``ppo_ring.zip`` runs again); ``digests`` caches each file's digest."""
    path = record.get("checkpoint")
    if path and path not in digests:
        digests[path] = file_digest(path) if Path(path).is_file() else ""
    if path and digests[path] != record.get("checkpoint_sha"):
        return False
    return record.get("code") == current_code_key() and record.get("status") == "ok"


def _done(cfg: BenchmarkConfig) -> dict[tuple, dict[str, Any]]:
    """This code's finished records of ``out`` by job."""
    found, digests = {}, {}
    for r in read_records(cfg.out):
        b = r.get("benchmark")
        if b and _current(r, digests):
            found[_key(b["task"], b["index"], b["policy"], b["seed"], b["episode_length"],
                       b.get("copy", 0), b.get("copies", 1))] = r  # fmt: skip
    return found


def run_table(cfg: BenchmarkConfig, progress: bool = True) -> dict[tuple, dict[str, Any]]:
    """Run the missing episodes (``workers`` at a time); every job's record."""
    done = _done(cfg)
    todo = [j for j in jobs(cfg) if not all(k in done for k in _copies_of(j))]
    with ProcessPoolExecutor(max_workers=cfg.workers) as pool:
        for k, (job, records) in enumerate(zip(todo, pool.map(run_job, todo)), 1):
            for key, record in zip(_copies_of(job), records):
                write_record_atomic(cfg.out, record)
                done[key] = record
            if progress:
                print(f"  [{k}/{len(todo)}] {job[0]} eval {job[1]}, {job[2]}, seed {job[3]}: "
                      f"{records[0]['status']}", file=sys.stderr)  # fmt: skip
    return {key: done[key] for j in jobs(cfg) for key in _copies_of(j)}


def _terminal(record: dict[str, Any]) -> int:
    """AV trips ended by a terminal event, plus collisions without an AV (each collision once:
    an AV's is also its ``terminal_collision``)."""
    m = record.get("metrics") or {}
    events = terminal_events(m)
    return sum(events.values()) + max(0, int(m.get("collisions") or 0) - events.get("collision", 0))


def _metric(record: dict[str, Any], name: str) -> float:
    value = (record.get("metrics") or {}).get(name)
    return math.nan if value is None else float(value)


def scores(cfg: BenchmarkConfig, records: dict[tuple, dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per task and controller: score (mean, 95 % half-width, replicates: seeds, or
    (seed, copy) pairs), the columns' means, the speed std as a share of all-human traffic's on
    the same replicate and config (mean, 95 % log-scale interval, which stays >= 0) and the
    terminal events."""
    rows = []
    reps = [(s, c) for s in cfg.seeds for c in range(cfg.copies)]
    for name in cfg.tasks:
        task, n = TASKS[name], len(TASKS[name].eval)

        def rec(i: int, p: str, r: tuple[int, int], name: str = name) -> dict[str, Any]:
            return records[_key(name, i, p, r[0], cfg.episode_length, r[1], cfg.copies)]

        value = {(i, p, r): _metric(rec(i, p, r), task.metric)
                 for i in range(n) for p in cfg.policies for r in reps}  # fmt: skip
        std = {(i, p, r): _metric(rec(i, p, r), "speed_std")
               for i in range(n) for p in cfg.policies for r in reps}  # fmt: skip
        events = {p: sum(_terminal(rec(i, p, r)) for i in range(n) for r in reps)
                  for p in cfg.policies}  # fmt: skip
        refs = [_reference(task, i) for i in range(n)]
        for p in cfg.policies:
            per_rep = [np.mean([normalised(value[i, p, r], value[i, "idm", r], refs[i])
                                for i in range(n)]) for r in reps]  # fmt: skip
            score, half, count = mean_ci(per_rep)
            cols = {c: mean_ci([_metric(rec(i, p, r), c) for i in range(n) for r in reps])[0]
                    for c in COLUMNS}  # fmt: skip
            ratio, ratio_lo, ratio_hi, _ = nonneg_mean_ci(
                [np.mean([std[i, p, r] / std[i, "idm", r] for i in range(n)]) for r in reps]
            )
            rows.append({"task": name, "policy": p, "score": score,
                         "score_half_width": half, "seeds": count, **cols,
                         "std_ratio": ratio, "std_ratio_lo": ratio_lo, "std_ratio_hi": ratio_hi,
                         "terminal_events": events[p], "references": refs})  # fmt: skip
    return rows


def _reference(task: Task, index: int) -> float:
    """Score 1 of one eval config: the ring's uniform flow or the road's free flow."""
    config = task.eval[index]
    if task.reference == "uniform-flow":
        return uniform_flow_speed(config, config.ring_length[0])
    return free_flow_speed(config)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m mixed_traffic.benchmark",
                                description=__doc__.split("\n\n")[0])  # fmt: skip
    add_config_args(p, BenchmarkConfig)
    try:
        cfg = config_from_args(p.parse_args(argv), BenchmarkConfig)
    except ValueError as e:
        p.error(str(e))
    rows = scores(cfg, run_table(cfg))
    text = json.dumps(rows, indent=1).encode()
    atomic_write(cfg.out.with_name("scores.json"), lambda f: f.write(text))
    table = markdown(rows)
    build(rows, cfg.runs, cfg.report, notes=[_provenance(cfg)])
    atomic_write(cfg.out.with_name("table.md"), lambda f: f.write(f"{table}\n".encode()))
    if cfg.update_reference:
        update_table(reference(TABLE_DOC), table)
        print(f"updated the table in {TABLE_DOC}", file=sys.stderr)
    print(table)
    print(f"report: {cfg.report}", file=sys.stderr)
    return 0


def _provenance(cfg: BenchmarkConfig) -> str:
    """One line: what the table ran, on which code and SUMO."""
    return (
        f"Seeds {list(cfg.seeds)}, each task's horizon"
        f"{'' if not cfg.episode_length else f' cut to {cfg.episode_length:g} s'}; code "
        f"{current_code_key()}, SUMO {sumo_version()}. Score: 0 = all-human traffic, 1 = the "
        "ring's uniform flow or elsewhere the free flow of the measured road (its limit); "
        "mean over each task's held-out configs, then over seeds with a 95 % t-interval. "
        "Columns: means over configs and seeds; terminal events summed."
    )
