"""Evaluate a policy over episodes and record flow and safety metrics (DESIGN §9, §11).

    python -m mixed_traffic.evaluate --policy idm --scenario straight --density 120 \\
        --penetration 0 --seeds 0 1 2 [--episode-length 120] [--warmup 30] [--json]

The episode length and warm-up default to the scenario's own where its spec gives them
(wave-highway: 420 s after 120 s, so that its queue reaches the measured segment), else 120 s
and 30 s.

prints a metrics table (one column per seed, plus the mean), appends one record per episode to
``--out`` (JSON lines, layout in ``mixed_traffic.schema``, atomic writes) and, with ``--json``,
prints the records as JSON lines on stdout (the table then goes to stderr). Episodes run in
``runner.run_episode``, as in every study; ``idm`` is the all-human reference (SUMO drives the
AVs).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from agents.policies import checkpoint_path
from mixed_traffic.config import EnvConfig
from mixed_traffic.experiments.cli import add_config_args, config_from_args, policy_arg
from mixed_traffic.experiments.runner import (
    DEFAULT_WARMUP,
    cell_of,
    check_checkpoint,
    run_copies,
    validate,
)
from mixed_traffic.provenance import check_writable, record_meta, write_record_atomic
from mixed_traffic.schema import LEARNED, METRICS
from mixed_traffic.world.backend import SumoError

DEFAULT_OUT = Path("results/evaluate/records.jsonl")
#: EnvConfig fields exposed as options, in help order.
CONFIG_OPTIONS = [
    "scenario", "density", "ring_length", "ring_vehicles", "penetration", "weather",
    "episode_length", "step_length", "lateral_resolution", "backend", "v2x", "copies",
]  # fmt: skip


# --------------------------------------------------------------------------- output
#: How a metric without a value reads (the others: "-").
MISSING = {"wave_speed": "no waves"}


def _fmt(value: Any, missing: str = "-") -> str:
    if value is None:
        return missing
    if isinstance(value, float):
        return f"{value:.3g}" if abs(value) < 1000 else f"{value:.0f}"
    return str(value)


def metrics_table(records: list[dict[str, Any]]) -> str:
    """Plain-text table: one row per metric measured in any record, one column per seed + mean."""
    keys = [k for k in METRICS
            if k in MISSING or any(r["metrics"].get(k) is not None for r in records)]  # fmt: skip
    seeds = [f"seed {r['seed']}" + (f"/{r['cell']['copy']}" if r["config"].get("copies", 1) > 1
                                     else "") for r in records]  # fmt: skip
    head = ["metric", "unit", *seeds, "mean"]
    rows = []
    for k in keys:
        vals = [r["metrics"].get(k) for r in records]
        nums = [v for v in vals if isinstance(v, (int, float))]
        mean = float(np.mean(nums)) if nums else None
        shown = [_fmt(v, MISSING.get(k, "-")) for v in (*vals, mean)]
        rows.append([METRICS[k].label, METRICS[k].unit, *shown])
    rings = [r.get("ring_length") for r in records]  # drawn per seed from a range
    if any(v is not None for v in rings):
        nums = [v for v in rings if v is not None]
        rows.append(["ring length", "m", *map(_fmt, rings), _fmt(float(np.mean(nums)))])
    di = [r.get("diagnostics", {}).get("delay_index_crossed_mean") for r in records]
    if any(v is not None for v in di):
        nums = [v for v in di if v is not None]
        rows.append(["DI (crossed)", "-", *map(_fmt, di), _fmt(float(np.mean(nums)))])
    widths = [max(len(str(x)) for x in col) for col in zip(head, *rows)]
    line = "  ".join(
        h.ljust(w) if i < 2 else h.rjust(w) for i, (h, w) in enumerate(zip(head, widths))
    )
    out = [line, "-" * len(line)]
    for row in rows:
        cells = (c.ljust(w) if i < 2 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths)))
        out.append("  ".join(cells))
    return "\n".join(out)


# --------------------------------------------------------------------------- CLI
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m mixed_traffic.evaluate",
        description="Run episodes of a policy and report flow and safety metrics (DESIGN §9).",
    )
    parser.add_argument(
        "--policy", type=policy_arg, default="idm",
        help="policy driving the AVs; idm = all-human reference (default: idm)",
    )  # fmt: skip
    add_config_args(parser, EnvConfig, only=CONFIG_OPTIONS, group_title="environment")
    parser.add_argument(
        "--seeds", type=int, nargs="+", default=[EnvConfig.seed], metavar="SEED",
        help="root seeds, one episode each (default: 0)",
    )  # fmt: skip
    parser.add_argument(
        "--warmup", type=float, default=None, metavar="S",
        help="simulated time before density and speed are averaged [s] (default: the "
        f"scenario's, {DEFAULT_WARMUP:g} s unless its spec gives one)",
    )  # fmt: skip
    parser.add_argument(
        "--out", type=Path, default=DEFAULT_OUT, metavar="FILE",
        help=f"records file, one JSON line per episode, appended (default: {DEFAULT_OUT})",
    )  # fmt: skip
    parser.add_argument(
        "--json", action="store_true", help="print the records as JSON lines on stdout"
    )
    parser.add_argument(
        "--checkpoint", type=Path, default=None, metavar="FILE",
        help="AUTO checkpoint for --policy auto (default: the shipped agents/checkpoints/auto.pt)",
    )  # fmt: skip
    parser.add_argument(
        "--gif", type=Path, default=None, metavar="FILE",
        help="record the (first) episode as an animated GIF (bird's-eye view)",
    )  # fmt: skip
    parser.add_argument(
        "--progress", action=argparse.BooleanOptionalAction, default=True,
        help="show progress bars: over the seeds, and over the steps of a single episode "
        "(default: on)",
    )  # fmt: skip
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        configs = [config_from_args(args, EnvConfig, seed=s) for s in args.seeds]
        configs, warmups = zip(*(validate(c, args.warmup, args.policy) for c in configs))
        if args.checkpoint is not None and args.policy not in LEARNED:
            raise ValueError(f"--checkpoint is used by a learned policy (auto, auto-raw, ppo, ppo-ring or a "
                             f"study policy), not {args.policy!r}")  # fmt: skip
        if args.policy in LEARNED:  # before any episode, not as a failed record after it
            check_checkpoint(checkpoint_path(args.policy, args.checkpoint))
        check_writable(args.out)
        if args.gif is not None:
            check_writable(args.gif, what="GIF")
    except (ValueError, KeyError) as e:
        parser.error(str(e).strip("'\""))
    records: list[dict[str, Any]] = []
    failed = 0
    bar = not args.progress or len(configs) == 1 or None  # None: only on a terminal
    for cfg, warmup in tqdm(list(zip(configs, warmups)), desc="episodes", disable=bar):
        try:
            extra = {"checkpoint": args.checkpoint, "gif": args.gif if cfg is configs[0] else None,
                     "progress": args.progress and len(configs) == 1 and sys.stderr.isatty()}  # fmt: skip
            batch = run_copies(cfg, args.policy, warmup, **extra)
        except (SumoError, ValueError) as e:  # e.g. SUMO failed, or a bad checkpoint
            print(f"error: seed {cfg.seed}: {e}", file=sys.stderr)
            failed += 1
            batch = [{"cell": {**cell_of(cfg, args.policy), "copy": c}, "status": "failed",
                      "error": str(e), **record_meta(cfg), "metrics": {}}
                     for c in range(cfg.copies)]  # fmt: skip
        for record in batch:
            write_record_atomic(args.out, record)
        records += [r for r in batch if r["status"] == "ok"]
    if records:
        table = metrics_table(records)
        header = (
            f"policy={args.policy} scenario={configs[0].scenario} density={configs[0].density} "
            f"veh/km penetration={configs[0].penetration} episode={configs[0].episode_length} s "
            f"warmup={warmups[0]} s  records -> {args.out}"
        )
        print(header + "\n" + table, file=sys.stderr if args.json else sys.stdout)
    if args.json:
        for r in records:
            print(json.dumps(r, allow_nan=False))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
