"""``python -m mixed_traffic.experiments.fleet``: fleet-return search on an AUTO checkpoint.

    python -m mixed_traffic.experiments.fleet --init runs/auto/auto.pt --out runs/fleet --minutes 60

Evolution strategies (:mod:`agents.training.fleet_search`) on the actor's accel outputs, judged
by what the whole traffic does: every candidate drives the AVs (``auto-raw``, no safety module)
of a whole episode sampled from the train-split scenarios, densities, penetrations and weathers,
through the one episode runner. Each iteration also runs the current policy against ACC-LC on
one more sampled config (the ``gain`` column of the curves: its fleet score minus ACC-LC's).

OUT holds ``base.pt`` (a copy of --init), ``episodes.jsonl`` (every episode's record with
its iteration, role and score), ``thetas.jsonl`` (θ after every iteration, so any iteration's
policy can be rebuilt from ``base.pt``), ``state.json`` (θ, Adam, iteration; written
atomically after every iteration), ``curves.csv`` and ``auto.pt`` (the current policy, a
normal checkpoint). A second run with the same OUT resumes; kill -9 loses one iteration (whose
episodes a redone iteration appends again: the last record per iteration and role counts).
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing as mp
import shutil
import sys
import time
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from mixed_traffic.config import WEATHERS, EnvConfig
from mixed_traffic.experiments import cli
from mixed_traffic.experiments.runner import check_checkpoint, run_episode
from mixed_traffic.provenance import atomic_write, check_folder, git_revision, write_record_atomic

CURVE_FIELDS = ("iteration", "minutes", "episodes", "mean_d", "unsafe", "gain", "gain_scenario",
                "theta_norm", "bias_left", "bias_follow", "bias_right")  # fmt: skip


def _search_config() -> Any:
    """The default ES step (imported late: ``agents.training`` loads torch)."""
    from agents.training.fleet_search import SearchConfig

    return SearchConfig()


@dataclass(frozen=True)
class FleetConfig:
    """A fleet-search run; the command line is built from these fields."""

    init: Path | None = None
    """Checkpoint to start from (needed for a new OUT; a resumed run uses OUT/base.pt)."""
    out: Path = Path("runs/fleet")
    """Output folder (state.json, curves.csv, auto.pt); an existing one is resumed."""
    minutes: float = 60.0
    """Wall-time budget of this invocation [min] (0 = none)."""
    iterations: int = 0
    """Budget: total iterations of the run including resumed ones (0 = none)."""
    workers: int = 2
    """Episode worker processes."""
    seed: int = 0
    """Root seed: noise vectors and episode configs of iteration i come from (seed, i)."""
    scenarios: tuple[str, ...] = ()
    """Train-split scenarios to sample ('' = all; a family is drawn first, then its variant)."""
    densities: tuple[float, ...] = (60.0, 120.0, 180.0, 0.0)
    """Densities sampled per episode [veh/km, all lanes]; 0 = the scenario's default; infeasible skipped."""
    penetrations: tuple[float, ...] = (0.05, 0.5, 1.0)
    """AV shares sampled per episode [0-1] (0.05 on a 22-car ring is one AV)."""
    weathers: tuple[str, ...] = WEATHERS
    """Weather presets sampled per episode."""
    episode_length: float = 120.0
    """Simulated time per episode [s]."""
    warmup: float = 30.0
    """Time before the fleet's speed is measured [s]."""
    speed_governor: bool = True
    """Residual checkpoints: drive with the speed governor (``LearnerConfig.speed_governor``),
    whatever the --init checkpoint says; False keeps the checkpoint's setting."""
    rss_governor: bool = True
    """Residual checkpoints: drive with the RSS governor (``LearnerConfig.rss_governor``),
    whatever the --init checkpoint says; False keeps the checkpoint's setting."""
    target: str = "accel"
    """What the search moves: ``accel`` (the actor's accel_brake outputs) or ``gate`` (its
    hold gate, added closed to a checkpoint without one; ``LearnerConfig.hold_gate``)."""
    search: Any = field(default_factory=_search_config)
    """The evolution-strategies step (``agents.training.fleet_search.SearchConfig``)."""
    progress: bool = True
    """Show a progress bar."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.minutes) and self.minutes >= 0) or self.iterations < 0:
            raise ValueError(f"minutes={self.minutes} and iterations={self.iterations} must be "
                             "finite and >= 0")  # fmt: skip
        if not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed={self.seed!r} must be an integer >= 0")
        if not (self.minutes or self.iterations):
            raise ValueError("give a budget: --minutes or --iterations")
        if self.workers < 1:
            raise ValueError(f"workers={self.workers} must be at least 1")
        if not self.densities or not self.penetrations:
            raise ValueError("densities and penetrations need at least one value each")
        if any(not d >= 0 for d in self.densities):  # also refuses nan
            raise ValueError(f"densities {list(self.densities)} must be >= 0 veh/km "
                             "(0 = the scenario's default)")  # fmt: skip
        if any(not 0 < p <= 1 for p in self.penetrations):
            raise ValueError(f"penetrations {list(self.penetrations)} must lie in (0, 1]")
        if not self.weathers or any(w not in WEATHERS for w in self.weathers):
            raise ValueError(f"weathers {list(self.weathers)}: choose from {WEATHERS}")
        if not 0 < self.episode_length <= 86400:  # also refuses nan
            raise ValueError(f"episode_length={self.episode_length} must be in (0, 86400] s")
        if not 0 <= self.warmup < self.episode_length:
            raise ValueError(f"warmup {self.warmup} s must be in [0, episode_length "
                             f"{self.episode_length}) s")  # fmt: skip
        if self.target not in ("accel", "gate"):
            raise ValueError(f"target={self.target!r}: choose accel or gate")
        if self.init is not None:
            check_checkpoint(self.init)


# ---------------------------------------------------------------- episode configs
def scenario_pool(names: tuple[str, ...]) -> dict[str, list[str]]:
    """Family → its train-split variants (of ``names``, or all); ValueError on an eval one."""
    from mixed_traffic.world.registry import train_scenarios, train_split_scenario

    pool: dict[str, list[str]] = {}
    for name in names or tuple(train_scenarios()):
        pool.setdefault(train_split_scenario(name).family, []).append(name)
    return pool


def sample_config(rng: np.random.Generator, cfg: FleetConfig, pool: dict[str, list[str]],
                  densities: dict[str, tuple[float | None, ...]]) -> EnvConfig:  # fmt: skip
    """One episode config: family, variant, one of its feasible ``densities`` (by name),
    penetration, weather, seed."""
    family = sorted(pool)[rng.integers(len(pool))]
    name = pool[family][rng.integers(len(pool[family]))]
    dens = densities[name]
    return EnvConfig(
        scenario=name, density=dens[rng.integers(len(dens))],
        penetration=float(cfg.penetrations[rng.integers(len(cfg.penetrations))]),
        weather=cfg.weathers[rng.integers(len(cfg.weathers))], seed=int(rng.integers(2**31)),
        episode_length=cfg.episode_length,
    )  # fmt: skip


def _record(config: EnvConfig, policy: str, warmup: float, checkpoint: str | None) -> dict:
    """Worker: one episode's record."""
    return run_episode(config, policy, warmup, checkpoint=checkpoint)


