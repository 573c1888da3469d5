"""Multi-worker RBP-DQN training (paper §IV-F; DESIGN §10): N rollout workers, one learner.

Topology: each worker (:mod:`agents.collection.workers`) runs one env with a single-threaded copy of the
policy and its own exploration (Ape-X ladder, :func:`agents.collection.workers.exploration_ladder`), and
flushes its LocalBuffer in chunks of ≥ ``local_buffer`` transitions to the learner. The learner
(this process) holds the GlobalBuffer (:class:`agents.learning.replay.ReplayBuffer`), runs
:meth:`agents.learning.rbpdqn.RBPDQN.update` at ``update_ratio`` updates per transition received, and
broadcasts weights every ``sync_every`` updates.

Backends (:class:`TrainConfig.backend`):

- ``process`` with ``workers == 1``: the worker runs *in the learner process* on a synchronous
  schedule (collect one chunk, do the updates it is owed, repeat). Deterministic for a seed.
- ``process`` with ``workers ≥ 2``: spawned processes, one pipe each, weights via shared memory;
  asynchronous. When the learner lags more than ``max_lag`` updates it stops reading, so the
  pipes fill and the workers block (back-pressure keeps the update ratio).
- ``ray``: the same topology with Ray core actors (workers), the replay in the learner (driver);
  ``address`` joins an existing cluster.

A worker that dies (segfault, SIGKILL, exception) is restarted with a fresh env and fresh seeds;
everything it had sent is already in the replay, only its unsent LocalBuffer is lost.

Outputs in ``out``: ``curves.csv`` (+ TensorBoard if installed), ``checkpoint.pt`` (learner and
optimisers, :func:`agents.checkpoint.save_checkpoint`), ``replay.pt``, ``state.json`` (counters,
RNG), all atomic and rewritten every ``checkpoint_every`` seconds and at the end; with
``keep_snapshots`` each periodic checkpoint is also kept as ``snapshots/<env steps>.pt``; then
``auto.pt`` + ``auto.json`` (command, git revision, wall time, env steps, config).
"""

from __future__ import annotations

import csv
import json
import math
import multiprocessing as mp
import sys
import time
from dataclasses import asdict, dataclass, fields, replace
from multiprocessing.connection import wait as mp_wait
from pathlib import Path
from typing import Any

import numpy as np
import torch

from agents.checkpoint import atomic_write_bytes, load_checkpoint, save_checkpoint
from agents.collection.workers import (
    Chunk,
    RolloutWorker,
    SharedWeights,
    WorkerSpec,
    exploration_ladder,
    process_main,
    weight_vector,
)
from agents.learning.rbpdqn import RBPDQN, LearnerConfig
from agents.learning.replay import ReplayBuffer
from agents.nets.lca import LCAConfig
from mixed_traffic.config import WEATHERS, EnvConfig

BACKENDS = ("process", "ray")
ABLATIONS = ("none", "nohis", "nolane", "nostar", "noimp", "nomul", "novec")
CURVE_COLUMNS = (
    "env_steps", "wall_time", "episodes", "updates", "replay_size", "mean_episode_reward",
    "mean_reward_per_action", "terminal_rate", "collision_rate", "critic_loss", "actor_loss",
    "demo_fraction",
)  # fmt: skip
"""curves.csv columns: terminal/collision rates are per AV trip ended in the row's window (all
transitions, demonstrator included: see demo_fraction); mean_episode_reward is the return per
AV of policy-driven episodes that ended in the window (NaN if none)."""


