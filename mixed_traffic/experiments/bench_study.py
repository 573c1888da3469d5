"""Section ``study`` of ``python -m mixed_traffic.bench``: the default study's wall time against
its SUMO-only floor, measured in one run.

The study is ``python -m mixed_traffic.sweep --penetration`` with its defaults (every policy,
penetration and seed, the all-human reference and traffic cells, then the PDF report), run into
a scratch folder. The floor runs the same cells (same scenario, penetration, density, seed and
episode length, the same number of worker processes) with SUMO driving every vehicle, AVs
included (policy ``idm``), and writes no report: what the study would cost if the AVs' whole
pipeline (perception, observation, policy, control, metrics) were free.

The limit runs the same cells again with SUMO stepping, the state read (the env's snapshot and
boundary) and every AV's command written each step (a set speed and a lateral move, the calls
the controller makes), but no env stage. SUMO's step is dearer with commanded AVs than with
the floor's human-typed ones (issue 45: 1.4-2x), so ``ratio_to_limit``, the study over the
limit, is the share the pipeline owns. The limit's AVs keep SUMO's safety (speed mode 31) and
are commanded 1 m/s above their speed, so they drive near their safe speed.
"""

from __future__ import annotations

import argparse
import shutil
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from mixed_traffic.config import EnvConfig
from mixed_traffic.paths import scratch_dir


@dataclass
class StudyResult:
    cells: int
    """Episodes in each run (the study's cells and the traffic cells)."""
    study_s: float
    """Wall time of the study: its cells and its report [s]."""
    report_s: float
    """Of which the report (figures and PDF) [s]."""
    floor_s: float
    """Wall time of the same cells with SUMO driving every vehicle [s]."""
    limit_s: float
    """Wall time of the same cells with SUMO stepping, the state read and the AVs' commands
    written, and no env stage [s]."""

    @property
    def ratio(self) -> float:
        """Study over floor [-] (target: at most 1.5)."""
        return self.study_s / self.floor_s

    @property
    def ratio_to_limit(self) -> float:
        """Study over limit [-]: what the pipeline owns (target: at most 1.3)."""
        return self.study_s / self.limit_s

    def record(self) -> dict[str, float | int]:
        return {"section": "study", "cells": self.cells, "study_s": round(self.study_s, 1),
                "report_s": round(self.report_s, 1), "floor_s": round(self.floor_s, 1),
                "ratio": round(self.ratio, 3), "limit_s": round(self.limit_s, 1),
                "ratio_to_limit": round(self.ratio_to_limit, 3)}  # fmt: skip


def study_sweep(args: argparse.Namespace, out: Path):  # -> SweepConfig
    """The default penetration study into ``out``; ``--study-seeds`` and ``--study-episode``
    shrink it (for tests and quick looks)."""
    from mixed_traffic.experiments.sweep import SweepConfig

    cfg = SweepConfig(axis="penetration", out=out, workers=args.study_workers)
    if args.study_seeds:
        cfg = replace(cfg, seeds=tuple(range(args.study_seeds)))
    if args.study_episode:
        cfg = replace(cfg, episode_length=args.study_episode,
                      warmup=min(cfg.warmup, args.study_episode / 2))  # fmt: skip
    return cfg


def floor_cells(sweep) -> list:
    """Every cell the study runs (its traffic cells too), each with SUMO driving."""
    from mixed_traffic.experiments.sweep import cells, fd_sweep

    todo = cells(sweep) + (cells(fd_sweep(sweep)) if sweep.traffic else [])
    return [replace(c, policy="idm") for c in todo]


def limit_episode(config: EnvConfig) -> tuple[int, int]:
    """One cell of the limit (module docstring): no env stage, every AV commanded each step;
    (AV commands written, collisions)."""
    from mixed_traffic.env.parallel import MixedTrafficEnv

    env = MixedTrafficEnv(config=config, sumo_drives_avs=True, metrics=False)
    try:
        env.reset(seed=config.seed, options={"allow_no_agents": True})
        backend, t, safe, commands, collisions = env._backend, env.sim_time, set(), 0, 0
        while t < config.episode_length - 1e-9:
            snap = env._advance()  # SUMO's step, the snapshot and the boundary
            av = np.flatnonzero(snap.is_av)
            ids = [snap.ids[i] for i in av.tolist()]
            # an AV that entered has the env's speed mode, without SUMO's safety: release it
            backend.release_control([v for v in ids if v not in safe])
            safe.update(ids)
            backend.set_speeds(ids, snap.speed[av] + 1.0)
            backend.change_sublane(ids, np.zeros(len(ids)))
            commands += len(ids)
            collisions += len(snap.collisions)
            t = snap.time
    finally:
        env.close()
    return commands, collisions


def run_limit(configs: list[EnvConfig], workers: int, progress: bool = True) -> None:
    """Every config's :func:`limit_episode`, ``workers`` at a time, each in a fresh process
    forked as the sweep's cells are (one SUMO per process)."""
    from mixed_traffic.experiments.sweep import cell_context

    ctx = cell_context(learned=False)
    with ProcessPoolExecutor(workers, mp_context=ctx, max_tasks_per_child=1) as pool:
        jobs = [pool.submit(limit_episode, c) for c in configs]
        for job in tqdm(as_completed(jobs), total=len(jobs), desc="study limit", unit="episode",
                        disable=not progress):  # fmt: skip
            job.result()


def run_study_and_floor(sweep, progress: bool = True) -> StudyResult:
    """Time the study (cells, then report), its floor, then its limit, in this order in one
    process."""
    from analysis.report import build_report
    from mixed_traffic.experiments.sweep import cell_config, run_cells, run_sweep

    todo = floor_cells(sweep)
    t0 = time.perf_counter()
    run_sweep(sweep, progress)
    t1 = time.perf_counter()
    build_report(sweep.results, sweep.report_pdf)
    t2 = time.perf_counter()
    floor = replace(sweep, out=sweep.results.parent / "floor", policies=("idm",), traffic=False,
                    report=False, checkpoint=None)  # fmt: skip
    run_cells(todo, floor, progress)
    t3 = time.perf_counter()
    run_limit([cell_config(c, sweep) for c in todo], sweep.workers, progress)
    t4 = time.perf_counter()
    return StudyResult(cells=len(todo), study_s=t2 - t0, report_s=t2 - t1, floor_s=t3 - t2,
                       limit_s=t4 - t3)  # fmt: skip


def section_study(args: argparse.Namespace) -> list[StudyResult]:
    """The study and its floor in a scratch folder (removed afterwards)."""
    out = Path(scratch_dir())
    try:
        result = run_study_and_floor(study_sweep(args, out / "study"), progress=True)
    finally:
        shutil.rmtree(out, ignore_errors=True)
    print(f"study: {result.cells} cells x 3; study {result.study_s:.0f} s (report "
          f"{result.report_s:.0f} s), SUMO-only floor {result.floor_s:.0f} s, ratio "
          f"{result.ratio:.2f} (target <= 1.5); limit {result.limit_s:.0f} s, ratio_to_limit "
          f"{result.ratio_to_limit:.2f} (target <= 1.3)", flush=True)  # fmt: skip
    return [result]