# ---------------------------------------------------------------- the run
class FleetSearch:
    """Resumable ES run in ``cfg.out``."""

    def __init__(self, cfg: FleetConfig) -> None:
        from agents.checkpoint import load_checkpoint, with_hold_gate
        from agents.training.curves import trim_curves
        from agents.training.fleet_search import Adam, get_theta
        from mixed_traffic.world.registry import load_scenario

        self.cfg, self.out = cfg, cfg.out
        # every check before OUT is touched: a refused run leaves no base.pt to resume from
        self.pool = scenario_pool(cfg.scenarios)
        self.densities = {n: load_scenario(n).feasible_densities(cfg.densities)
                          for names in self.pool.values() for n in names}  # fmt: skip
        try:
            check_folder(self.out)
        except ValueError as e:
            raise ValueError(f"--out: {e}") from None
        self.out.mkdir(parents=True, exist_ok=True)
        base = self.out / "base.pt"
        state = self._read_state()
        if state is None:
            if cfg.init is None:
                raise ValueError(f"{self.out} holds no run to resume; give --init CHECKPOINT")
            shutil.copyfile(cfg.init, base)
        self.learner, self.meta = load_checkpoint(base)
        if self.learner.cfg.residual:
            on = {k: True for k in ("speed_governor", "rss_governor") if getattr(cfg, k)}
            self.learner.cfg = replace(self.learner.cfg, **on)
        if cfg.target == "gate":
            self.learner = with_hold_gate(self.learner)
        theta = get_theta(self.learner.actor, cfg.target)
        self.state = state or {"iteration": 0, "episodes": 0, "minutes": 0.0,
                               "theta": theta.tolist(), "adam": None}  # fmt: skip
        self.theta = np.array(self.state["theta"])
        self.adam = Adam(len(self.theta), cfg.search.lr, self.state["adam"])
        # rows past the committed iteration (and a row torn by a kill) are redone
        trim_curves(self.out / "curves.csv", self.state["iteration"], CURVE_FIELDS, "iteration")

    def _read_state(self) -> dict | None:
        path = self.out / "state.json"
        if not path.exists():
            return None
        try:
            return json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: corrupt state ({exc}); remove it to start afresh") from exc

    def run(self) -> Path:
        """Iterate until a budget is spent; returns OUT/auto.pt."""
        cfg, start = self.cfg, time.perf_counter()
        bar = tqdm(desc="fleet search", unit="it", disable=not cfg.progress,
                   initial=self.state["iteration"], total=cfg.iterations or None)  # fmt: skip
        ctx = mp.get_context("spawn")
        executor = ProcessPoolExecutor(cfg.workers, mp_context=ctx)
        try:
            while not self._spent(start):
                t = time.perf_counter()
                row, executor = self._iterate(executor, ctx)
                self.state["minutes"] += (time.perf_counter() - t) / 60
                self._commit(row)
                bar.update(1)
                bar.set_postfix(gain=f"{row['gain']:+.3f}", d=f"{row['mean_d']:+.3f}")
        finally:
            executor.shutdown(cancel_futures=True)
            bar.close()
        return self.out / "auto.pt"

    def _spent(self, start: float) -> bool:
        cfg = self.cfg
        if cfg.iterations and self.state["iteration"] >= cfg.iterations:
            return True
        return bool(cfg.minutes) and (time.perf_counter() - start) / 60 >= cfg.minutes

    def _iterate(self, executor: ProcessPoolExecutor, ctx: Any) -> tuple[dict, ProcessPoolExecutor]:
        """Run one iteration's episodes and move θ; (curve row, the live executor)."""
        from agents.training.fleet_search import episode_score, es_gradient, unsafe_events

        cfg, s, it = self.cfg, self.cfg.search, self.state["iteration"]
        rng = np.random.default_rng([cfg.seed, it])
        eps = rng.standard_normal((s.pairs, len(self.theta)))
        configs = [sample_config(rng, cfg, self.pool, self.densities) for _ in range(s.pairs + 1)]
        jobs, roles = [], []
        for i in range(s.pairs):
            for sign, tag in ((1, "+"), (-1, "-")):
                ckpt = self._candidate(f"p{i}{tag}", self.theta + sign * s.sigma * eps[i])
                jobs.append((configs[i], "auto-raw", ckpt))
                roles.append(f"p{i}{tag}")
        jobs += [(configs[-1], "auto-raw", self._candidate("center", self.theta)),
                 (configs[-1], "acc-lc", None)]  # fmt: skip
        roles += ["center", "acc-lc"]
        records, executor = _run_jobs(executor, ctx, cfg, jobs)
        metrics = [r["metrics"] if r else None for r in records]
        scores = np.array(
            [
                episode_score(m, s.unsafe_penalty, s.spread_weight) if m else math.nan
                for m in metrics
            ]
        )
        for record, role, score in zip(records, roles, scores):
            if record:
                record.update(fleet={"iteration": it + 1, "role": role, "score": score})
                write_record_atomic(self.out / "episodes.jsonl", record)
        with np.errstate(invalid="ignore"):
            d = scores[0 : 2 * s.pairs : 2] - scores[1 : 2 * s.pairs : 2]
        self.theta = self.adam.step(self.theta, es_gradient(eps, d, s.sigma, s.clip))
        bias = self.theta[-3:] if cfg.target == "accel" else [math.nan, self.theta[-1], math.nan]
        finite = d[np.isfinite(d)]
        row = {
            "iteration": it + 1, "minutes": 0.0, "episodes": self.state["episodes"] + len(jobs),
            "mean_d": float(np.abs(finite).mean()) if len(finite) else math.nan,
            "unsafe": sum(unsafe_events(m) for m in metrics if m),
            "gain": float(scores[-2] - scores[-1]), "gain_scenario": configs[-1].scenario,
            "theta_norm": float(np.linalg.norm(self.theta)),
            "bias_left": bias[0], "bias_follow": bias[1], "bias_right": bias[2],
        }  # fmt: skip
        return row, executor

    def _candidate(self, name: str, theta: np.ndarray) -> str:
        """A checkpoint of the actor with ``theta`` in OUT/candidates/ → its path."""
        from agents.checkpoint import save_checkpoint
        from agents.training.fleet_search import set_theta

        set_theta(self.learner.actor, theta, self.cfg.target)
        return str(save_checkpoint(self.out / "candidates" / f"{name}.pt", self.learner, self.meta))

    def _commit(self, row: dict) -> None:
        """Checkpoint, then state, then the curve row (a kill in between redoes the iteration)."""
        from agents.checkpoint import save_checkpoint
        from agents.training.curves import write_curves
        from agents.training.fleet_search import set_theta

        row["minutes"] = round(self.state["minutes"], 2)
        self.state.update(iteration=row["iteration"], episodes=row["episodes"],
                          theta=self.theta.tolist(), adam=self.adam.state())  # fmt: skip
        set_theta(self.learner.actor, self.theta, self.cfg.target)
        meta = {**self.meta, "fleet_search": {"iteration": row["iteration"],
                "episodes": row["episodes"], "config": _jsonable(self.cfg),
                "git_revision": git_revision()}}  # fmt: skip
        save_checkpoint(self.out / "auto.pt", self.learner, meta)
        write_record_atomic(self.out / "thetas.jsonl", {"iteration": row["iteration"],
                                                        "theta": self.state["theta"]})  # fmt: skip
        text = json.dumps(self.state).encode()
        atomic_write(self.out / "state.json", lambda f: f.write(text))
        write_curves(self.out / "curves.csv", [row], CURVE_FIELDS)