@dataclass(frozen=True)
class TrainConfig:
    """Training run settings; ``python -m mixed_traffic.train`` builds its options from these."""

    workers: int = 2
    """Rollout worker processes N (1 = in-process, synchronous, deterministic)."""
    backend: str = "process"
    """Worker transport: process (multiprocessing spawn) | ray (Ray core actors)."""
    address: str = ""
    """Ray cluster address for ray.init(address=...), e.g. 'auto' or 'host:6379' ('' = local)."""
    scenarios: tuple[str, ...] = ()
    """Training scenarios sampled per episode ('' = every train-split scenario)."""
    densities: tuple[float, ...] = (60.0, 120.0, 180.0)
    """Traffic densities sampled per episode [veh/km]."""
    penetrations: tuple[float, ...] = (0.2, 0.5, 1.0)
    """AV penetration rates sampled per episode [0-1]."""
    weathers: tuple[str, ...] = WEATHERS
    """Weather presets sampled per episode."""
    episode_length: float = 120.0
    """Simulated time per training episode [s]."""
    env_steps: int = 0
    """Budget: total transitions (AV actions) over the run including resumed parts (0 = none)."""
    minutes: float = 0.0
    """Budget: wall time of this invocation [min] (0 = none). At least one budget is needed."""
    seed: int = 0
    """Root seed: learner init, replay sampling, per-worker episode configs and exploration."""
    out: str = "runs/auto"
    """Output directory (checkpoints, curves, final auto.pt/auto.json)."""
    demo_steps: int = 20000
    """Transitions first driven by the demonstrator (ACC-LC) to seed the replay (0 = off)."""
    demo_share: float = 0.05
    """Probability that a later episode is also driven by the demonstrator [0-1]."""
    pretrain_updates: int = 0
    """Learner updates on the demonstrations alone, as soon as the demonstration phase ends
    (all ``demo_steps`` arrived, or a worker switched to its own policy), before the learned
    weights are published (0 = none)."""
    demo_policy: str = "acc-lc"
    """Demonstrator policy name for agents.policies.make_policy."""
    expert_labels: bool = True
    """Label every transition the learning policy drives with the demonstrator's action for
    the same observation; behaviour cloning and the DQfD margin then target it (DAgger-style
    deviation from the paper, see agents.learning.rbpdqn; off = BC on the taken action)."""
    alpha: float = 0.6
    """Weight α of the normalised Q term in the actor loss after pretraining [-] (paper 0.6)."""
    lr: float = 1e-3
    """Adam learning rate of actor and critic [-] (paper 1e-3)."""
    lr_final: float = 0.0
    """Learning rate reached at the end of the ``env_steps`` budget by cosine decay from
    ``lr``, a function of transitions received, so it survives --resume and keeps one-worker
    runs deterministic [-] (0 = constant ``lr``)."""
    bc_accel_weight: float = 1.0
    """Weight of accel_brake errors in the behaviour-cloning term, relative to 1 per unit²
    (steering: ``LearnerConfig.bc_steer_weight``) [-] (1 = the paper's loss)."""
    bc_accel_expectile: float = 0.5
    """Expectile τ of the accel_brake fit: errors below the label weigh 2τ, above it 2(1 − τ)
    [-] (0.5 = the paper's squared error; see ``LearnerConfig.bc_accel_expectile``)."""
    init: str = ""
    """Checkpoint whose networks (and optimiser states) start a new run: fine-tuning with a
    fresh replay and counters ('' = random init; ignored by --resume). A paper-form checkpoint
    (no ego fusion) is widened with zero weights on the ego input, so the run starts from the
    same policy."""
    ablation: str = "none"
    """Paper §V-A variant: none | nohis | nolane | nostar | noimp | nomul | novec."""
    ego_fusion: bool = True
    """The ego embedding joins LCA's lane-wise fusion (``LCAConfig.ego_fusion``); False trains
    the paper's fusion of the three lane vectors only."""
    bp_dqn: bool = False
    """Train the BP-DQN baseline (no behaviour-cloning regulariser) instead of RBP-DQN."""
    local_buffer: int = 256
    """B_l: transitions a worker buffers before flushing them to the learner [transitions]."""
    replay_capacity: int = 200_000
    """B_g: GlobalBuffer capacity [transitions] (about 7 kB each)."""
    batch_size: int = 128
    """Learner mini-batch b [transitions]."""
    update_ratio: float = 1 / 32
    """Learner updates per transition received (1/32 with b=128 replays each sample ~4 times)."""
    learning_starts: int = 2000
    """Transitions in the replay before the first update."""
    max_lag: int = 64
    """Process/Ray backends: updates the learner may owe before it stops reading chunks."""
    sync_every: int = 50
    """K: learner updates between weight broadcasts to the workers."""
    epsilon: float = 0.2
    """Base ε of the Ape-X ladder: worker i uses ε^(1 + spread·i/(N−1)) [-]."""
    noise_std: float = 0.3
    """Base exploration noise σ of the ladder (same exponent) [action units]."""
    ladder_spread: float = 3.0
    """Exponent spread of the exploration ladder over the workers [-]."""
    checkpoint_every: float = 300.0
    """Seconds between checkpoints [s]."""
    keep_snapshots: bool = True
    """Also keep each periodic checkpoint's weights as ``snapshots/<env steps>.pt`` (≈ 1 MB
    each), so a run's intermediate networks can be compared afterwards."""
    log_every: int = 20000
    """Transitions between learning-curve rows."""
    learner_threads: int = 1
    """torch threads of the learner process."""
    progress: bool = True
    """Show a tqdm progress bar."""
    max_worker_restarts: int = 50
    """Give up when one worker slot has been restarted this many times."""
    crash_after_chunks: int = 0
    """Test hook: worker 0 SIGKILLs itself after sending this many chunks (0 = off)."""

    def __post_init__(self) -> None:
        def bad(name: str, why: str) -> None:
            raise ValueError(f"TrainConfig.{name}={getattr(self, name)!r}: {why}")

        if self.workers < 1:
            bad("workers", "need at least 1 worker")
        if self.backend not in BACKENDS:
            bad("backend", f"choose from {BACKENDS}")
        if self.address and self.backend != "ray":
            bad("address", "only meaningful with backend='ray'")
        if self.ablation not in ABLATIONS:
            bad("ablation", f"choose from {ABLATIONS}")
        if self.ablation == "novec":
            bad("ablation", "NoVEC (rasterised BEV + CNN encoder) is not implemented")
        if self.ablation == "nomul" and self.workers != 1:
            bad("ablation", "NoMUL is the single-worker variant: pass --workers 1")
        if not self.densities or any(d <= 0 for d in self.densities):
            bad("densities", "need positive densities")
        if not self.penetrations or any(not 0 < p <= 1 for p in self.penetrations):
            bad("penetrations", "need penetrations in (0, 1]")
        if not self.weathers or any(w not in WEATHERS for w in self.weathers):
            bad("weathers", f"choose from {WEATHERS}")
        if self.env_steps < 0 or self.minutes < 0:
            bad("env_steps", "budgets must be >= 0")
        if self.env_steps == 0 and self.minutes == 0:
            bad("env_steps", "give a budget: env_steps > 0 and/or minutes > 0")
        if not 0 <= self.demo_share <= 1:
            bad("demo_share", "must be in [0, 1]")
        if self.demo_steps < 0:
            bad("demo_steps", "must be >= 0")
        if self.pretrain_updates < 0:
            bad("pretrain_updates", "must be >= 0")
        if not self.alpha >= 0:
            bad("alpha", "must be >= 0")
        if not self.lr > 0:
            bad("lr", "must be > 0")
        if not 0 <= self.lr_final <= self.lr:
            bad("lr_final", "must be in [0, lr] (0 = no decay)")
        if self.lr_final and not self.env_steps:
            bad("lr_final", "the decay runs over the env_steps budget: give env_steps > 0")
        if not self.bc_accel_weight >= 0:
            bad("bc_accel_weight", "must be >= 0")
        if not 0 < self.bc_accel_expectile < 1:
            bad("bc_accel_expectile", "must be in (0, 1)")
        for name in ("local_buffer", "replay_capacity", "batch_size", "sync_every", "log_every"):
            if getattr(self, name) < 1:
                bad(name, "must be >= 1")
        if self.update_ratio < 0 or self.learning_starts < 0 or self.max_lag < 1:
            bad("update_ratio", "update_ratio/learning_starts must be >= 0, max_lag >= 1")
        if self.checkpoint_every <= 0:
            bad("checkpoint_every", "must be > 0")

    def to_dict(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TrainConfig:
        names = {f.name for f in fields(cls)}
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()
                      if k in names})  # fmt: skip


