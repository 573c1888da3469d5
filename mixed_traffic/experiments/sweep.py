"""Scalability sweeps over AV penetration, traffic density, weather (paper §V-G) or the
detection range (§V-J).

``python -m mixed_traffic.sweep --penetration`` runs every (policy, value, seed) cell in parallel
worker processes, appends each episode's record to ``RESULTS/records.jsonl`` as soon as it
finishes (atomically; a re-run skips cells already recorded by the same code), then writes
figures and a PDF report. Each cell runs in its own process: libsumo allows one simulation per
process, and a SUMO segfault then costs one cell (recorded as failed with its exit code), not
the sweep.
"""

from __future__ import annotations

import argparse
import dataclasses
import multiprocessing as mp
import sys
import time
import traceback
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from tqdm import tqdm

from mixed_traffic.config import EnvConfig
from mixed_traffic.experiments.cli import add_config_args, config_dest, config_from_args
from mixed_traffic.paths import RESULTS, reference
from mixed_traffic.provenance import (
    FolderBusyError,
    check_writable,
    current_code_key,
    exclusive_folder,
    file_digest,
    read_records,
    record_meta,
    records_of_this_code,
    write_record_atomic,
)
from mixed_traffic.schema import (
    AUTO_POLICIES,
    CELL_KEYS,
    FD_DIR,
    LEARNED,
    POLICIES,
    STUDY_POLICIES,
    TRACE_DIR,
)
from mixed_traffic.world.episode import check_batch
from mixed_traffic.world.registry import load_scenario
from mixed_traffic.world.scenario import Scenario

PENETRATIONS = (0.2, 0.4, 0.6, 0.8, 1.0)
DENSITIES = (60.0, 120.0, 180.0)
WEATHERS = ("normal", "rain", "fog", "night")
DETECTION_RANGES = (0.6, 0.8, 1.0, 1.2)
"""Default detection ranges [share of the nominal 90 m LiDAR / 60 m camera] (the paper's
LiDAR table spans 50-110 m)."""
SWEEP_EPISODE_LENGTH = 150.0
"""Episode length [s] where neither the options nor the scenario's spec give one."""
SWEEP_WARMUP = 30.0
"""Warm-up [s] where neither the options nor the scenario's spec give one."""
AXES = ("penetration", "density", "weather", "detection_range")
DEFAULT_VALUES = {"penetration": PENETRATIONS, "density": DENSITIES, "weather": WEATHERS,
                  "detection_range": DETECTION_RANGES}  # fmt: skip


