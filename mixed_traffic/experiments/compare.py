"""Choose among AUTO checkpoints on the train split, relative to the tuned ACC-LC.

    python -m mixed_traffic.compare runs/ft6 agents/checkpoints/auto.pt

A run folder stands for its ``snapshots/*.pt`` and ``auto.pt``. Every checkpoint drives the
``auto`` policy (network behind the safety module) in the same cells as the ``baseline`` rule
(``acc-lc-tuned`` unless given; "ACC-LC" below): train-split scenarios only, so the held-out
eval variants stay unseen until the final table. Per cell the score is AUTO's AvgDT-A excess
over ACC-LC's [%] (mean over seeds); a checkpoint's rank is its
largest excess over the cells, so no single scenario (urban's long trips) dominates the choice;
checkpoints whose largest excess is within ``tie`` points of the best one's (seed noise) are
ordered by their mean excess instead. A checkpoint with a terminal event (collision, leaving
the road, ...) or a failed episode is ranked last. Records go to ``OUT/<density, length,
warm-up>/code-<code hash>/<policy or checkpoint content hash>/<scenario>/records.jsonl`` through
:mod:`mixed_traffic.experiments.sweep`, so an interrupted comparison resumes where it stopped and a
checkpoint compared before is not run again. The cache is also keyed by the code
(``provenance.code_key``: the Python sources, shipped checkpoint and scenarios), so after a
change to the env, perception or ACC-LC every episode, ACC-LC's included, runs again.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from agents.rules.spec import parse_policy
from mixed_traffic.experiments.cli import add_config_args, config_from_args
from mixed_traffic.experiments.runner import check_checkpoint, check_policy
from mixed_traffic.experiments.sweep import SweepConfig, run_sweep
from mixed_traffic.provenance import FolderBusyError, check_folder, current_code_key, read_records
from mixed_traffic.world.registry import train_split_scenario

TRAIN_CELLS = ("merge-ramp", "bottleneck-3to2", "urban-grid3x3", "highway-curves", "straight-3lane")


@dataclass(frozen=True)
class CompareConfig:
    """Cells in which checkpoints are compared with ACC-LC."""

    scenarios: tuple[str, ...] = TRAIN_CELLS
    """Train-split scenarios (held-out eval variants are refused)."""
    density: float | None = None
    """Traffic density [veh/km, all lanes] (default: each scenario's, 120 veh/km unless its spec gives
    one)."""
    penetrations: tuple[float, ...] = (0.2, 1.0)
    """AV penetrations [0-1]."""
    seeds: tuple[int, ...] = (100, 101)
    """Root seeds (apart from the eval table's 0-2)."""
    episode_length: float = 60.0
    """Simulated time per episode [s]."""
    warmup: float = 10.0
    """Time before flow metrics are recorded [s]."""
    workers: int = 2
    """Parallel worker processes."""
    tie: float = 0.5
    """Largest excesses within this of the lowest count as equal (seed noise); those checkpoints
    are ordered by their mean excess [percentage points]."""
    out: Path = Path("results/compare")
    """Records folder; a re-run skips episodes already recorded with the same code."""
    baseline: str = "acc-lc-tuned"
    """The rule the checkpoints are compared with: a policy name or spec (acc-lc:T=1.0,...)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "baseline", check_policy(self.baseline))
        if not (self.tie >= 0):
            raise ValueError(f"--tie: {self.tie} must be >= 0 percentage points")
        if not self.scenarios:
            raise ValueError("--scenarios: give at least one train-split scenario")
        for name in self.scenarios:
            try:
                train_split_scenario(name)
            except ValueError as e:
                raise ValueError(f"--scenarios: {e}") from None
        self.sweep(self.baseline, None, self.scenarios[0], Path("."))  # validates the rest

    @property
    def folder(self) -> Path:
        """Records of these settings and this code (seeds and penetrations are picked from
        them)."""
        density = "default" if self.density is None else f"{self.density:g}"
        cells = f"{density}vkm-{self.episode_length:g}s-w{self.warmup:g}"
        return self.out / cells / f"code-{current_code_key()}"

    def wanted(self, record: dict) -> bool:
        cell = record["cell"]
        return cell["seed"] in self.seeds and cell["penetration"] in self.penetrations

    def sweep(self, policy: str, checkpoint: Path | None, scenario: str, out: Path) -> SweepConfig:
        return SweepConfig(
            scenario=scenario, at_density=self.density, values=self.penetrations,
            reference=False, policies=(policy,), seeds=self.seeds,
            episode_length=self.episode_length, warmup=self.warmup, checkpoint=checkpoint,
            workers=self.workers, out=out, report=False, traffic=False,
        )  # fmt: skip


def expand(paths: list[Path]) -> list[Path]:
    """Checkpoint files; a folder stands for its snapshots/*.pt and auto.pt."""
    out: list[Path] = []
    for path in paths:
        if path.is_dir():
            found = sorted((path / "snapshots").glob("*.pt")) + sorted(path.glob("auto.pt"))
            if not found:
                raise ValueError(f"{path}: no snapshots/*.pt or auto.pt in this folder")
            out += found
        elif path.is_file():
            out.append(path)
        else:
            raise ValueError(f"{path}: no such checkpoint file or run folder")
    for path in out:  # an unreadable one must not rank (its cells would all fail)
        check_checkpoint(path)
    return out


def content_key(path: Path) -> str:
    """Records folder name of a checkpoint: its content hash (a rewritten file is new)."""
    return hashlib.sha256(path.read_bytes()).hexdigest()[:12]


def cell_means(records: list[dict]) -> dict[tuple[str, float], dict[str, float]]:
    """(scenario, penetration) -> mean AvgDT-A [s], terminal events and failed episodes."""
    groups: dict[tuple[str, float], list[dict]] = {}
    for r in records:
        groups.setdefault((r["cell"]["scenario"], r["cell"]["penetration"]), []).append(r)
    out = {}
    for key, rs in groups.items():
        ok = [r["metrics"] for r in rs if r["status"] == "ok"]
        dt = [m["avg_dt_a"] for m in ok if m.get("avg_dt_a") is not None]
        out[key] = {
            "avg_dt_a": float(np.mean(dt)) if dt else math.nan,
            "terminal": sum(v or 0 for m in ok for k, v in m.items() if k.startswith("terminal_")),
            "failed": len(rs) - len(ok),
        }
    return out


def score(auto: dict, acc: dict) -> dict:
    """Excess of AvgDT-A over ACC-LC per cell [%], its max and mean, and the safety guard."""
    excess = {k: 100 * (auto[k]["avg_dt_a"] / acc[k]["avg_dt_a"] - 1) if k in auto else math.nan
              for k in sorted(acc)}  # fmt: skip
    values = list(excess.values())
    unsafe = sum(c["terminal"] + c["failed"] for c in auto.values()) + sum(
        k not in auto for k in acc
    )
    return {
        "excess": excess,
        "max_excess": max(values) if not any(map(math.isnan, values)) else math.nan,
        "mean_excess": float(np.mean(values)),
        "unsafe": int(unsafe),
    }


def rank_key(s: dict) -> tuple:
    """Safe before unsafe, then the smallest largest excess (NaN last)."""
    return (s["unsafe"] > 0, math.isnan(s["max_excess"]), s["max_excess"])


def rank(scores: list[dict], tie: float) -> list[dict]:
    """Best first by :func:`rank_key`; safe checkpoints within ``tie`` of the best largest
    excess are reordered by their mean excess."""
    ordered = sorted(scores, key=rank_key)
    if not ordered or ordered[0]["unsafe"] or math.isnan(ordered[0]["max_excess"]):
        return ordered
    limit = ordered[0]["max_excess"] + tie
    near = [s for s in ordered if not s["unsafe"] and s["max_excess"] <= limit]
    return sorted(near, key=lambda s: s["mean_excess"]) + ordered[len(near) :]


def run(cfg: CompareConfig, checkpoints: list[Path], progress: bool = True) -> list[dict]:
    """Run the missing episodes; one score dict per checkpoint, best first."""
    base = cfg.baseline
    base_key = (
        base if base == parse_policy(base).base else hashlib.sha256(base.encode()).hexdigest()[:12]
    )
    jobs = [(base, None, base_key)] + [("auto", c, content_key(c)) for c in checkpoints]
    bar = tqdm(total=len(jobs) * len(cfg.scenarios), desc="compare", unit="scenario",
               disable=not progress)  # fmt: skip
    records: dict[str, list[dict]] = {}
    for policy, ckpt, key in jobs:
        for scenario in cfg.scenarios:
            bar.set_postfix_str(f"{ckpt or policy} {scenario}")
            sweep = cfg.sweep(policy, ckpt, scenario, cfg.folder / key / scenario)
            path = run_sweep(sweep, progress=False)
            records.setdefault(key, []).extend(r for r in read_records(path) if cfg.wanted(r))
            bar.update(1)
    bar.close()
    acc = cell_means(records[base_key])
    scores = [{"checkpoint": str(c), "key": k, **score(cell_means(records[k]), acc)}
              for _, c, k in jobs[1:]]  # fmt: skip
    return rank(scores, cfg.tie)


def table(scores: list[dict]) -> str:
    """One row per checkpoint (best first): excess per cell [%], max, mean, unsafe episodes."""
    cells = list(scores[0]["excess"])
    head = ["checkpoint", *(f"{s[:10]} {p:g}" for s, p in cells), "max %", "mean %", "unsafe"]
    rows = [[s["checkpoint"], *(f"{s['excess'][c]:+.1f}" for c in cells),
             f"{s['max_excess']:+.1f}", f"{s['mean_excess']:+.2f}", str(s["unsafe"])]
            for s in scores]  # fmt: skip
    widths = [max(len(r[i]) for r in [head, *rows]) for i in range(len(head))]
    return "\n".join("  ".join(v.rjust(w) for v, w in zip(r, widths, strict=True))
                     for r in [head, *rows])  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m mixed_traffic.compare",
        description="Rank AUTO checkpoints by their largest AvgDT-A excess over the tuned ACC-LC on "
        "train-split cells (safe ones first, near-ties by the mean excess); the best is "
        "printed last.",
    )
    p.add_argument("checkpoints", nargs="+", type=Path,
                   help="checkpoint files or training run folders (their snapshots and auto.pt)")  # fmt: skip
    add_config_args(p, CompareConfig)
    p.add_argument("--json", action="store_true", help="print the scores as JSON")
    args = p.parse_args(argv)
    try:
        cfg = config_from_args(args, CompareConfig)
        checkpoints = expand(args.checkpoints)
    except ValueError as e:
        p.error(str(e))
    try:
        check_folder(cfg.out)
    except ValueError as e:
        p.error(f"--out: {e}")
    try:
        scores = run(cfg, checkpoints)
    except FolderBusyError as e:
        p.error(str(e))
    print(json.dumps(scores, indent=1) if args.json else table(scores))
    print(f"best: {scores[0]['checkpoint']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