# ---------------------------------------------------------------------------- helpers
def lca_config(cfg: TrainConfig, env_base: EnvConfig) -> LCAConfig:
    """Encoder config from the env's history/waypoints and the ablation."""
    flags = {"nohis": {"history": False}, "nolane": {"lane_wise": False},
             "nostar": {"star": False}}.get(cfg.ablation, {})  # fmt: skip
    return LCAConfig(z=env_base.sensors.history, m=env_base.sensors.waypoints,
                     ego_fusion=cfg.ego_fusion, **flags)  # fmt: skip


def env_base_config(cfg: TrainConfig, env_base: EnvConfig | None = None) -> EnvConfig:
    """Fixed env fields for every episode: episode length and, for NoIMP, w_impact = 0."""
    base = replace(env_base or EnvConfig(), episode_length=cfg.episode_length)
    if cfg.ablation == "noimp":
        base = replace(base, reward=replace(base.reward, w_impact=0.0))
    return base


def atomic_write_json(path: Path, data: dict) -> None:
    atomic_write_bytes(path, lambda f: f.write(json.dumps(data, indent=2).encode()))


class Window:
    """Aggregates chunks/episodes/losses between two learning-curve rows."""

    def __init__(self) -> None:
        self.ep_returns: list[float] = []
        self.trips = self.terminals = self.collisions = 0.0
        self.reward_sum = 0.0
        self.transitions = self.demo = 0
        self.c_loss: list[float] = []
        self.a_loss: list[float] = []

    def add_chunk(self, chunk: Chunk) -> None:
        self.reward_sum += float(chunk["reward"].sum())
        self.transitions += len(chunk["decision"])
        self.demo += int(chunk["demo"])
        self.trips += chunk["trips"]
        self.terminals += chunk["terminals"]
        self.collisions += chunk["collisions"]
        for ep in chunk["episodes"]:
            if not ep["demo"]:  # returns of the learning policy, not of the demonstrator
                self.ep_returns.append(ep["return_per_av"])

    def row(self) -> dict[str, float]:
        def mean(x: list[float]) -> float:
            return float(np.mean(x)) if x else math.nan

        trips = self.trips if self.trips > 0 else math.nan
        return {
            "mean_episode_reward": mean(self.ep_returns),
            "mean_reward_per_action": self.reward_sum / self.transitions
            if self.transitions else math.nan,
            "terminal_rate": self.terminals / trips,
            "collision_rate": self.collisions / trips,
            "critic_loss": mean(self.c_loss),
            "actor_loss": mean(self.a_loss),
            "demo_fraction": self.demo / self.transitions if self.transitions else math.nan,
        }  # fmt: skip