@dataclass(frozen=True)
class SweepConfig:
    """One sweep: which axis, which cells, where results go. The CLI is built from it."""

    axis: str = "penetration"
    """penetration | density | weather | detection_range."""
    scenario: str = "straight"
    """Scenario name or .net.xml/.sumocfg path (see ``python -m mixed_traffic.scenario --list``)."""
    at_density: float | None = None
    """Density for the penetration and weather sweeps [veh/km, all lanes] (default: the scenario's, 120
    veh/km unless its spec gives one)."""
    at_penetration: float = 0.2
    """AV penetration for the density and weather sweeps [0-1]."""
    ring_length: float = 0.0
    """Circumference a ring scenario is scaled to [m], 150-400; its vehicle count is density x
    length (0 = the ring as bundled)."""
    values: tuple[float | str, ...] = ()
    """Values of the swept axis (default: penetration 0.2 .. 1.0, density 60 120 180 veh/km,
    every weather, or detection range 0.6 .. 1.2 of nominal)."""
    reference: bool = True
    """Add the all-human 0 % reference cells to a penetration sweep."""
    policies: tuple[str, ...] = ("auto", "acc-lc-tuned", "acc-lc")
    """Policies to compare: auto (AUTO behind its safety module), auto-raw, acc-lc-tuned (the
    baseline a learned policy is compared with), acc-lc (its default), a rule's spec such as
    acc-lc:T=1.0,speed_factor=1.0, idm, random, ..."""
    seeds: tuple[int, ...] = (0, 1, 2)
    """Root seeds; each cell runs once per seed."""
    copies: int = 1
    """Copies of the scenario in each cell's simulation (batched worlds: ring, straight,
    highway, wave-highway, merge and bottleneck); each copy is an episode of its own, with its
    own record."""
    episode_length: float | None = None
    """Simulated time per episode [s] (default: the scenario's, 150 s unless its spec gives
    one)."""
    warmup: float | None = None
    """Time before flow metrics are recorded [s] (default: the scenario's, 30 s unless its
    spec gives one)."""
    checkpoint: Path | None = None
    """AUTO checkpoint (default: the shipped agents/checkpoints/auto.pt)."""
    checkpoints: Path | None = None
    """Folder of the study policies' checkpoints, <policy>.pt (default: agents/checkpoints/study)."""
    workers: int = 2
    """Parallel worker processes (or Ray tasks at a time)."""
    backend: str = "process"
    """process (local worker processes) | ray (Ray tasks, local or on a cluster)."""
    address: str = ""
    """With backend ray: cluster address for ray.init, e.g. auto (default: start Ray locally)."""
    out: Path | None = None
    """Results folder for records.jsonl (default: results/<axis>)."""
    report: bool = True
    """Write figures and the PDF report after the cells."""
    pdf: Path | None = None
    """PDF report path, figures beside it (default: <results folder>/<axis>.pdf)."""
    update_reference: bool = False
    """Write the report over the committed reference, reports/<axis>.pdf, and its figures
    beside it (the README shows reports/penetration-dt_tf_vs_penetration.png)."""
    traffic: bool = True
    """Run the cells of the report's traffic figures: up to 7 short one-seed all-human cells
    over densities (fundamental diagram) and the trajectories of the first seed's reference
    cell and last cell of the first policy (space-time diagram)."""

    def __post_init__(self) -> None:
        def bad(name: str, why: str) -> None:
            value = getattr(self, name)
            shown = str(value) if isinstance(value, Path) else repr(value)
            raise ValueError(f"--{name.replace('_', '-')}={shown}: {why}")

        if self.axis not in AXES:
            bad("axis", f"choose from {AXES}")
        try:  # names first: a typo is the error to show, not what follows from it
            scenario = load_scenario(self.scenario)
        except ValueError as e:
            bad("scenario", str(e))
        if not self.policies:
            bad("policies", f"give at least one; choose from {list(POLICIES)}")
        from mixed_traffic.experiments.runner import check_checkpoint, check_policy

        try:  # canonical specs: acc-lc:T=1 and acc-lc:T=1.0 are one cell
            specs = tuple(dict.fromkeys(check_policy(p) for p in self.policies))
        except ValueError as e:
            bad("policies", str(e))
        object.__setattr__(self, "policies", specs)
        if self.checkpoint is not None and not set(AUTO_POLICIES) & set(self.policies):
            bad("checkpoint", f"no {'/'.join(AUTO_POLICIES)} policy in --policies would use it")
        if self.checkpoint is not None:
            try:
                check_checkpoint(self.checkpoint)
            except ValueError as e:
                bad("checkpoint", str(e))
        if not self.seeds:
            bad("seeds", "give at least one seed")
        if any(s < 0 for s in self.seeds):
            bad("seeds", "seeds must be >= 0")
        if self.workers < 1:
            bad("workers", "must be >= 1")
        if self.update_reference and (self.pdf is not None or not self.report):
            bad("update_reference", "writes the reference report: drop --pdf and --no-report")
        self._episode_defaults(scenario)
        if self.backend not in ("process", "ray"):
            bad("backend", "choose from process, ray")
        if self.address and self.backend != "ray":
            bad("address", "--address needs --backend ray")
        if not 0 < self.episode_length <= 86400:  # also refuses nan
            bad("episode_length", "must be in (0, 86400] s")
        if not 0 <= self.warmup < self.episode_length:
            bad("warmup", f"must be in [0, episode length {self.episode_length})")
        if self.ring_length and not scenario.ring:
            bad("ring_length", f"{self.scenario} is not a ring")
        try:
            base = EnvConfig(scenario=self.scenario, density=self.at_density,
                             penetration=self.at_penetration, episode_length=self.episode_length,
                             ring_length=_ring(self.ring_length))  # fmt: skip
        except ValueError as e:
            bad("ring_length", str(e))
        try:
            check_batch(scenario, scenario.configure(replace(base, copies=self.copies)))
        except ValueError as e:
            bad("copies", str(e))
        try:
            for v in self.axis_values():  # each value must make a valid config
                scenario.configure(with_axis(base, self.axis, v))
        except ValueError as e:
            bad("values", str(e))

    def _episode_defaults(self, scenario: Scenario) -> None:
        """Fill in the episode length and warm-up the options leave open: the scenario's,
        else the sweep's own (150 s, 30 s)."""
        if self.episode_length is None:
            length = scenario.episode_length or SWEEP_EPISODE_LENGTH
            object.__setattr__(self, "episode_length", length)
        warmup = scenario.default_warmup(self.warmup, SWEEP_WARMUP, self.episode_length)
        object.__setattr__(self, "warmup", warmup)

    def axis_values(self) -> tuple:
        """The swept values: numbers for penetration and density, names for weather."""
        if not self.values:
            return DEFAULT_VALUES[self.axis]
        return self.values if self.axis == "weather" else tuple(float(v) for v in self.values)

    @property
    def results(self) -> Path:
        """Folder of records.jsonl."""
        return self.out or RESULTS / self.axis

    @property
    def report_pdf(self) -> Path | None:
        """Where the PDF goes, or None without a report: beside the results, or over the
        committed reference with ``update_reference``."""
        if not self.report:
            return None
        if self.update_reference:
            return reference(f"reports/{self.axis}.pdf")
        return self.pdf or self.results / f"{self.axis}.pdf"

    def cell_checkpoint(self, policy: str) -> Path | None:
        """The checkpoint option of ``policy``'s cells (None: the policy's default)."""
        if policy in AUTO_POLICIES:
            return self.checkpoint
        if policy in STUDY_POLICIES and self.checkpoints is not None:
            return self.checkpoints / f"{policy}.pt"
        return None

    def checkpoint_key(self, policy: str) -> tuple[str, str]:
        """The weights ``policy``'s cells run: (absolute path, content digest), ('', '') for a
        rule (``acc-lc-tuned``: its parameters' file); part of their key, so other weights
        (another file, or the same file retrained) are another cell."""
        if policy == "acc-lc-tuned":
            from agents.rules.tuned import TUNED_FILE

            return str(TUNED_FILE), file_digest(TUNED_FILE)
        if policy not in LEARNED:
            return "", ""
        from agents.policies import checkpoint_path

        path = checkpoint_path(policy, self.cell_checkpoint(policy)).resolve()
        return str(path), file_digest(path) if path.is_file() else ""

    def check_checkpoints(self) -> None:
        """ValueError naming the first learned policy whose checkpoint is unreadable."""
        from agents.policies import checkpoint_path
        from mixed_traffic.experiments.runner import check_checkpoint

        for policy in (p for p in self.policies if p in LEARNED):
            try:
                check_checkpoint(checkpoint_path(policy, self.cell_checkpoint(policy)))
            except ValueError as e:
                raise ValueError(f"--policies {policy}: {e}") from e


