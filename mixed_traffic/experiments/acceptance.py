"""Check an AUTO checkpoint against the "done when" list of issue 43 (held-out eval variants),
which extends issue 22's.

    python -m mixed_traffic.experiments.acceptance --checkpoint runs/auto/auto.pt

Each check runs its cells through :mod:`mixed_traffic.experiments.sweep` (parallel, cached by
code and checkpoint content, resumable) and compares paired seeds with 95 % t-intervals
(:func:`analysis.stats.paired_difference`):

- ``dt_gain``: AUTO's AvgDT-A gain over the ``baseline`` rule (``acc-lc-tuned``) [%] on
  straight-eval and merge-eval at 50 % AVs: at least 3 % and the interval excludes 0 (the
  gain over the default ACC-LC is shown beside it);
- ``auto_mean``: ``auto-mean`` (AUTO with its continuous parameters replaced by their mean over
  ``runner.REFERENCE_STATES``) keeps at most half of that gain: the gain is behaviour, not a
  constant;
- ``at_c``: AvgAT-C (AUTO − the baseline) not significantly above 0;
- ``terminal``: no terminal event of AUTO in those cells;
- ``sm_share``: the safety module changes at most 10 % of AUTO's actions;
- ``raw_terminal``: ``auto-raw`` at 100 % AVs ends at most 0.2 % of its AV trips in a terminal
  event on both;
- ``dt_tf``: on straight at 120 veh/km, DT-TF with 100 % AUTO is at most the all-human one;
- ``ring_std``, ``ring_speed``, ``ring_wake``: one AV (``ring_policy``: ``auto``, or the
  ring-family ``auto-ring``) among 22 vehicles on the ``ring-v2`` task's eval rings (210 and
  280 m, lengths no training uses), 300 s from t = 0: the speed std at most half the all-human
  one, the mean speed at least FollowerStopper's, and ``speed_std_behind`` below
  ``speed_std_ahead``;
- ``wave``: on ``wave-highway-eval`` at 5 % AVs (the ``wave-highway-v1`` task's eval: 420 s,
  warm-up 120 s; a checkpoint trained with V2X reads it), AUTO lowers the speed std by at least
  20 % and fuel by at least 5 % against all-human traffic, with DT-TF at most 2 % worse.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from analysis.stats import paired_difference
from mixed_traffic.experiments.cli import add_config_args, check_table, config_from_args
from mixed_traffic.experiments.compare import content_key
from mixed_traffic.experiments.runner import check_checkpoint, check_policy
from mixed_traffic.experiments.sweep import SweepConfig, run_sweep
from mixed_traffic.provenance import FolderBusyError, current_code_key, read_records

EVAL = ("straight-eval", "merge-eval")
RING_POLICIES = ("auto", "auto-ring")
CHECK_GROUPS = ("eval", "dt_tf", "ring", "wave")
"""The check groups ``--checks`` takes (``CHECKS`` runs each)."""


@dataclass(frozen=True)
class AcceptanceConfig:
    """The checkpoint and how many episodes back each check."""

    checkpoint: Path | None = None
    """AUTO checkpoint to check (default: the shipped agents/checkpoints/auto.pt)."""
    seeds: tuple[int, ...] = (0, 1, 2, 3, 4, 5)
    """Root seeds; every cell runs once per seed (paired across policies)."""
    episode_length: float = 150.0
    """Simulated time per episode on the open roads [s] (the ring runs 300 s)."""
    warmup: float = 30.0
    """Time before flow metrics are recorded [s]."""
    workers: int = 2
    """Parallel worker processes."""
    out: Path = Path("results/acceptance")
    """Records folder; a re-run skips the episodes already recorded with the same code."""
    baseline: str = "acc-lc-tuned"
    """The rule AUTO is compared with: a policy name or spec (acc-lc:T=1.0,...)."""
    checks: tuple[str, ...] = CHECK_GROUPS
    """Check groups to run: eval (dt_gain, auto_mean, at_c, terminal, sm_share, raw_terminal),
    dt_tf, ring (ring_std, ring_speed, ring_wake), wave."""
    ring_policy: str = "auto"
    """The ring checks' policy: auto (the checkpoint checked) or auto-ring (the shipped
    ring-family checkpoint of the same learner)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "baseline", check_policy(self.baseline))
        if not self.checks or not set(self.checks) <= set(CHECK_GROUPS):
            raise ValueError(f"--checks {' '.join(self.checks)}: choose from "
                             f"{' '.join(CHECK_GROUPS)}")  # fmt: skip
        if self.ring_policy not in RING_POLICIES:
            raise ValueError(f"--ring-policy {self.ring_policy}: choose from {RING_POLICIES}")
        if len(self.seeds) < 2:
            raise ValueError(f"--seeds: {list(self.seeds)} gives no interval; give at least 2")
        if self.checkpoint is not None:
            check_checkpoint(self.checkpoint)

    @property
    def path(self) -> Path:
        """The checkpoint file checked."""
        from agents.policies import SHIPPED_CHECKPOINT

        return self.checkpoint if self.checkpoint is not None else SHIPPED_CHECKPOINT

    def records(self, name: str, scenario: str, policies: tuple[str, ...],
                penetration: float, density: float | None = None, length: float | None = None,
                reference: bool = False, **sweep_kw: Any) -> pd.DataFrame:  # fmt: skip
        """Run (or reuse) one cell per policy and seed (``reference``: plus the all-human
        ``idm`` cell at 0 %) → one row per episode: policy, seed and the record's metrics.
        ``sweep_kw``: other :class:`SweepConfig` fields (warmup, ring_length, checkpoint)."""
        folder = self.out / f"code-{current_code_key()}" / content_key(self.path) / name
        sweep = SweepConfig(**{
            "scenario": scenario, "at_density": density, "values": (penetration,),
            "reference": reference, "policies": policies, "seeds": self.seeds,
            "episode_length": length or self.episode_length, "warmup": self.warmup,
            "checkpoint": self.path, "workers": self.workers, "out": folder, "report": False,
            "traffic": False, **sweep_kw,
        })  # fmt: skip
        rows = [{"policy": r["cell"]["policy"], "seed": r["cell"]["seed"], **r["metrics"]}
                for r in read_records(run_sweep(sweep, progress=False))
                if r["status"] == "ok" and r["cell"]["seed"] in self.seeds]  # fmt: skip
        return pd.DataFrame(rows)