# ---------------------------------------------------------------------------- collectors
class InProcessCollector:
    """``workers == 1``: the worker lives in the learner process (synchronous, deterministic)."""

    synchronous = True

    def __init__(self, specs: list[WorkerSpec], n: int) -> None:
        self.worker = RolloutWorker(specs[0])
        self.n = n
        self.restarts = 0

    def publish(self, vec: np.ndarray) -> None:
        self.worker.set_weights(vec)

    def poll(self, timeout: float) -> list[Chunk]:
        return [self.worker.collect(self.n)]

    def close(self) -> None:
        self.worker.close()


def _next_incarnation(collector: Any, wid: int, why: str) -> None:
    """Count a restart of worker ``wid`` (giving up after ``max_restarts``) and give its spec
    a new incarnation (fresh env seeds)."""
    collector.slot_restarts[wid] += 1
    collector.restarts += 1
    if collector.slot_restarts[wid] > collector.max_restarts:
        raise RuntimeError(f"worker {wid} restarted {collector.max_restarts} times; last: {why}")
    spec = collector.specs[wid]
    collector.specs[wid] = replace(spec, incarnation=spec.incarnation + 1)


class ProcessCollector:
    """Spawned worker processes, one pipe each; weights through :class:`SharedWeights`."""

    synchronous = False

    def __init__(self, specs: list[WorkerSpec], n: int, vec: np.ndarray, max_restarts: int,
                 log: Any) -> None:  # fmt: skip
        self.ctx = mp.get_context("spawn")
        self.n, self.max_restarts, self.log = n, max_restarts, log
        self.weights = SharedWeights(self.ctx, len(vec))
        self.weights.publish(vec)
        self.stop = self.ctx.Event()
        self.specs = {s.worker_id: s for s in specs}
        self.procs: dict[int, Any] = {}
        self.conns: dict[int, Any] = {}
        self.restarts = 0
        self.slot_restarts = dict.fromkeys(self.specs, 0)
        for wid in self.specs:
            self._spawn(wid)

    def _spawn(self, wid: int) -> None:
        reader, writer = self.ctx.Pipe(duplex=False)
        p = self.ctx.Process(
            target=process_main, args=(self.specs[wid], writer, self.weights, self.stop, self.n),
            name=f"mt-worker-{wid}", daemon=True,
        )  # fmt: skip
        p.start()
        writer.close()  # only the child holds the write end: its death → EOF here
        self.procs[wid], self.conns[wid] = p, reader

    def _restart(self, wid: int, why: str) -> None:
        self.conns.pop(wid).close()
        p = self.procs.pop(wid)
        p.join(timeout=5)
        if p.is_alive():
            p.kill()
            p.join(timeout=5)
        _next_incarnation(self, wid, why)
        self.log(f"worker {wid} died (exit code {p.exitcode}): {why.strip()[-2000:]}; restarting")
        self._spawn(wid)

    def publish(self, vec: np.ndarray) -> None:
        self.weights.publish(vec)

    def poll(self, timeout: float) -> list[Chunk]:
        out: list[Chunk] = []
        by_conn = {c: wid for wid, c in self.conns.items()}
        for conn in mp_wait(list(by_conn), timeout=timeout):
            wid = by_conn[conn]
            try:
                kind, payload = conn.recv()
            except (EOFError, OSError):
                self._restart(wid, "connection closed (process died)")
                continue
            if kind == "chunk":
                out.append(payload)
            else:
                self._restart(wid, payload)
        for wid, p in list(self.procs.items()):
            if not p.is_alive() and not self.conns[wid].poll():
                self._restart(wid, "process not alive")
        return out

    def close(self) -> None:
        self.stop.set()
        for c in self.conns.values():
            c.close()  # a worker blocked in send gets BrokenPipeError and exits
        for p in self.procs.values():
            p.join(timeout=10)
            if p.is_alive():
                p.kill()
                p.join(timeout=5)


