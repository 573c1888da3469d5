"""Benchmarks (speed only; tests never assert wall-clock times).

    python -m mixed_traffic.bench [--section snapshot] [--steps N] [--densities 60 120 180]

Section ``snapshot``: on ``straight`` at each density, one simulation alternates blocks of
steps in two modes, both doing identical work so the traffic is the same:

* *raw*: ``backend.raw_step()`` is timed (bare ``simulationStep``), then ``backend.collect()``
  runs untimed so the boundary condition can keep the density;
* *step*: ``backend.step()`` (simulationStep + events + full snapshot) is timed.

Blocks come in adjacent (raw, step) pairs; per pair the mean ms/step of each mode, their ratio
and the snapshot cost per vehicle are computed, and the median over pairs is reported (robust to
load from other processes on a small machine). Target: the
snapshot adds ≤ 30 % to a raw step. Sections are functions in ``SECTIONS`` so others can add
theirs.

Section ``env`` is in ``bench_env``, ``soak`` (memory over a 600 s episode) in ``bench_soak``,
``throughput`` (learner samples per core on batched worlds) in ``bench_throughput``;
``inference`` times AUTO's batched forward pass, ``learner`` the RBP-DQN update
(``agents.bench_learner``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mixed_traffic.config import EnvConfig
from mixed_traffic.experiments.bench_env import PENETRATIONS, section_env
from mixed_traffic.experiments.bench_scale import AV_LADDER, section_scale
from mixed_traffic.experiments.bench_soak import section_soak
from mixed_traffic.experiments.bench_study import section_study
from mixed_traffic.experiments.bench_throughput import add_arguments as throughput_arguments
from mixed_traffic.experiments.bench_throughput import section_throughput
from mixed_traffic.paths import scratch_dir
from mixed_traffic.world.backend import SumoBackend
from mixed_traffic.world.boundary import PeriodicBoundary
from mixed_traffic.world.demand import make_demand, write_demand
from mixed_traffic.world.registry import load_scenario
from mixed_traffic.world.scenario import sumo_args

DENSITIES = (60.0, 120.0, 180.0)
TARGET_OVERHEAD = 0.30


@dataclass
class SnapshotResult:
    density: float
    """Target density [veh/km]."""
    raw_ms: float
    """Median over blocks of the bare simulationStep [ms/step]."""
    step_ms: float
    """Median over blocks of backend.step() [ms/step]."""
    ratio: float
    """Median over block pairs of step / raw [-]."""
    us_per_vehicle: float
    """Median over block pairs of (step - raw) / vehicles: snapshot cost per vehicle [µs]."""
    vehicles: float
    """Mean vehicles in the network."""
    blocks: int


def start_straight(
    density: float, backend_kind: str = "libsumo", seed: int = 0, episode_length: float = 3600.0
) -> tuple[SumoBackend, PeriodicBoundary]:
    """A running ``straight`` simulation at ``density`` with its periodic boundary (sublane on)."""
    cfg = EnvConfig(
        scenario="straight", density=density, penetration=0.0, seed=seed,
        episode_length=episode_length, backend=backend_kind,
    )  # fmt: skip
    sc = load_scenario(cfg.scenario)
    hd = sc.hdmap
    demand = make_demand(sc, cfg, np.random.default_rng(seed))
    route_file = Path(scratch_dir()) / "demand.rou.xml"
    write_demand(demand, cfg, route_file)
    backend = SumoBackend(cfg.backend, cfg.second_instance)
    backend.set_lane_table(hd.lane_ids, hd.lane_edge)
    backend.start(sumo_args(sc, cfg, route_file, seed=seed))
    boundary = PeriodicBoundary.for_demand(sc, demand, cfg.human, cfg.step_length, False)
    return backend, boundary


def bench_snapshot_density(
    density: float, steps: int, block: int = 20, warm: int = 100, backend_kind: str = "libsumo"
) -> SnapshotResult:
    """Alternate raw/step blocks of ``block`` steps for ``steps`` timed steps in total."""
    backend, boundary = start_straight(density, backend_kind)
    clock = time.perf_counter
    try:
        for _ in range(warm):
            boundary.step(backend.step(), backend)
        raw_blocks: list[float] = []
        step_blocks: list[float] = []
        n_veh: list[int] = []
        veh_blocks: list[float] = []
        n_blocks = max(2, steps // block) // 2 * 2
        for b in range(n_blocks):
            timed = 0.0
            if b % 2 == 0:
                for _ in range(block):
                    t0 = clock()
                    backend.raw_step()
                    timed += clock() - t0
                    snap = backend.collect()
                    boundary.step(snap, backend)
                raw_blocks.append(timed / block)
            else:
                for _ in range(block):
                    t0 = clock()
                    snap = backend.step()
                    timed += clock() - t0
                    boundary.step(snap, backend)
                    n_veh.append(snap.n)
                step_blocks.append(timed / block)
                veh_blocks.append(float(np.mean(n_veh[-block:])))
    finally:
        backend.close()
    pairs = list(zip(raw_blocks, step_blocks, veh_blocks))
    return SnapshotResult(
        density=density,
        raw_ms=statistics.median(raw_blocks) * 1e3,
        step_ms=statistics.median(step_blocks) * 1e3,
        ratio=statistics.median(s / r for r, s, _ in pairs),
        us_per_vehicle=statistics.median((s - r) * 1e6 / max(v, 1.0) for r, s, v in pairs),
        vehicles=float(np.mean(n_veh)),
        blocks=n_blocks,
    )


def section_snapshot(args: argparse.Namespace) -> list[SnapshotResult]:
    """Raw simulationStep vs backend step()+snapshot on straight at each density."""
    print(
        f"snapshot: straight, sublane on, {args.backend}, {args.steps} timed steps per density "
        f"in alternating blocks of {args.block} (median of blocks)"
    )
    head = f"{'veh/km':>7} {'vehicles':>9} {'raw ms':>8} {'step ms':>8} {'ratio':>6} {'us/veh':>7}  target"
    print(head)
    print("-" * len(head))
    results = []
    for density in args.densities:
        r = bench_snapshot_density(density, args.steps, args.block, backend_kind=args.backend)
        ok = "ok" if r.ratio <= 1 + TARGET_OVERHEAD else f"MISSED (> {1 + TARGET_OVERHEAD:.2f})"
        print(
            f"{r.density:>7.0f} {r.vehicles:>9.0f} {r.raw_ms:>8.3f} {r.step_ms:>8.3f} "
            f"{r.ratio:>6.3f} {r.us_per_vehicle:>7.2f}  {ok}",
            flush=True,
        )
        results.append(r)
    return results


def section_inference(args: argparse.Namespace) -> float:
    """AvgIT: AUTO's batched forward (actor + critic + masked selection) per decision, 128
    agents on one core, observations already built (paper: 8.96 ms per decision on a GPU)."""
    from agents.bench_inference import avg_inference_us

    us = avg_inference_us(n_agents=128, threads=1)
    print(f"inference: AUTO batched forward, 128 agents, 1 thread: {us:.1f} us per decision "
          f"(target <= 20 us; CPU time, best of 7)")  # fmt: skip
    sm = avg_inference_us(n_agents=128, threads=1, safety=True)
    print(f"inference: the same plus the safety module (ACC-LC checks): {sm:.1f} us per decision")
    return us


def section_learner(args: argparse.Namespace) -> object:
    """RBP-DQN learner updates/s and samples/s vs the pre-issue-22 code, side by side (issue 22:
    target >= 300 updates/s at batch 128, or the same samples/s)."""
    from agents.bench_learner import run

    return run(args.learner_batch, args.learner_threads, args.learner_blocks,
               args.learner_block_seconds, args.learner_json, args.learner_compile)  # fmt: skip


#: Section name -> function(args). Other modules' sections are registered here.
SECTIONS: dict[str, Callable[[argparse.Namespace], object]] = {
    "snapshot": section_snapshot,
    "env": section_env,
    "inference": section_inference,
    "soak": section_soak,
    "learner": section_learner,
    "study": section_study,
    "scale": section_scale,
    "throughput": section_throughput,
}
JSON_SECTIONS = ("env", "study", "scale", "throughput")
"""Sections whose results ``--json`` prints, one JSON object a line."""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m mixed_traffic.bench",
        description="Speed benchmarks of the simulation stack.",
    )
    p.add_argument(
        "--section", choices=sorted(SECTIONS), nargs="+", default=sorted(SECTIONS),
        help="sections to run (default: all)",
    )  # fmt: skip
    p.add_argument(
        "--steps", type=int, default=2000, help="timed steps per density (default: 2000)"
    )
    p.add_argument(
        "--block", type=int, default=20, help="steps per alternating block (default: 20)"
    )
    p.add_argument(
        "--densities", type=float, nargs="+", default=list(DENSITIES), metavar="K",
        help="densities [veh/km, all lanes] (default: 60 120 180)",
    )  # fmt: skip
    p.add_argument(
        "--penetrations", type=float, nargs="+", default=list(PENETRATIONS), metavar="P",
        help="env section: AV penetrations (default: 0.2 0.5 1.0)",
    )  # fmt: skip
    p.add_argument(
        "--env-policy", choices=("random", "keep"), nargs="+", default=["random", "keep"],
        help="env section: action policies (default: both; see bench_actions)",
    )  # fmt: skip
    p.add_argument(
        "--env-density", type=float, default=120.0, help="env section: veh/km (default: 120)"
    )
    p.add_argument(
        "--env-steps", type=int, default=1000,
        help="env section: timed env steps per penetration (default: 1000)",
    )  # fmt: skip
    p.add_argument(
        "--env-episode", type=float, default=40.0,
        help="env section: simulated seconds between resets (default: 40)",
    )  # fmt: skip
    p.add_argument(
        "--soak-length", type=float, default=600.0,
        help="soak section: simulated seconds of the one episode (default: 600)",
    )  # fmt: skip
    p.add_argument(
        "--soak-density", type=float, default=180.0,
        help="soak section: veh/km, 100 %% AVs (default: 180)",
    )  # fmt: skip
    p.add_argument(
        "--learner-batch", type=int, nargs="+", default=[128, 1024], metavar="B",
        help="learner section: batch sizes (default: 128 1024)",
    )  # fmt: skip
    p.add_argument(
        "--learner-threads", type=int, nargs="+", default=[1, 2], metavar="T",
        help="learner section: torch thread counts (default: 1 2)",
    )  # fmt: skip
    p.add_argument(
        "--learner-blocks", type=int, default=6,
        help="learner section: timed blocks per learner and setting (default: 6)",
    )  # fmt: skip
    p.add_argument(
        "--learner-block-seconds", type=float, default=0.5,
        help="learner section: seconds per timed block (default: 0.5)",
    )  # fmt: skip
    p.add_argument(
        "--learner-json", default="", metavar="PATH",
        help="learner section: also write the results as JSON to PATH",
    )  # fmt: skip
    p.add_argument(
        "--learner-compile", action="store_true",
        help="learner section: time the learner with torch.compile (compiles first, ~1 min)",
    )  # fmt: skip
    p.add_argument(
        "--study-workers", type=int, default=2,
        help="study section: worker processes of the study and its floor (default: 2)",
    )  # fmt: skip
    p.add_argument(
        "--study-seeds", type=int, default=0,
        help="study section: run seeds 0..N-1 (default: the study's own, 0 1 2)",
    )  # fmt: skip
    p.add_argument(
        "--study-episode", type=float, default=0.0,
        help="study section: simulated seconds per episode (default: the study's own, 150)",
    )  # fmt: skip
    p.add_argument(
        "--scale-avs", type=int, nargs="+", default=list(AV_LADDER), metavar="N",
        help="scale section: AV counts to try on the long road, rising (default: 250 .. 4000)",
    )  # fmt: skip
    p.add_argument(
        "--scale-lanes", type=int, default=4, help="scale section: lanes of the road (default: 4)"
    )
    p.add_argument(
        "--scale-density", type=float, default=25.0,
        help="scale section: veh/km per lane on the road (default: 25)",
    )  # fmt: skip
    p.add_argument(
        "--scale-steps", type=int, default=50,
        help="scale section: timed env steps per AV count (default: 50)",
    )  # fmt: skip
    p.add_argument(
        "--city-grid", type=int, default=30,
        help="scale section: junctions per side of the city grid (default: 30)",
    )  # fmt: skip
    p.add_argument(
        "--city-density", type=float, default=12.0,
        help="scale section: veh/km per lane in the city (default: 12)",
    )  # fmt: skip
    p.add_argument(
        "--city-penetration", type=float, default=0.1,
        help="scale section: AV share in the city (default: 0.1)",
    )  # fmt: skip
    p.add_argument(
        "--city-episode", type=float, default=300.0,
        help="scale section: simulated seconds of the city episode (default: 300)",
    )  # fmt: skip
    throughput_arguments(p)
    p.add_argument(
        "--json", action="store_true",
        help=f"sections {', '.join(JSON_SECTIONS)} only: one JSON object per result on stdout, "
        "the tables on stderr",
    )  # fmt: skip
    p.add_argument(
        "--backend", choices=("libsumo", "traci"), default="libsumo",
        help="SUMO binding (default: libsumo)",
    )  # fmt: skip
    return p


#: Options that must be finite and > 0, and counts that must be >= 1.
_POSITIVE = ("densities", "env_density", "env_episode", "soak_length", "soak_density",
             "learner_block_seconds", "scale_density", "city_density", "city_episode",
             "city_penetration")  # fmt: skip
_COUNTS = ("env_steps", "learner_batch", "learner_threads", "learner_blocks", "study_workers",
           "scale_avs", "scale_lanes", "scale_steps", "throughput_copies", "throughput_decisions",
           "throughput_steps", "throughput_rollouts")  # fmt: skip


def check_args(args: argparse.Namespace) -> str | None:
    """The first out-of-range option as a one-line message naming it (None: all fine)."""
    for name in _POSITIVE + _COUNTS:
        values = getattr(args, name)
        for v in values if isinstance(values, list) else [values]:
            if name in _COUNTS and v < 1:
                return f"--{name.replace('_', '-')}={v} must be >= 1"
            if name in _POSITIVE and not (math.isfinite(v) and v > 0):
                return f"--{name.replace('_', '-')}={v} must be a finite number > 0"
    for name in ("study_seeds", "study_episode"):  # 0 = the study's own
        v = getattr(args, name)
        if not (math.isfinite(v) and v >= 0):
            return f"--{name.replace('_', '-')}={v} must be >= 0 (0: the study's default)"
    if args.city_grid < 2:
        return f"--city-grid={args.city_grid} must be >= 2"
    if args.city_penetration > 1:
        return f"--city-penetration={args.city_penetration} must be in (0, 1]"
    if any(not 0 < p <= 1 for p in args.penetrations):
        return f"--penetrations={args.penetrations}: each must be in (0, 1]"
    from mixed_traffic.benchmark.tasks import get_task

    for task in (*args.throughput_tasks, *args.throughput_ppo):
        try:
            get_task(task)
        except ValueError as e:
            return f"--throughput-tasks: {e}"
    return None


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.steps < 2 * args.block or args.block < 1:
        parser.error(f"--steps={args.steps} must be at least 2 x --block={args.block}")
    bad = check_args(args)
    if bad:  # before the first section, not when the section that uses it comes
        parser.error(bad)
    others = sorted(set(args.section) - set(JSON_SECTIONS))
    if args.json and others:
        parser.error(f"--json prints sections {', '.join(JSON_SECTIONS)}, not {', '.join(others)} "
                     "(the learner section has --learner-json)")  # fmt: skip
    if not args.json:
        for name in args.section:
            SECTIONS[name](args)
        return 0
    for name in args.section:
        with contextlib.redirect_stdout(sys.stderr):
            results = SECTIONS[name](args)
        for r in results:
            print(json.dumps(r.record()), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