@dataclass(frozen=True)
class Cell:
    policy: str
    scenario: str
    density: float
    penetration: float
    weather: str
    seed: int
    detection_range: float = 1.0
    copy: int = 0
    """A cell runs its copies (``SweepConfig.copies``) in one simulation: copy 0 names it."""

    def key(self) -> tuple:
        return tuple(getattr(self, k) for k in CELL_KEYS)


def cells(sweep: SweepConfig) -> list[Cell]:
    """Every cell of the sweep, in a stable order (seed-major, so early results span the axis)."""
    density = sweep.at_density or load_scenario(sweep.scenario).density
    base = dict(
        scenario=sweep.scenario,
        density=density,
        penetration=sweep.at_penetration,
        weather="normal",
        detection_range=1.0,
    )
    out: list[Cell] = []
    for seed in sweep.seeds:
        if sweep.axis == "penetration" and sweep.reference:
            out.append(Cell("idm", **{**base, "penetration": 0.0}, seed=seed))
        for value in sweep.axis_values():
            out += [Cell(p, **{**base, sweep.axis: value}, seed=seed) for p in sweep.policies]
    return out


def with_axis(config: EnvConfig, axis: str, value: float | str) -> EnvConfig:
    """``config`` with sweep ``axis`` set to ``value`` (the detection range is a sensor field)."""
    if axis == "detection_range":
        return replace(config, sensors=replace(config.sensors, range_factor=float(value)))
    return replace(config, **{axis: value})