class RayCollector:
    """Ray core actors as workers; the learner (driver) holds the replay."""

    synchronous = False

    def __init__(self, specs: list[WorkerSpec], n: int, vec: np.ndarray, address: str,
                 max_restarts: int, log: Any) -> None:  # fmt: skip
        import ray

        self.ray = ray
        self.owns_ray = not ray.is_initialized()
        if self.owns_ray:
            if address:
                ray.init(address=address)
            else:
                ray.init(num_cpus=len(specs) + 1, include_dashboard=False,
                         log_to_driver=False)  # fmt: skip
        self.remote_cls = ray.remote(num_cpus=1, max_restarts=0)(RolloutWorker)
        self.n, self.max_restarts, self.log = n, max_restarts, log
        self.specs = {s.worker_id: s for s in specs}
        self.actors: dict[int, Any] = {}
        self.pending: dict[Any, int] = {}
        self.sent_version: dict[int, int] = {}
        self.version = 0
        self.weights_ref = ray.put(vec)
        self.restarts = 0
        self.slot_restarts = dict.fromkeys(self.specs, 0)
        for wid in self.specs:
            self.actors[wid] = self.remote_cls.remote(self.specs[wid])
            self._submit(wid)

    def _submit(self, wid: int) -> None:
        w = self.weights_ref if self.sent_version.get(wid) != self.version else None
        self.sent_version[wid] = self.version
        self.pending[self.actors[wid].collect_with.remote(self.n, w)] = wid

    def publish(self, vec: np.ndarray) -> None:
        self.version += 1
        self.weights_ref = self.ray.put(vec)

    def poll(self, timeout: float) -> list[Chunk]:
        out: list[Chunk] = []
        ready, _ = self.ray.wait(list(self.pending), num_returns=1, timeout=timeout)
        for ref in ready:
            wid = self.pending.pop(ref)
            try:
                out.append(self.ray.get(ref))
            except Exception as exc:  # RayActorError (died) or a task error
                self._restart(wid, f"{type(exc).__name__}: {str(exc).splitlines()[0]}")
            self._submit(wid)
        return out

    def _restart(self, wid: int, why: str) -> None:
        self.ray.kill(self.actors[wid], no_restart=True)
        _next_incarnation(self, wid, why)
        self.log(f"ray worker {wid} failed ({why.strip()[-2000:]}); restarting")
        self.actors[wid] = self.remote_cls.remote(self.specs[wid])
        self.sent_version.pop(wid, None)

    def close(self) -> None:
        for a in self.actors.values():
            self.ray.kill(a, no_restart=True)
        self.pending.clear()
        if self.owns_ray:
            self.ray.shutdown()