def _run_jobs(executor: ProcessPoolExecutor, ctx: Any, cfg: FleetConfig,
              jobs: list[tuple]) -> tuple[list[dict | None], ProcessPoolExecutor]:  # fmt: skip
    """Each job's record (None where its episode failed); a broken pool is replaced."""
    futures: list[Future] = [executor.submit(_record, c, p, cfg.warmup, k) for c, p, k in jobs]
    out: list[dict | None] = []
    broken = False
    for fut in futures:
        try:
            out.append(fut.result())
        except BrokenProcessPool:
            out.append(None)
            broken = True
        except Exception as exc:  # a failed episode leaves its pair out of the gradient
            print(f"fleet search: episode failed: {type(exc).__name__}: {exc}", file=sys.stderr)
            out.append(None)
    if broken:
        executor.shutdown(cancel_futures=True)
        executor = ProcessPoolExecutor(cfg.workers, mp_context=ctx)
    return out, executor


def _jsonable(cfg: FleetConfig) -> dict:
    data = asdict(replace(cfg, init=None))
    return json.loads(json.dumps(data, default=str))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m mixed_traffic.experiments.fleet",
        description="Fleet-return search (evolution strategies) on an AUTO checkpoint's accel "
        "outputs, scored by the mean speed of all vehicles and safety events of whole episodes.",
    )
    cli.add_config_args(p, FleetConfig)
    args = p.parse_args(argv)
    try:
        search = FleetSearch(cli.config_from_args(args, FleetConfig))
    except ValueError as e:
        p.error(str(e))
    path = search.run()
    print(f"fleet search: {search.state['iteration']} iterations, {search.state['episodes']} "
          f"episodes; policy in {path}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