def _by_seed(df: pd.DataFrame, policy: str, metric: str) -> pd.Series:
    rows = df[df["policy"] == policy]
    return pd.Series(rows[metric].astype(float).to_numpy(), index=rows["seed"].to_numpy())


def _terminal(df: pd.DataFrame, policy: str) -> float:
    cols = [c for c in df.columns if c.startswith("terminal_")]
    return float(df.loc[df["policy"] == policy, cols].fillna(0).to_numpy().sum())


def _row(check: str, where: str, value: str, passed: bool) -> dict:
    return {"check": check, "where": where, "value": value, "pass": bool(passed)}


def eval_checks(cfg: AcceptanceConfig) -> list[dict]:
    """:func:`eval_rows` of each eval variant."""
    out = []
    for sc in EVAL:
        policies = tuple(dict.fromkeys(("auto", "auto-mean", cfg.baseline, "acc-lc")))
        half = cfg.records(f"{sc}-50", sc, policies, 0.5)
        raw = cfg.records(f"{sc}-100-raw", sc, ("auto-raw",), 1.0)
        out += eval_rows(sc, half, raw, cfg.baseline)
    return out


def eval_rows(where: str, half: pd.DataFrame, raw: pd.DataFrame, baseline: str) -> list[dict]:
    """dt_gain, auto_mean, at_c, terminal and sm_share from the 50 % episodes ``half`` (auto,
    auto-mean, the ``baseline`` rule and the default acc-lc), raw_terminal from the 100 %
    ``auto-raw`` episodes ``raw``."""
    base = _by_seed(half, baseline, "avg_dt_a")
    gain, plain = (paired_difference(100 * (1 - _by_seed(half, "auto", "avg_dt_a") / b), 0 * b)
                   for b in (base, _by_seed(half, "acc-lc", "avg_dt_a")))  # fmt: skip
    kept = paired_difference(100 * (1 - _by_seed(half, "auto-mean", "avg_dt_a") / base), 0 * base)
    at = paired_difference(_by_seed(half, "auto", "avg_at_c"), _by_seed(half, baseline, "avg_at_c"))
    term = _terminal(half, "auto")
    share = float(half.loc[half["policy"] == "auto", "sm_share"].mean())  # [%]
    trips = float(raw["av_trips"].sum())
    rate = 100 * _terminal(raw, "auto-raw") / trips if trips else math.nan  # [%]
    return [
        _row("dt_gain", where, f"{gain.mean:+.2f} ± {gain.half_width:.2f} % over {baseline} "
             f"(n={gain.n}; over acc-lc {plain.mean:+.2f} ± {plain.half_width:.2f} %)",
             gain.mean >= 3 and gain.mean - gain.half_width > 0),
        _row("auto_mean", where, f"auto-mean gains {kept.mean:+.2f} ± {kept.half_width:.2f} % "
             f"(AUTO {gain.mean:+.2f} %)", gain.mean > 0 and kept.mean <= 0.5 * gain.mean),
        _row("at_c", where, f"{at.mean:+.3f} ± {at.half_width:.3f} s", at.mean - at.half_width <= 0),
        _row("terminal", where, f"{term:g} events", term == 0),
        _row("sm_share", where, f"{share:.1f} %", share <= 10),
        _row("raw_terminal", where, f"{rate:.2f} % of {trips:g} trips", rate <= 0.2),
    ]  # fmt: skip


def dt_tf_checks(cfg: AcceptanceConfig) -> list[dict]:
    """dt_tf on straight at 120 veh/km: 100 % auto against all-human traffic."""
    return dt_tf_rows(
        cfg.records("straight-120", "straight", ("auto",), 1.0, density=120.0, reference=True)
    )