# ---------------------------------------------------------------------------- trainer
class Trainer:
    """The learner: GlobalBuffer + RBP-DQN updates + weight broadcast + logging/checkpoints."""

    def __init__(self, cfg: TrainConfig, env_base: EnvConfig | None = None,
                 resume: bool = False, command: str = "", log: Any = None) -> None:  # fmt: skip
        if not cfg.scenarios:
            raise ValueError(
                "TrainConfig.scenarios is empty (mixed_traffic.experiments.train fills it)"
            )
        self.cfg, self.command = cfg, command or " ".join(sys.argv)
        self.log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
        self.out = Path(cfg.out)
        self.env_base = env_base_config(cfg, env_base)
        self.lca = lca_config(cfg, self.env_base)
        torch.set_num_threads(cfg.learner_threads)
        lcfg = LearnerConfig(batch_size=cfg.batch_size, regularize=not cfg.bp_dqn, alpha=cfg.alpha,
                             lr=cfg.lr, bc_accel_weight=cfg.bc_accel_weight,
                             bc_accel_expectile=cfg.bc_accel_expectile)  # fmt: skip
        self.learner = RBPDQN(self.lca, lcfg, seed=cfg.seed)
        self.replay = ReplayBuffer(cfg.replay_capacity, self.lca)
        self.rng = np.random.default_rng([cfg.seed, 7])
        self.c: dict[str, Any] = {
            "env_steps": 0, "sim_steps": 0, "updates": 0, "episodes": 0, "chunks": 0,
            "wall_time": 0.0, "run": 0, "worker_restarts": 0, "next_log": cfg.log_every,
            "demo_received": [0] * cfg.workers,
        }  # fmt: skip
        self.received: dict[tuple[int, int, int], int] = {}
        """(run, worker, incarnation) → last chunk seq received (checks nothing went missing)."""
        self.gaps = 0
        """Chunks that arrived out of sequence (must stay 0: nothing sent is ever lost)."""
        self.restart_base = 0
        state_file = self.out / "state.json"
        if resume:
            self._load()
        elif state_file.exists():
            raise FileExistsError(
                f"{self.out} already holds a training run; pass --resume or another --out"
            )
        elif cfg.init:
            self._init_from(Path(cfg.init))
        # every invocation of this run, first to last (auto.json provenance); the revision is
        # taken now, as commits made while a run trains do not change the code it runs
        from mixed_traffic.provenance import git_revision

        self.c["commands"] = [*self.c.get("commands", []), self.command]
        self.c["revisions"] = [*self.c.get("revisions", []), git_revision()]

    # -------------------------------------------------------------- persistence
    def _load(self) -> None:
        state_file = self.out / "state.json"
        if not state_file.is_file():
            raise FileNotFoundError(f"--resume: {state_file} not found")
        state = json.loads(state_file.read_text())
        old = TrainConfig.from_dict(state["config"])
        for name in ("ablation", "ego_fusion", "bp_dqn", "replay_capacity", "workers"):
            if getattr(old, name) != getattr(self.cfg, name):
                raise ValueError(
                    f"--resume: {name}={getattr(self.cfg, name)!r} differs from the run in "
                    f"{self.out} ({getattr(old, name)!r})"
                )
        load_checkpoint(self.out / "checkpoint.pt", learner=self.learner)
        sd = torch.load(self.out / "replay.pt", map_location="cpu", weights_only=True)
        self.replay.load_state_dict(sd)
        self.c.update(state["counters"])
        self.c["run"] += 1
        self.restart_base = self.c["worker_restarts"]
        self.rng.bit_generator.state = state["rng"]
        if self.learner.steps != self.c["updates"]:
            raise ValueError(
                f"--resume: checkpoint has {self.learner.steps} updates, state.json "
                f"{self.c['updates']} (torn checkpoint?)"
            )
        self._trim_curves()
        self.log(f"resumed {self.out}: {self.c['env_steps']} env steps, "
                 f"{self.c['updates']} updates, replay {len(self.replay)}")  # fmt: skip

    def _init_from(self, path: Path) -> None:
        """Start from ``path``'s networks; its provenance goes into this run's (``init``)."""
        _, meta = load_checkpoint(path, learner=self.learner, widen=True)
        self.learner.steps = 0  # this run's update counter (resume checks they agree)
        keys = ("commands", "git_revision", "env_steps", "updates", "wall_time")
        self.c["init"] = {"path": str(path), **{k: meta.get(k) for k in keys}}
        self.log(f"initialised from {path} ({meta.get('env_steps')} env steps)")

    def _trim_curves(self) -> None:
        """Drop curve rows written after the last checkpoint (they will be redone)."""
        path = self.out / "curves.csv"
        if not path.is_file():
            return
        with path.open() as f:
            rows = list(csv.DictReader(f))
        keep = [r for r in rows if int(float(r["env_steps"])) <= self.c["env_steps"]]
        if len(keep) != len(rows):
            self._write_curves(keep, mode="w")

    def _write_curves(self, rows: list[dict], mode: str = "a") -> None:
        path = self.out / "curves.csv"
        new = mode == "w" or not path.exists()
        with path.open(mode, newline="") as f:
            w = csv.DictWriter(f, fieldnames=CURVE_COLUMNS)
            if new:
                w.writeheader()
            w.writerows(rows)

    def save(self, snapshot: bool = False) -> None:
        """replay.pt, checkpoint.pt (and a snapshot copy), then state.json (the commit point),
        each atomically."""
        self.out.mkdir(parents=True, exist_ok=True)
        sd = self.replay.state_dict()
        atomic_write_bytes(self.out / "replay.pt", lambda f: torch.save(sd, f))
        meta = self._meta()
        save_checkpoint(self.out / "checkpoint.pt", self.learner, meta)
        if snapshot:
            path = self.out / "snapshots" / f"{self.c['env_steps']:09d}.pt"
            save_checkpoint(path, self.learner, meta)
        state = {"config": self.cfg.to_dict(), "counters": self.c,
                 "rng": self.rng.bit_generator.state}  # fmt: skip
        atomic_write_json(self.out / "state.json", state)

    def _meta(self) -> dict[str, Any]:
        return {
            "command": self.command,
            "commands": self.c["commands"],
            "git_revision": self.c["revisions"][-1],
            "git_revisions": self.c["revisions"],
            "train_config": self.cfg.to_dict(),
            "env_base": self.env_base.to_dict(),
            **{k: self.c[k] for k in ("env_steps", "updates", "episodes", "wall_time")},
            **({"init": self.c["init"]} if "init" in self.c else {}),
        }

    def finish(self) -> dict[str, Any]:
        """auto.pt (the learner) and auto.json (provenance)."""
        meta = self._meta()
        save_checkpoint(self.out / "auto.pt", self.learner, meta)
        info = {**meta, "wall_time_s": self.c["wall_time"], "sim_steps": self.c["sim_steps"],
                "worker_restarts": self.c["worker_restarts"]}  # fmt: skip
        atomic_write_json(self.out / "auto.json", info)
        return info

    # -------------------------------------------------------------- workers
    def worker_specs(self) -> list[WorkerSpec]:
        cfg = self.cfg
        ladder = exploration_ladder(cfg.workers, cfg.epsilon, cfg.noise_std, cfg.ladder_spread)
        share = math.ceil(cfg.demo_steps / cfg.workers)
        return [
            WorkerSpec(
                worker_id=i, env_base=self.env_base, lca=self.lca, scenarios=cfg.scenarios,
                densities=cfg.densities, penetrations=cfg.penetrations, weathers=cfg.weathers,
                seed=cfg.seed, run=self.c["run"], epsilon=ladder[i][0], noise_std=ladder[i][1],
                demo_quota=max(0, share - self.c["demo_received"][i]), demo_share=cfg.demo_share,
                demo_policy=cfg.demo_policy, expert_labels=cfg.expert_labels,
                crash_after_chunks=cfg.crash_after_chunks if i == 0 and self.c["run"] == 0 else 0,
            )
            for i in range(cfg.workers)
        ]  # fmt: skip

    def make_collector(self) -> Any:
        cfg, vec = self.cfg, self.weights()
        specs = self.worker_specs()
        if cfg.backend == "ray":
            return RayCollector(specs, cfg.local_buffer, vec, cfg.address,
                                cfg.max_worker_restarts, self.log)  # fmt: skip
        if cfg.workers == 1:
            col = InProcessCollector(specs, cfg.local_buffer)
            col.publish(vec)
            return col
        return ProcessCollector(specs, cfg.local_buffer, vec, cfg.max_worker_restarts, self.log)

    def weights(self) -> np.ndarray:
        return weight_vector(self.learner.actor, self.learner.critic)

    # -------------------------------------------------------------- learner loop
    def ingest(self, chunk: Chunk, window: Window) -> None:
        """Chunk → replay, counters, curve window."""
        self.replay.add_batch(chunk["obs"], chunk["decision"], chunk["params"], chunk["reward"],
                              chunk["next_obs"], chunk["done"], chunk["labelled"],
                              chunk["label_decision"], chunk["label_params"])  # fmt: skip
        n = len(chunk["decision"])
        key = (self.c["run"], chunk["worker_id"], chunk["incarnation"])
        if chunk["seq"] != self.received.get(key, 0) + 1:
            self.gaps += 1
        self.received[key] = chunk["seq"]
        self.c["env_steps"] += n
        self.c["sim_steps"] += chunk["sim_steps"]
        self.c["chunks"] += 1
        self.c["episodes"] += len(chunk["episodes"])
        self.c["demo_received"][chunk["worker_id"]] += int(chunk["demo"])
        self.c["learned_received"] = self.c.get("learned_received", 0) + n - int(chunk["demo"])
        window.add_chunk(chunk)

    def owed_updates(self) -> int:
        """Updates the ratio asks for now (0 until ``learning_starts``; ratio 0 → always 1)."""
        cfg = self.cfg
        if len(self.replay) < max(cfg.learning_starts, cfg.batch_size):
            return 0
        if cfg.update_ratio == 0:
            return 1
        target = math.floor(cfg.update_ratio * (self.c["env_steps"] - cfg.learning_starts))
        return max(0, target - (self.c["updates"] - self.c.get("pretrain_done", 0)))

    def pretrain_due(self) -> bool:
        """The demonstration phase is over (all demonstrations arrived, or a worker has switched
        to its own policy: quotas are per worker and fill at different rates) and the demo-only
        updates have not run yet."""
        cfg = self.cfg
        demos = sum(self.c["demo_received"])
        over = demos >= cfg.demo_steps or self.c.get("learned_received", 0) > 0
        return bool(cfg.pretrain_updates) and not self.c.get("pretrain_done") and over

    def pretrain(self, window: Window, collector: Any) -> None:
        """Updates on the replay as it is (the demonstrations), then publish the weights.

        The actor learns by behaviour cloning alone here (α = 0): early on the critic's Q is
        noise, and its gradient would pull the actor away from the demonstrations.
        """
        rl_cfg = self.learner.cfg
        self.learner.cfg = replace(rl_cfg, alpha=0.0)
        try:
            for _ in range(self.cfg.pretrain_updates):
                self.update_once(window, collector)
        finally:
            self.learner.cfg = rl_cfg
        self.c["pretrain_done"] = self.cfg.pretrain_updates
        collector.publish(self.weights())
        # kept apart: the policy before any RL update, to compare against the final one
        save_checkpoint(
            self.out / "pretrained.pt", self.learner, {**self._meta(), "phase": "pretrained"}
        )

    def lr_now(self) -> float:
        """The scheduled learning rate after ``env_steps`` transitions (cosine to lr_final)."""
        cfg = self.cfg
        if not cfg.lr_final:
            return cfg.lr
        done = min(1.0, self.c["env_steps"] / cfg.env_steps)
        return cfg.lr_final + 0.5 * (cfg.lr - cfg.lr_final) * (1 + math.cos(math.pi * done))

    def update_once(self, window: Window, collector: Any) -> None:
        self.learner.set_lr(self.lr_now())
        batch = self.replay.sample(self.cfg.batch_size, self.rng)
        losses = self.learner.update(batch)
        window.c_loss.append(losses["critic_loss"])
        window.a_loss.append(losses["actor_loss"])
        self.c["updates"] += 1
        if self.c["updates"] % self.cfg.sync_every == 0:
            collector.publish(self.weights())

    def budget_left(self, t_start: float) -> bool:
        cfg = self.cfg
        if cfg.env_steps and self.c["env_steps"] >= cfg.env_steps:
            return False
        return not (cfg.minutes and time.monotonic() - t_start >= 60 * cfg.minutes)

    def run(self) -> dict[str, Any]:
        """Train until the budget is spent; checkpoint; write auto.pt/auto.json → summary."""
        cfg = self.cfg
        self.out.mkdir(parents=True, exist_ok=True)
        tb = _tensorboard(self.out)
        t0 = time.monotonic()
        wall0 = self.c["wall_time"]
        last_ckpt = last_bar = t0
        window = Window()
        bar = _progress(cfg, self.c["env_steps"])
        collector = self.make_collector()
        self.collector = collector
        try:
            while self.budget_left(t0):
                if self.pretrain_due():
                    self.pretrain(window, collector)
                owed = self.owed_updates()
                if collector.synchronous:
                    for _ in range(owed):
                        self.update_once(window, collector)
                    chunks = collector.poll(0)
                else:
                    if owed > 0:
                        self.update_once(window, collector)
                    chunks = [] if owed > cfg.max_lag else collector.poll(0 if owed else 0.2)
                for chunk in chunks:
                    before = self.c["env_steps"]
                    self.ingest(chunk, window)
                    bar.update(self.c["env_steps"] - before)
                if chunks and time.monotonic() - last_bar >= 1.0:
                    self._postfix(bar, window)
                    last_bar = time.monotonic()
                self.c["worker_restarts"] = self.restart_base + collector.restarts
                self.c["wall_time"] = wall0 + time.monotonic() - t0
                if self.c["env_steps"] >= self.c["next_log"]:
                    self._log_row(window, tb, bar)
                    window = Window()
                    while self.c["next_log"] <= self.c["env_steps"]:
                        self.c["next_log"] += cfg.log_every
                if time.monotonic() - last_ckpt >= cfg.checkpoint_every:
                    self.save(snapshot=cfg.keep_snapshots)
                    last_ckpt = time.monotonic()
        finally:
            collector.close()
            bar.close()
        if window.transitions:
            self._log_row(window, tb, bar)
        self.c["wall_time"] = wall0 + time.monotonic() - t0
        self.save()
        info = self.finish()
        if tb is not None:
            tb.close()
        return info

    def _log_row(self, window: Window, tb: Any, bar: Any) -> None:
        row = {"env_steps": self.c["env_steps"], "wall_time": round(self.c["wall_time"], 3),
               "episodes": self.c["episodes"], "updates": self.c["updates"],
               "replay_size": len(self.replay), **window.row()}  # fmt: skip
        self._write_curves([row])
        if tb is not None:
            for k, v in row.items():
                if k != "env_steps" and not (isinstance(v, float) and math.isnan(v)):
                    tb.add_scalar(f"train/{k}", v, self.c["env_steps"])
        self._last_row = row

    def _postfix(self, bar: Any, window: Window) -> None:
        """Progress bar: updates, and episode reward / collision rate of the last curve row."""
        row = getattr(self, "_last_row", None) or window.row()
        bar.set_postfix(
            upd=self.c["updates"], ep_rew=f"{row['mean_episode_reward']:.3g}",
            coll=f"{row['collision_rate']:.3f}", demo=f"{row['demo_fraction']:.2f}",
            restarts=self.c["worker_restarts"], refresh=False,
        )  # fmt: skip


def _tensorboard(out: Path) -> Any:
    """A SummaryWriter under ``out/tb`` when torch.utils.tensorboard + tensorboard import."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(str(out / "tb"))


def _progress(cfg: TrainConfig, initial: int) -> Any:
    from tqdm import tqdm

    return tqdm(total=cfg.env_steps or None, initial=initial, unit="tr", desc="train",
                disable=not cfg.progress, dynamic_ncols=True, smoothing=0.05)  # fmt: skip