def cell_config(cell: Cell, sweep: SweepConfig) -> EnvConfig:
    base = EnvConfig(
        scenario=cell.scenario,
        density=cell.density,
        penetration=cell.penetration,
        weather=cell.weather,
        seed=cell.seed,
        episode_length=sweep.episode_length,
        ring_length=_ring(sweep.ring_length),
        copies=sweep.copies,
    )
    return with_axis(base, "detection_range", cell.detection_range)


def _ring(length: float) -> tuple[float, ...]:
    """``EnvConfig.ring_length`` of a sweep's ``ring_length`` (0 = the ring as bundled)."""
    return (length,) if length else ()


def episode_records(cell: Cell, sweep: SweepConfig) -> list[dict]:
    """The episode of ``cell``: one record per copy, or failed records carrying the error."""
    try:
        from mixed_traffic.experiments.runner import run_copies

        config = cell_config(cell, sweep)
        records = run_copies(config, cell.policy, sweep.warmup,
                             checkpoint=sweep.cell_checkpoint(cell.policy),
                             trace=trace_path(cell, sweep))  # fmt: skip
    except Exception as e:  # any failure becomes a failed record; the sweep carries on
        return _failed(cell, sweep, f"{type(e).__name__}: {e}\n{traceback.format_exc(limit=3)}")
    for c, record in enumerate(records):
        record["cell"] = asdict(replace(cell, copy=c))
    return records


def trace_path(cell: Cell, sweep: SweepConfig) -> Path | None:
    """Where a representative cell's trajectories go (the first seed's all-human reference,
    and its cell of the first policy at the last axis value), else None."""
    last = sweep.axis_values()[-1]
    representative = cell.seed == sweep.seeds[0] and (
        (cell.policy == "idm" and cell.penetration == 0.0)
        or (cell.policy == sweep.policies[0] and getattr(cell, sweep.axis) == last)
    )
    if not (sweep.traffic and representative):
        return None
    value = getattr(cell, sweep.axis)
    return sweep.results / TRACE_DIR / f"{cell.policy}-{sweep.axis}-{value}-seed{cell.seed}.npz"


FD_LABEL = "fundamental diagram (all-human cells of the traffic figures)"
FD_PER_LANE = (12.0, 20.0, 28.0, 36.0, 44.0, 52.0, 60.0)
"""Densities of the fundamental diagram's all-human cells [veh/km/lane]."""


def fd_sweep(sweep: SweepConfig) -> SweepConfig:
    """The one-seed all-human cells of the fundamental diagram: short episodes (at most 120 s
    after at most 30 s) at ``FD_PER_LANE`` densities, in ``RESULTS/fd``."""
    scenario = load_scenario(sweep.scenario)
    values = tuple(
        k * scenario.lanes for k in FD_PER_LANE if k * scenario.lanes <= scenario.max_density
    )
    length = min(sweep.episode_length, 120.0)
    return replace(
        sweep, axis="density", values=values, policies=("idm",), at_penetration=0.0,
        seeds=sweep.seeds[:1], reference=False, episode_length=length,
        warmup=min(sweep.warmup, 30.0, length / 2), out=sweep.results / FD_DIR, report=False,
        update_reference=False, traffic=False, checkpoint=None,
    )  # fmt: skip


def _failed(cell: Cell, sweep: SweepConfig, error: str) -> list[dict]:
    """A failed record for each copy of ``cell``, carrying ``error``."""
    meta = record_meta(cell_config(cell, sweep))
    return [{**meta, "status": "failed", "metrics": {}, "error": error,
             "cell": asdict(replace(cell, copy=c))} for c in range(sweep.copies)]  # fmt: skip


def _run_cell(cell: Cell, sweep: SweepConfig, queue: mp.Queue) -> None:
    """Worker process: one episode's records onto the queue."""
    queue.put(episode_records(cell, sweep))