def dt_tf_rows(full: pd.DataFrame) -> list[dict]:
    """dt_tf from ``full`` (100 % auto and all-human idm episodes)."""
    d = paired_difference(_by_seed(full, "auto", "dt_tf"), _by_seed(full, "idm", "dt_tf"))
    return [_row("dt_tf", "straight 120 veh/km", f"{d.mean:+.2f} ± {d.half_width:.2f} s/km "
                 "(100 % AUTO − all human)", d.mean - d.half_width <= 0)]  # fmt: skip


def ring_checks(cfg: AcceptanceConfig) -> list[dict]:
    """:func:`ring_rows` of one ``ring_policy`` AV on each ring-v2 eval ring (22 vehicles,
    300 s from t = 0)."""
    from mixed_traffic.benchmark import get_task

    rings = []
    for ring in get_task("ring-v2").eval:
        length = ring.ring_length[0]
        rings.append(cfg.records(
            f"ring-{length:g}", "ring", (cfg.ring_policy, "follower-stopper"), ring.penetration,
            density=ring.ring_vehicles / (length / 1000), length=ring.episode_length,
            reference=True, warmup=0.0, ring_length=length,
            checkpoint=cfg.path if cfg.ring_policy == "auto" else None,
        ).assign(ring=length))  # fmt: skip
    return ring_rows(pd.concat(rings, ignore_index=True), cfg.ring_policy)


def ring_rows(ring: pd.DataFrame, policy: str = "auto") -> list[dict]:
    """ring_std, ring_speed and ring_wake from ``ring`` (``policy``, follower-stopper and idm
    episodes, a ``ring`` column naming each one's length)."""
    ring = ring.assign(seed=ring["seed"].astype(str) + "@" + ring["ring"].astype(str))
    idm = _by_seed(ring, "idm", "speed_std")
    std = paired_difference(_by_seed(ring, policy, "speed_std") / idm, 0 * idm)
    speed = {p: _by_seed(ring, p, "mean_speed").mean() for p in (policy, "follower-stopper")}
    wake = {k: _by_seed(ring, policy, f"speed_std_{k}").mean() for k in ("ahead", "behind")}
    where = f"ring-v2 eval rings, 1 {policy}"
    return [
        _row("ring_std", where, f"speed std {std.mean:.2f} ± {std.half_width:.2f} of all "
             f"human's (n={std.n})", std.mean <= 0.5),
        _row("ring_speed", where, f"mean speed {speed[policy]:.2f} m/s vs FollowerStopper "
             f"{speed['follower-stopper']:.2f}", speed[policy] >= speed["follower-stopper"]),
        _row("ring_wake", where, f"speed std behind {wake['behind']:.2f} vs ahead "
             f"{wake['ahead']:.2f} m/s", wake["behind"] < wake["ahead"]),
    ]  # fmt: skip


def wave_checks(cfg: AcceptanceConfig) -> list[dict]:
    """:func:`wave_rows` of the wave-highway-v1 task's eval (5 % AVs, 420 s, warm-up 120 s)."""
    from mixed_traffic.benchmark import get_task

    task = get_task("wave-highway-v1")
    road = task.eval[0]
    waves = cfg.records("wave-highway-eval", road.scenario, ("auto",), road.penetration,
                        length=road.episode_length, reference=True, warmup=task.warmup)  # fmt: skip
    return wave_rows(waves)


def wave_rows(wave: pd.DataFrame) -> list[dict]:
    """wave from ``wave`` (auto and idm episodes): AUTO's mean ratios to all human."""
    ratio = {k: (_by_seed(wave, "auto", k) / _by_seed(wave, "idm", k)).mean()
             for k in ("speed_std", "fuel", "dt_tf")}  # fmt: skip
    return [
        _row("wave", "wave-highway-eval, 5 % AUTO", f"vs all human: speed std x"
             f"{ratio['speed_std']:.2f}, fuel x{ratio['fuel']:.2f}, DT-TF x{ratio['dt_tf']:.3f}",
             ratio["speed_std"] <= 0.8 and ratio["fuel"] <= 0.95 and ratio["dt_tf"] <= 1.02),
    ]  # fmt: skip


CHECKS = dict(zip(CHECK_GROUPS, (eval_checks, dt_tf_checks, ring_checks, wave_checks)))
"""The function of each check group."""


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m mixed_traffic.experiments.acceptance",
        description="Check an AUTO checkpoint against issue 43's done list on the held-out "
        "eval variants (paired seeds, 95 % t-intervals).",
    )
    add_config_args(p, AcceptanceConfig)
    p.add_argument("--json", action="store_true", help="print the checks as JSON")
    args = p.parse_args(argv)
    try:
        cfg = config_from_args(args, AcceptanceConfig)
    except ValueError as e:
        p.error(str(e))
    try:
        rows = [row for name in cfg.checks for row in CHECKS[name](cfg)]
    except FolderBusyError as e:
        p.error(str(e))
    print(json.dumps(rows, indent=1) if args.json else check_table(rows))
    return 0 if all(r["pass"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
