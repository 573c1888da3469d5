"""Scalability sweeps over AV penetration, traffic density or weather (paper §V-G).

``python -m mixed_traffic.sweep --penetration`` runs every (policy, value, seed) cell in parallel
worker processes, appends each episode's record to ``RESULTS/records.jsonl`` as soon as it
finishes (atomically; a re-run skips cells already recorded), then writes figures and a PDF
report. Each cell runs in its own process: libsumo allows one simulation per process, and a
SUMO segfault then costs one cell (recorded as failed with its exit code), not the sweep.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
import time
import traceback
from dataclasses import asdict, dataclass
from pathlib import Path

from tqdm import tqdm

from mixed_traffic.config import EnvConfig
from mixed_traffic.provenance import read_records, record_meta, write_record_atomic
from mixed_traffic.schema import CELL_KEYS, POLICIES

PENETRATIONS = (0.2, 0.4, 0.6, 0.8, 1.0)
DENSITIES = (60.0, 120.0, 180.0)
WEATHERS = ("normal", "rain", "fog", "night")


@dataclass(frozen=True)
class SweepConfig:
    """One sweep: which axis, which cells, where results go."""

    axis: str = "penetration"
    """penetration | density | weather."""
    scenario: str = "straight"
    """Scenario name (see ``python -m mixed_traffic.scenario --list``)."""
    density: float = 120.0
    """Density for the penetration and weather sweeps [veh/km]."""
    penetration: float = 0.2
    """AV penetration for the density and weather sweeps [0-1]."""
    policies: tuple[str, ...] = ("auto", "acc-lc")
    """Policies to compare; the penetration sweep adds an all-IDM 0 % reference."""
    seeds: tuple[int, ...] = (0, 1, 2)
    """Root seeds; each cell runs once per seed."""
    episode_length: float = 150.0
    """Simulated time per episode [s]."""
    warmup: float = 30.0
    """Time before flow metrics are recorded [s]."""
    workers: int = 2
    """Parallel worker processes."""
    out: Path = Path("results/penetration")
    """Results folder (records.jsonl, figures)."""
    report: Path | None = None
    """PDF report path (default reports/<axis>.pdf)."""
    checkpoint: Path | None = None
    """AUTO checkpoint (default: the shipped agents/checkpoints/auto.pt)."""
    values: tuple[float, ...] | tuple[str, ...] = ()
    """Values of the swept axis (default: the paper's, see PENETRATIONS/DENSITIES/WEATHERS)."""
    reference: bool = True
    """Add the all-IDM 0 % reference to a penetration sweep."""
    backend: str = "process"
    """process (local worker processes) | ray (Ray tasks, local or on a cluster)."""
    address: str = ""
    """Ray cluster address for ray.init(address=...), e.g. 'auto' ('' = start Ray locally)."""

    def axis_values(self) -> tuple:
        default = {"penetration": PENETRATIONS, "density": DENSITIES, "weather": WEATHERS}[
            self.axis
        ]
        return self.values or default


@dataclass(frozen=True)
class Cell:
    policy: str
    scenario: str
    density: float
    penetration: float
    weather: str
    seed: int

    def key(self) -> tuple:
        return tuple(getattr(self, k) for k in CELL_KEYS)


def cells(sweep: SweepConfig) -> list[Cell]:
    """Every cell of the sweep, in a stable order (seed-major, so early results span the axis)."""
    base = dict(
        scenario=sweep.scenario,
        density=sweep.density,
        penetration=sweep.penetration,
        weather="normal",
    )
    out: list[Cell] = []
    for seed in sweep.seeds:
        if sweep.axis == "penetration" and sweep.reference:
            out.append(Cell("idm", **{**base, "penetration": 0.0}, seed=seed))
        for value in sweep.axis_values():
            out += [Cell(p, **{**base, sweep.axis: value}, seed=seed) for p in sweep.policies]
    return out


def cell_config(cell: Cell, sweep: SweepConfig) -> EnvConfig:
    return EnvConfig(
        scenario=cell.scenario,
        density=cell.density,
        penetration=cell.penetration,
        weather=cell.weather,
        seed=cell.seed,
        episode_length=sweep.episode_length,
    )


def episode_record(cell: Cell, sweep: SweepConfig) -> dict:
    """One episode of ``cell``: its record, or a failed record carrying the error."""
    try:
        from mixed_traffic.evaluate import run_episode

        config = cell_config(cell, sweep)
        record = run_episode(config, cell.policy, sweep.warmup, checkpoint=sweep.checkpoint)
    except Exception as e:  # any failure becomes a failed record; the sweep carries on
        return _failed(cell, sweep, f"{type(e).__name__}: {e}\n{traceback.format_exc(limit=3)}")
    record["cell"] = asdict(cell)
    return record


def _failed(cell: Cell, sweep: SweepConfig, error: str) -> dict:
    record = {**record_meta(cell_config(cell, sweep)), "status": "failed", "metrics": {}}
    record.update(error=error, cell=asdict(cell))
    return record


def _run_cell(cell: Cell, sweep: SweepConfig, queue: mp.Queue) -> None:
    """Worker process: one episode's record onto the queue."""
    queue.put(episode_record(cell, sweep))


def run_sweep(sweep: SweepConfig, progress: bool = True) -> Path:
    """Run the missing cells of ``sweep``; returns the records file."""
    sweep.out.mkdir(parents=True, exist_ok=True)
    records_path = sweep.out / "records.jsonl"
    done = {_cell_key(r) for r in read_records(records_path)}
    todo = [c for c in cells(sweep) if c.key() not in done]
    bar = tqdm(total=len(todo), desc=f"{sweep.axis} sweep", unit="episode", disable=not progress)
    if sweep.backend == "ray":
        _run_ray(todo, sweep, records_path, bar)
    else:
        _run_processes(todo, sweep, records_path, bar)
    bar.close()
    return records_path


def _run_processes(todo: list[Cell], sweep: SweepConfig, records_path: Path, bar: tqdm) -> None:
    """At most ``workers`` cells at a time, each in its own spawned process."""
    ctx = mp.get_context("spawn")
    queue: mp.Queue = ctx.Queue()
    running: dict[int, tuple[mp.Process, Cell, float]] = {}
    pending = list(todo)
    while pending or running:
        while pending and len(running) < sweep.workers:
            cell = pending.pop(0)
            proc = ctx.Process(target=_run_cell, args=(cell, sweep, queue), daemon=True)
            proc.start()
            running[proc.pid] = (proc, cell, time.time())
        _collect(queue, running, records_path, bar, sweep)


def _collect(
    queue: mp.Queue, running: dict, records_path: Path, bar: tqdm, sweep: SweepConfig
) -> None:
    """Write records that arrived; turn dead workers without a record into failed records."""
    try:
        record = queue.get(timeout=0.5)
    except Exception:
        record = None
    if record is not None:
        write_record_atomic(records_path, record)
        key = _cell_key(record)
        for pid, (proc, cell, _) in list(running.items()):
            if cell.key() == key:
                proc.join(timeout=10)
                del running[pid]
        _advance(bar, record)
        return
    for pid, (proc, cell, _) in list(running.items()):
        if not proc.is_alive() and proc.exitcode not in (None, 0) and queue.empty():
            failed = _failed(cell, sweep, f"worker process died with exit code {proc.exitcode}")
            write_record_atomic(records_path, failed)
            del running[pid]
            _advance(bar, failed)


def _run_ray(todo: list[Cell], sweep: SweepConfig, records_path: Path, bar: tqdm) -> None:
    """Each cell a Ray task (one CPU, no retries); a task whose worker dies is a failed record."""
    import ray

    owns = not ray.is_initialized()
    if owns:
        local_cpus = None if sweep.address else sweep.workers
        ray.init(address=sweep.address or None, num_cpus=local_cpus, log_to_driver=False)
    task = ray.remote(num_cpus=1, max_retries=0)(episode_record)
    try:
        futures = {task.remote(c, sweep): c for c in todo}
        while futures:
            ready, _ = ray.wait(list(futures), num_returns=1)
            cell = futures.pop(ready[0])
            try:
                record = ray.get(ready[0])
            except Exception as e:  # the worker process died (e.g. a SUMO segfault)
                record = _failed(cell, sweep, f"Ray task failed: {type(e).__name__}: {e}")
            write_record_atomic(records_path, record)
            _advance(bar, record)
    finally:
        if owns:
            ray.shutdown()


def _advance(bar: tqdm, record: dict) -> None:
    cell = record["cell"]
    bar.update(1)
    bar.set_postfix_str(f"{cell['policy']} p={cell['penetration']} {record['status']}")


def _cell_key(record: dict) -> tuple:
    cell = record.get("cell", {})
    return tuple(cell.get(k) for k in CELL_KEYS)


# --------------------------------------------------------------------------- CLI
def parse_args(argv: list[str] | None) -> SweepConfig:
    d = SweepConfig()
    p = argparse.ArgumentParser(
        prog="python -m mixed_traffic.sweep",
        description="Penetration / density / weather sweeps with figures and a PDF report.",
    )
    axis = p.add_mutually_exclusive_group()
    axis.add_argument("--penetration", dest="axis", action="store_const", const="penetration",
                      help=f"sweep AV penetration {PENETRATIONS} plus an all-IDM 0 %% reference (default)")  # fmt: skip
    axis.add_argument("--density", dest="axis", action="store_const", const="density",
                      help=f"sweep density {DENSITIES} veh/km")  # fmt: skip
    axis.add_argument("--weather", dest="axis", action="store_const", const="weather",
                      help=f"sweep the weather presets {WEATHERS}")  # fmt: skip
    p.add_argument("--scenario", default=d.scenario, help="scenario name or .net.xml/.sumocfg path")
    p.add_argument(
        "--at-density",
        type=float,
        default=d.density,
        help="density for penetration/weather sweeps [veh/km]",
    )
    p.add_argument(
        "--at-penetration",
        type=float,
        default=d.penetration,
        help="penetration for density/weather sweeps [0-1]",
    )
    p.add_argument(
        "--values", nargs="+", default=None,
        help="values of the swept axis (default: penetration 0.2 .. 1.0, density 60 120 180, all weathers)",
    )  # fmt: skip
    p.add_argument(
        "--no-reference", action="store_true", help="skip the all-IDM 0 %% reference cells"
    )
    p.add_argument(
        "--policies", nargs="+", default=list(d.policies), help=f"policies: {' '.join(POLICIES)}"
    )
    p.add_argument("--seeds", nargs="+", type=int, default=list(d.seeds), help="root seeds")
    p.add_argument(
        "--episode-length",
        type=float,
        default=d.episode_length,
        help="simulated seconds per episode",
    )
    p.add_argument(
        "--warmup", type=float, default=d.warmup, help="seconds before flow metrics count"
    )
    p.add_argument("--workers", type=int, default=d.workers, help="parallel worker processes")
    p.add_argument("--out", type=Path, default=None, help="results folder (default results/<axis>)")
    p.add_argument(
        "--report", type=Path, default=None, help="PDF path (default reports/<axis>.pdf)"
    )
    p.add_argument(
        "--checkpoint", type=Path, default=None, help="AUTO checkpoint (default: shipped)"
    )
    p.add_argument("--backend", choices=("process", "ray"), default=d.backend,
                   help="run cells in local worker processes or as Ray tasks")  # fmt: skip
    p.add_argument("--address", default=d.address,
                   help="with --backend ray: cluster address, e.g. auto (default: start Ray locally)")  # fmt: skip
    p.add_argument("--no-report", action="store_true", help="skip figures and the PDF")
    a = p.parse_args(argv)
    a.axis = a.axis or "penetration"
    bad = [x for x in a.policies if x not in POLICIES]
    if bad:
        p.error(f"unknown policies {bad}; choose from {list(POLICIES)}")
    if a.workers < 1:
        p.error(f"--workers={a.workers} must be >= 1")
    if a.address and a.backend != "ray":
        p.error("--address needs --backend ray")
    try:
        EnvConfig(scenario=a.scenario, density=a.at_density, penetration=a.at_penetration,
                  episode_length=a.episode_length)  # fmt: skip
    except ValueError as e:
        p.error(str(e))
    values: tuple = ()
    if a.values:
        try:
            values = tuple(a.values) if a.axis == "weather" else tuple(float(v) for v in a.values)
            for v in values:  # each value must make a valid config
                EnvConfig(**{"density": a.at_density, "penetration": a.at_penetration, a.axis: v})
        except ValueError as e:
            p.error(f"--values: {e}")
    if a.warmup < 0 or a.warmup >= a.episode_length:
        p.error(f"--warmup={a.warmup} must be in [0, episode length {a.episode_length})")
    sweep = SweepConfig(
        axis=a.axis,
        scenario=a.scenario,
        density=a.at_density,
        penetration=a.at_penetration,
        policies=tuple(a.policies),
        seeds=tuple(a.seeds),
        episode_length=a.episode_length,
        warmup=a.warmup,
        workers=a.workers,
        out=a.out or Path("results") / a.axis,
        report=None if a.no_report else (a.report or Path("reports") / f"{a.axis}.pdf"),
        checkpoint=a.checkpoint,
        values=values,
        reference=not a.no_reference,
        backend=a.backend,
        address=a.address,
    )
    return sweep


def main(argv: list[str] | None = None) -> int:
    sweep = parse_args(argv)
    t0 = time.time()
    records = run_sweep(sweep)
    print(f"records: {records} ({time.time() - t0:.0f} s)")
    if sweep.report is not None:
        from analysis.report import build_report

        pdf = build_report(sweep.out, sweep.report)
        print(f"report: {pdf}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