def run_sweep(sweep: SweepConfig, progress: bool = True, label: str = "") -> Path:
    """Run the missing cells of ``sweep`` (``label``: its progress bar's, default the axis);
    returns the records file."""
    records_path = sweep.results / "records.jsonl"
    with exclusive_folder(sweep.results):  # a second run into the folder stops here
        todo = _missing(sweep, records_of_this_code(records_path))  # failed ones: again
        _run(todo, sweep, records_path, progress, label or f"{sweep.axis} sweep")
    if sweep.traffic:
        run_sweep(fd_sweep(sweep), progress, FD_LABEL)
    return records_path


def run_cells(todo: list[Cell], sweep: SweepConfig, progress: bool = True) -> Path:
    """Run every cell of ``todo`` (recorded or not, repeats included) with the workers and
    backend of ``sweep``, into its records file; returns that file."""
    records_path = sweep.results / "records.jsonl"
    with exclusive_folder(sweep.results):
        _run(todo, sweep, records_path, progress, f"{sweep.axis} cells")
    return records_path


def _run(todo: list[Cell], sweep: SweepConfig, records_path: Path, progress: bool,
         label: str) -> None:  # fmt: skip
    if not todo:  # a resumed run with nothing left: say so instead of an empty bar
        if progress:
            print(f"{label}: every cell is already recorded in {records_path}", file=sys.stderr)
        return
    bar = tqdm(total=len(todo), desc=label, unit="episode", disable=not progress)
    if sweep.backend == "ray":
        _run_ray(todo, sweep, records_path, bar)
    else:
        _run_processes(todo, sweep, records_path, bar)
    bar.close()


def _run_processes(todo: list[Cell], sweep: SweepConfig, records_path: Path, bar: tqdm) -> None:
    """At most ``workers`` cells at a time, each in its own process."""
    ctx = cell_context(learned=any(c.policy in LEARNED for c in todo))
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


def cell_context(learned: bool) -> mp.context.BaseContext:
    """Fork cells from a server that has imported the runner and loaded the compiled kernels
    (and torch with the learned policies) once: a fresh interpreter per cell paid 1-4 s of
    imports, and each cell about 0.5 s for the kernels' first call. The server itself
    starts no simulation and no torch thread, so each cell is still a clean process; the
    backend loads libsumo in the cell, when its simulation starts. Spawn where the platform
    has no forkserver."""
    if "forkserver" not in mp.get_all_start_methods():
        return mp.get_context("spawn")
    ctx = mp.get_context("forkserver")
    torch = ["agents.policies", "agents.checkpoint"] if learned else []
    ctx.set_forkserver_preload(["mixed_traffic.experiments.preload", *torch])
    return ctx


def _collect(
    queue: mp.Queue, running: dict, records_path: Path, bar: tqdm, sweep: SweepConfig
) -> None:
    """Write records that arrived; turn dead workers without a record into failed records."""
    try:
        records = queue.get(timeout=0.5)
    except Exception:
        records = None
    if records is not None:
        _write(records_path, records)
        key = _cell_key(records[0])[:-3]  # the cell, without its copy and the checkpoint
        for pid, (proc, cell, _) in list(running.items()):
            if cell.key()[:-1] == key:
                proc.join(timeout=10)
                del running[pid]
        _advance(bar, records)
        return
    for pid, (proc, cell, _) in list(running.items()):
        if not proc.is_alive() and proc.exitcode not in (None, 0) and queue.empty():
            failed = _failed(cell, sweep, f"worker process died with exit code {proc.exitcode}")
            _write(records_path, failed)
            del running[pid]
            _advance(bar, failed)


def _write(records_path: Path, records: list[dict]) -> None:
    for record in records:
        write_record_atomic(records_path, record)


def _run_ray(todo: list[Cell], sweep: SweepConfig, records_path: Path, bar: tqdm) -> None:
    """Each cell a Ray task (one CPU, no retries); a task whose worker dies is a failed record."""
    import ray

    owns = not ray.is_initialized()
    if owns:
        local_cpus = None if sweep.address else sweep.workers
        ray.init(address=sweep.address or None, num_cpus=local_cpus, log_to_driver=False)
    task = ray.remote(num_cpus=1, max_retries=0)(episode_records)
    try:
        futures = {task.remote(c, sweep): c for c in todo}
        while futures:
            ready, _ = ray.wait(list(futures), num_returns=1)
            cell = futures.pop(ready[0])
            try:
                records = ray.get(ready[0])
            except Exception as e:  # the worker process died (e.g. a SUMO segfault)
                records = _failed(cell, sweep, f"Ray task failed: {type(e).__name__}: {e}")
            _write(records_path, records)
            _advance(bar, records)
    finally:
        if owns:
            ray.shutdown()


