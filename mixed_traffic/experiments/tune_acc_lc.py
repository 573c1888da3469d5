"""Tune ACC-LC per scenario family: the ``acc-lc-tuned`` baseline (issue 42).

Every setting of a grid over the time gap T, the share of the limit it aims at
(``speed_factor``) and its maximum acceleration ``a`` runs on each family's default **train**
variant at ``penetration`` AVs, one episode per seed. A setting is admissible when none of its
episodes has a terminal event or a collision; the admissible setting with the highest mean
speed of all vehicles in the measurement segment (the fleet's, not the AVs') wins, after it
also drives without a terminal event or collision at ``check_penetration`` (a full fleet has
no human to absorb a short gap), else the next one. A family the tuning did not cover (a
user's network) gets the ``default``: the setting admissible in every family whose speed,
as a share of each family's best, is highest on average.

    python -m mixed_traffic.experiments.tune_acc_lc            # every family, then the file
    python -m mixed_traffic.experiments.tune_acc_lc --families straight merge --choose-only
    python -m mixed_traffic.experiments.tune_acc_lc --verify   # the choice on held-out cells

``--verify`` runs the whole grid and ``acc-lc-tuned`` on held-out eval variants on other
seeds, and tests on paired seeds whether the tuned setting is within noise of, or better
than, the best grid point there (by the same criterion, the fleet's mean speed).

Cells run through the sweep machinery (parallel, resumable: a re-run skips recorded cells)
into ``OUT/<scenario>/``; the choice goes atomically to ``OUT/acc_lc_tuned.json`` after every
family, with the table it was made from (``--update-reference``: over the shipped
``agents/checkpoints/acc_lc_tuned.json``, which ``acc-lc-tuned`` drives with).
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from agents.rules.spec import parse_policy
from agents.rules.tuned import TUNED_FIELDS, TUNED_FILE
from analysis.stats import paired_difference
from mixed_traffic.experiments.cli import add_config_args, config_from_args
from mixed_traffic.experiments.sweep import SweepConfig, run_sweep
from mixed_traffic.paths import RESULTS
from mixed_traffic.provenance import (
    atomic_write,
    current_code_key,
    git_revision,
    now_iso,
    read_records,
    sumo_version,
)
from mixed_traffic.schema import TERMINAL_REASONS
from mixed_traffic.world.registry import list_scenarios, load_scenario

CRITERION = (
    "highest mean speed of all vehicles in the measurement segment (metric mean_speed), mean "
    "over the family's train variant and seeds, among settings without a terminal event or "
    "collision in any episode, also at the check penetration"
)


@dataclass(frozen=True)
class TuneConfig:
    """The grid, the cells it runs on and where the choice goes. The CLI is built from it."""

    families: tuple[str, ...] = ()
    """Scenario families to tune (default: every family with a train variant)."""
    T: tuple[float, ...] = (1.0, 1.1, 1.2, 1.4)
    """Time gaps of the grid [s]."""
    speed_factor: tuple[float, ...] = (0.95, 1.0)
    """Desired speeds of the grid as a share of the limit [-]."""
    a: tuple[float, ...] = (1.5, 2.0, 2.5)
    """Maximum accelerations of the grid [m/s²] (AUTO's learned change was +0.65 m/s²)."""
    penetration: float = 0.5
    """AV share of the grid's cells [0-1]."""
    check_penetration: float = 1.0
    """AV share at which the chosen setting must also be safe [0-1]."""
    seeds: tuple[int, ...] = (0, 1)
    """Root seeds, one episode each per cell (the eval checks use others)."""
    episode_length: float = 150.0
    """Simulated time per episode [s]."""
    warmup: float = 30.0
    """Time before flow metrics are recorded [s]."""
    workers: int = 2
    """Parallel worker processes."""
    out: Path = RESULTS / "tune-acc-lc"
    """Folder of the cells' records, one subfolder per scenario."""
    file: Path | None = None
    """Where the choice goes (JSON; default: acc_lc_tuned.json in ``out``)."""
    update_reference: bool = False
    """Write the choice over the shipped agents/checkpoints/acc_lc_tuned.json, the parameters
    acc-lc-tuned drives with."""
    choose_only: bool = False
    """Choose from the records already in ``out`` without running cells."""
    verify: bool = False
    """Instead of tuning: check the stored choice against the grid on ``verify_scenarios``."""
    verify_scenarios: tuple[str, ...] = ("straight-eval", "merge-eval")
    """Held-out scenarios of the check."""
    verify_seeds: tuple[int, ...] = (10, 11, 12, 13)
    """Seeds of the check (paired across settings; apart from the tuning's)."""

    def __post_init__(self) -> None:
        for name in ("T", "speed_factor", "a", "seeds", "verify_seeds"):
            if not getattr(self, name):
                raise ValueError(f"--{name.replace('_', '-')}: give at least one value")
        for p in self.grid():  # each grid point must be a valid ACC-LC
            parse_policy(p)
        if self.update_reference and self.file is not None:
            raise ValueError("--update-reference writes the shipped file: drop --file")
        if self.file is None:
            file = TUNED_FILE if self.update_reference else self.out / TUNED_FILE.name
            object.__setattr__(self, "file", file)
        known = sorted({load_scenario(n).family for n in list_scenarios()})
        for f in self.families:
            if f not in known:
                raise ValueError(f"--families: unknown family {f!r}; known: {known}")

    def grid(self) -> list[str]:
        """The grid's policy specs."""
        points = itertools.product(self.T, self.speed_factor, self.a)
        return [str(parse_policy(f"acc-lc:T={t},speed_factor={v},a={a}")) for t, v, a in points]

    def sweep(self, scenario: str, policies: tuple[str, ...], penetration: float,
              seeds: tuple[int, ...] = ()) -> SweepConfig:  # fmt: skip
        """The sweep of ``policies`` on ``scenario`` at ``penetration`` (default seeds:
        the tuning's)."""
        return SweepConfig(
            axis="penetration", scenario=scenario, values=(penetration,), reference=False,
            policies=policies, seeds=seeds or self.seeds, episode_length=self.episode_length,
            warmup=self.warmup, workers=self.workers, out=self.out / scenario, report=False,
            traffic=False,
        )  # fmt: skip


def tuned_variant(family: str) -> str:
    """The train variant a family is tuned on: its default, else its first train variant."""
    names = [n for n in list_scenarios() if load_scenario(n).family == family]
    train = [n for n in names if load_scenario(n).split == "train"]
    if not train:
        raise ValueError(f"family {family!r} has no train variant to tune on")
    return family if family in train else sorted(train)[0]


def setting_table(records: list[dict[str, Any]], penetration: float) -> dict[str, dict[str, Any]]:
    """Per policy spec at ``penetration``: mean speed [m/s] over its ok episodes, their count,
    and its terminal events + collisions (a failed episode counts as unsafe)."""
    out: dict[str, dict[str, Any]] = {}
    for r in records:
        cell = r.get("cell", {})
        if cell.get("penetration") != penetration:
            continue
        row = out.setdefault(cell["policy"], {"speeds": [], "events": 0, "failed": 0})
        if r.get("status") != "ok":
            row["failed"] += 1
            continue
        m = r["metrics"]
        row["speeds"].append(m.get("mean_speed"))
        row["events"] += sum(int(m.get(f"terminal_{k}") or 0) for k in TERMINAL_REASONS)
        row["events"] += int(m.get("collisions") or 0)
    return {
        p: {"mean_speed": float(np.mean(v["speeds"])) if v["speeds"] else None,
            "episodes": len(v["speeds"]), "events": v["events"], "failed": v["failed"]}
        for p, v in out.items()
    }  # fmt: skip


def admissible(row: dict[str, Any], seeds: int) -> bool:
    """Every seed ran, none failed, and no terminal event or collision happened."""
    return row["episodes"] == seeds and not row["failed"] and row["events"] == 0


def ranked(table: dict[str, dict[str, Any]], seeds: int) -> list[str]:
    """Admissible specs, fastest first."""
    ok = [p for p, row in table.items() if admissible(row, seeds)]
    return sorted(ok, key=lambda p: -table[p]["mean_speed"])


def tune_family(cfg: TuneConfig, family: str) -> dict[str, Any]:
    """Run (or read) the grid on the family's train variant and choose its setting."""
    scenario = tuned_variant(family)
    grid = tuple(cfg.grid())
    if not cfg.choose_only:
        run_sweep(cfg.sweep(scenario, grid, cfg.penetration), progress=True)
    records = read_records(cfg.out / scenario / "records.jsonl")
    table = setting_table(records, cfg.penetration)
    order = [p for p in ranked(table, len(cfg.seeds)) if p in grid]
    checked: dict[str, dict[str, Any]] = {}
    for start in range(0, len(order), 3):  # the check, three candidates at a time
        batch = tuple(order[start : start + 3])
        if not cfg.choose_only:
            run_sweep(cfg.sweep(scenario, batch, cfg.check_penetration), progress=True)
        records = read_records(cfg.out / scenario / "records.jsonl")
        checked.update(setting_table(records, cfg.check_penetration))
        passed = [p for p in batch if p in checked and admissible(checked[p], len(cfg.seeds))]
        if passed:
            return _entry(scenario, passed[0], table, checked)
    raise RuntimeError(f"no setting of the grid is safe on {scenario}: see {cfg.out / scenario}")


def _entry(scenario: str, spec: str, table: dict, checked: dict) -> dict[str, Any]:
    params = parse_policy(spec).overrides
    return {
        "params": {k: params[k] for k in TUNED_FIELDS},
        "scenario": scenario,
        "mean_speed": table[spec]["mean_speed"],
        "table": {p: table[p] for p in sorted(table)},
        "check": {p: checked[p] for p in sorted(checked)},
    }


def default_choice(families: dict[str, dict[str, Any]], seeds: int) -> dict[str, Any]:
    """The setting admissible in every family with the highest mean share of each family's
    best admissible speed (a family's chosen setting must also have passed its check there)."""
    scores: dict[str, list[float]] = {}
    for entry in families.values():
        table = entry["table"]
        best = max(table[p]["mean_speed"] for p in ranked(table, seeds))
        for p in ranked(table, seeds):
            scores.setdefault(p, []).append(table[p]["mean_speed"] / best)
    common = [p for p, s in scores.items() if len(s) == len(families)]
    if not common:
        raise RuntimeError("no setting of the grid is admissible in every tuned family")
    spec = max(common, key=lambda p: float(np.mean(scores[p])))
    params = parse_policy(spec).overrides
    return {"params": {k: params[k] for k in TUNED_FIELDS},
            "mean_share_of_best": float(np.mean(scores[spec]))}  # fmt: skip


def write_choice(cfg: TuneConfig, families: dict[str, dict[str, Any]]) -> None:
    """The tuned file, atomically (earlier families of the file that were not re-tuned stay)."""
    data = {
        "criterion": CRITERION,
        "grid": {"T": list(cfg.T), "speed_factor": list(cfg.speed_factor), "a": list(cfg.a)},
        "penetration": cfg.penetration, "check_penetration": cfg.check_penetration,
        "seeds": list(cfg.seeds), "episode_length": cfg.episode_length, "warmup": cfg.warmup,
        "families": families, "default": default_choice(families, len(cfg.seeds)),
        "created": now_iso(), "git_revision": git_revision(), "code": current_code_key(),
        "sumo_version": sumo_version(),
        "command": "python -m mixed_traffic.experiments.tune_acc_lc " + " ".join(sys.argv[1:]),
    }  # fmt: skip
    text = json.dumps(data, indent=1, sort_keys=False).encode()
    cfg.file.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(cfg.file, lambda f: f.write(text))


def _previous(cfg: TuneConfig) -> dict[str, dict[str, Any]]:
    """Families of an existing tuned file made with the same grid and cells."""
    try:
        old = json.loads(cfg.file.read_text())
    except (OSError, json.JSONDecodeError):
        return {}
    same = old.get("grid") == {"T": list(cfg.T), "speed_factor": list(cfg.speed_factor),
                               "a": list(cfg.a)} and old.get("seeds") == list(cfg.seeds)  # fmt: skip
    return dict(old.get("families", {})) if same else {}


def verify(cfg: TuneConfig) -> list[dict[str, Any]]:
    """Per scenario of ``verify_scenarios``: the best admissible grid point by mean speed on
    the verify seeds, and ``acc-lc-tuned`` minus it on paired seeds (mean speed [m/s] and
    AvgDT-A [s/km], 95 % t-intervals); ``pass`` when the tuned one is within noise of, or
    better than, the best."""
    grid = tuple(cfg.grid())
    rows = []
    for scenario in cfg.verify_scenarios:
        sweep = cfg.sweep(scenario, (*grid, "acc-lc-tuned"), cfg.penetration, cfg.verify_seeds)
        records = [r for r in read_records(run_sweep(sweep)) if r["status"] == "ok"]
        table = setting_table(records, cfg.penetration)
        best = next(p for p in ranked(table, len(cfg.verify_seeds)) if p in grid)
        diff = {
            m: paired_difference(_per_seed(records, "acc-lc-tuned", m), _per_seed(records, best, m))
            for m in ("mean_speed", "avg_dt_a")
        }  # fmt: skip
        speed = diff["mean_speed"]
        rows.append({"scenario": scenario, "best_grid_point": best,
                     "tuned_minus_best": {m: [d.mean, d.half_width, d.n] for m, d in diff.items()},
                     "tuned_events": table.get("acc-lc-tuned", {}).get("events"),
                     "pass": bool(speed.mean + speed.half_width >= 0)})  # fmt: skip
    return rows


def _per_seed(records: list[dict[str, Any]], policy: str, metric: str) -> pd.Series:
    """(seeds,) ``metric`` of ``policy``'s episodes, indexed by seed."""
    mine = [r for r in records if r["cell"]["policy"] == policy]
    return pd.Series([r["metrics"][metric] for r in mine], index=[r["cell"]["seed"] for r in mine],
                     dtype=float)  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m mixed_traffic.experiments.tune_acc_lc",
                                description=__doc__.split("\n\n")[0])  # fmt: skip
    add_config_args(p, TuneConfig)
    try:
        cfg = config_from_args(p.parse_args(argv), TuneConfig)
    except ValueError as e:
        p.error(str(e))
    if cfg.verify:
        rows = verify(cfg)
        print("\n".join(json.dumps(r) for r in rows))
        return 0 if all(r["pass"] for r in rows) else 1
    names = cfg.families or sorted(
        {load_scenario(n).family for n in list_scenarios() if load_scenario(n).split == "train"}
    )
    families = _previous(cfg)
    for family in names:
        print(f"tuning {family} on {tuned_variant(family)}", file=sys.stderr)
        families[family] = tune_family(cfg, family)
        write_choice(cfg, families)
        print(f"{family}: {families[family]['params']}", file=sys.stderr)
    print(json.dumps({f: e["params"] for f, e in families.items()}))
    print(f"wrote {cfg.file}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