def _advance(bar: tqdm, records: list[dict]) -> None:
    cell, status = records[0]["cell"], records[0]["status"]
    bar.update(1)
    bar.set_postfix_str(f"{cell['policy']} p={cell['penetration']} {status}")


def _cell_key(record: dict) -> tuple:
    """A record's cell, with the checkpoint its auto cells ran (other weights: another cell)."""
    cell = record.get("cell", {})
    return (*(cell.get(k) for k in CELL_KEYS), record.get("checkpoint", ""),
            record.get("checkpoint_sha", ""))  # fmt: skip


def _planned_keys(cell: Cell, sweep: SweepConfig) -> list[tuple]:
    """``_cell_key`` of each record ``cell`` will write (one per copy)."""
    source = sweep.checkpoint_key(cell.policy)
    return [(*replace(cell, copy=c).key(), *source) for c in range(sweep.copies)]


def failed_cells(sweep: SweepConfig) -> list[Cell]:
    """The sweep's cells without a successful record of this code (after its run)."""
    return _missing(sweep, read_records(sweep.results / "records.jsonl"))


def _missing(sweep: SweepConfig, records: list[dict]) -> list[Cell]:
    """The sweep's cells that ``records`` hold no successful record of this code for."""
    ours = current_code_key()
    done = {_cell_key(r) for r in records if r.get("status") == "ok" and r.get("code") == ours}
    return [c for c in cells(sweep) if not done.issuperset(_planned_keys(c, sweep))]


# --------------------------------------------------------------------------- CLI
def parse_args(argv: list[str] | None) -> SweepConfig:
    """SweepConfig from the command line; exits with a message naming a bad option."""
    p = argparse.ArgumentParser(
        prog="python -m mixed_traffic.sweep",
        description="Penetration / density / weather / detection-range sweeps with figures and a "
        "PDF report.",
    )
    axis = p.add_mutually_exclusive_group()
    dest = config_dest("axis")  # the config field `axis`, set by one of three flags
    axis.add_argument("--penetration", dest=dest, action="store_const", const="penetration",
                      help=f"sweep AV penetration {PENETRATIONS} plus an all-human 0 %% reference (default)")  # fmt: skip
    axis.add_argument("--density", dest=dest, action="store_const", const="density",
                      help=f"sweep density {DENSITIES} veh/km")  # fmt: skip
    axis.add_argument("--weather", dest=dest, action="store_const", const="weather",
                      help=f"sweep the weather presets {WEATHERS}")  # fmt: skip
    axis.add_argument("--detection-range", dest=dest, action="store_const",
                      const="detection_range",
                      help=f"sweep the LiDAR and camera range as a share of the nominal 90 m / 60 m "
                      f"{DETECTION_RANGES} (SensorConfig.range_factor)")  # fmt: skip
    fields = [f.name for f in dataclasses.fields(SweepConfig) if f.name != "axis"]
    add_config_args(p, SweepConfig, only=fields)
    try:
        sweep = config_from_args(p.parse_args(argv), SweepConfig)
        sweep.check_checkpoints()
        check_writable(sweep.results / "records.jsonl")
        if sweep.report_pdf is not None:  # not only after every cell has run
            check_writable(sweep.report_pdf, what="report")
    except ValueError as e:
        p.error(str(e))
    return sweep


def main(argv: list[str] | None = None) -> int:
    sweep = parse_args(argv)
    t0 = time.time()
    try:
        records = run_sweep(sweep)
    except FolderBusyError as e:
        print(f"python -m mixed_traffic.sweep: error: {e}", file=sys.stderr)
        return 2
    print(f"records: {records} ({time.time() - t0:.0f} s)")
    failed = failed_cells(sweep)
    if sweep.report_pdf is not None:
        from analysis.report import build_report

        pdf = build_report(sweep.results, sweep.report_pdf)
        print(f"report: {pdf}")
    if failed:
        print(f"{len(failed)} of {len(cells(sweep))} cells failed (their errors are in {records}); "
              "run the sweep again to retry them", file=sys.stderr)  # fmt: skip
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
