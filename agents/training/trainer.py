"""Multi-worker RBP-DQN training (paper §IV-F; DESIGN §10): N rollout workers, one learner.

Topology: each worker (:mod:`agents.collection.workers`) runs one env with a single-threaded copy of the
policy and its own exploration (Ape-X ladder, :func:`agents.collection.workers.exploration_ladder`), and
flushes its LocalBuffer in chunks of ≥ ``local_buffer`` transitions to the learner. The learner
(this process) holds the GlobalBuffer (:class:`agents.learners.replay.ReplayBuffer`), runs
:meth:`agents.learners.rbpdqn.RBPDQN.update` at ``update_ratio`` updates per transition received, and
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

Outputs in ``out``: ``curves.csv`` (+ TensorBoard if installed); every ``checkpoint_every``
seconds and at the end one commit (:mod:`agents.training.commit`) of ``checkpoint.pt`` (learner
and optimisers), ``replay.pt`` and ``state.json`` (counters, RNG), from which ``--resume``
continues after a kill -9 at any instant; a copy of the last ``checkpoint.pt`` in ``out``; with
``keep_snapshots`` each periodic checkpoint also as ``snapshots/<env steps>.pt``; then
``auto.pt`` + ``auto.json`` (command, git revision, wall time, env steps, config).

The pieces: :mod:`agents.training.config` (:class:`TrainConfig`), :mod:`agents.training.collectors`
(the learner's side of each backend), :mod:`agents.training.curves` (``curves.csv``); this module
holds the :class:`Trainer` (learner loop, checkpoints, resume).
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from agents.checkpoint import checkpoint_payload, load_checkpoint, save_checkpoint
from agents.collection.workers import Chunk, WorkerSpec, exploration_ladder, weight_vector
from agents.learners.rbpdqn import LearnerConfig
from agents.learners.replay import ReplayBuffer
from agents.learners.variants import make_learner
from agents.training.collectors import make_collector
from agents.training.commit import commit, committed, remove_leftovers
from agents.training.config import TrainConfig, env_base_config, lca_config
from agents.training.curves import Window, progress, tensorboard, trim_curves, write_curves
from mixed_traffic.config import EnvConfig
from mixed_traffic.provenance import atomic_write

__all__ = ["TrainConfig", "Trainer", "atomic_write_json"]


def atomic_write_json(path: Path, data: dict) -> None:
    """Write ``data`` as indented JSON to ``path`` atomically."""
    atomic_write(path, lambda f: f.write(json.dumps(data, indent=2).encode()))


def _learner_config(cfg: TrainConfig) -> LearnerConfig:
    """The RBP-DQN learner's settings from the run's."""
    rl_only = cfg.bp_dqn or cfg.baseline in ("drl-mf", "head", "p-ddpg", "q-pamdp")
    algorithm = {"transfuser": "imitation", "p-ddpg": "p-ddpg", "q-pamdp": "q-pamdp"}
    return LearnerConfig(batch_size=cfg.batch_size, regularize=not rl_only, alpha=cfg.alpha,
                         algorithm=algorithm.get(cfg.baseline, "rbp-dqn"),
                         steer_control=cfg.baseline != "head",
                         lr=cfg.lr, bc_accel_weight=cfg.accel_bc_weight,
                         bc_accel_expectile=cfg.bc_accel_expectile, gamma=cfg.gamma,
                         residual=cfg.residual, steer_delta=cfg.steer_delta,
                         accel_delta=cfg.accel_delta, teacher_bonus=cfg.teacher_bonus,
                         decision_interval=cfg.decision_interval, multi_pass=cfg.multi_pass,
                         speed_governor=cfg.speed_governor,
                         rss_governor=cfg.rss_governor, twin=cfg.twin, set_speed=cfg.set_speed,
                         teacher=cfg.demo_policy if cfg.residual else "acc-lc",
                         # u of the residual form is already in bounded units, and ACC-LC's
                         # decisions get a selection bonus instead of the DQfD margin; a set
                         # speed is cloned as lightly as the acceleration (at 1.0 the pull to
                         # u = 0 held it there in the first auto-ring pilot)
                         **({"bc_steer_weight": cfg.accel_bc_weight if cfg.set_speed else 1.0,
                             "demo_weight": 0.0} if cfg.residual else {}))  # fmt: skip


def _fresh_counters(cfg: TrainConfig) -> dict[str, Any]:
    """The counters of a new run (``Trainer.c``; saved in state.json)."""
    return {
        "env_steps": 0, "sim_steps": 0, "updates": 0, "episodes": 0, "chunks": 0,
        "wall_time": 0.0, "run": 0, "worker_restarts": 0, "next_log": cfg.log_every,
        "demo_received": [0] * cfg.workers,
    }  # fmt: skip


@dataclass
class _Loop:
    """State of one :meth:`Trainer.run` between loop iterations."""

    tb: Any
    """TensorBoard writer or None."""
    t0: float
    """time.monotonic() at the start of this invocation."""
    wall0: float
    """Wall time of the earlier invocations [s]."""
    last_ckpt: float
    """time.monotonic() of the last checkpoint."""
    last_bar: float
    """time.monotonic() of the last progress-bar postfix."""
    window: Window
    """The curve window being filled."""
    bar: Any
    """The tqdm progress bar."""


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
        self.learner = make_learner(
            self.lca, _learner_config(cfg), seed=cfg.seed, compile=cfg.learner_compile
        )
        self.replay = ReplayBuffer(cfg.replay_capacity, self.lca)
        self.rng = np.random.default_rng([cfg.seed, 7])
        self.c: dict[str, Any] = _fresh_counters(cfg)
        self.received: dict[tuple[int, int, int], int] = {}
        """(run, worker, incarnation) → last chunk seq received (checks nothing went missing)."""
        self.gaps = 0
        """Chunks that arrived out of sequence (must stay 0: nothing sent is ever lost)."""
        self.restart_base = 0
        self._start(resume)

    def _start(self, resume: bool) -> None:
        """Resume the run in ``out`` from its last commit, or start a new one (from ``init``'s
        networks if given); then record this invocation. ``--resume`` on a run killed before
        its first commit starts afresh."""
        last = committed(self.out)
        if last is not None and not resume:
            raise FileExistsError(
                f"{self.out} already holds a training run; pass --resume or another --out"
            )
        remove_leftovers(self.out)
        if last is not None:
            self._load(last)
        else:
            if resume:
                self.log(f"--resume: nothing committed in {self.out} yet; starting afresh")
            trim_curves(self.out / "curves.csv", -1)  # rows of a run that never committed
            if self.cfg.init:
                self._init_from(Path(self.cfg.init))
        # every invocation of this run, first to last (auto.json provenance); the revision is
        # taken now, as commits made while a run trains do not change the code it runs
        from mixed_traffic.provenance import git_revision

        self.c["commands"] = [*self.c.get("commands", []), self.command]
        self.c["revisions"] = [*self.c.get("revisions", []), git_revision()]

    # -------------------------------------------------------------- persistence
    def _load(self, folder: Path) -> None:
        """Restore networks, optimisers, replay, counters and RNG from the commit ``folder``."""
        state = json.loads((folder / "state.json").read_text())
        self._check_resumable(TrainConfig.from_dict(state["config"]))
        load_checkpoint(folder / "checkpoint.pt", learner=self.learner)
        sd = torch.load(folder / "replay.pt", map_location="cpu", weights_only=True)
        self.replay.load_state_dict(sd)
        self.c.update(state["counters"])
        self.c["run"] += 1
        self.restart_base = self.c["worker_restarts"]
        self.rng.bit_generator.state = state["rng"]
        if self.learner.steps != self.c["updates"]:  # cannot happen with one commit; checked
            raise ValueError(
                f"--resume: {folder} has a checkpoint of {self.learner.steps} updates and "
                f"counters of {self.c['updates']}"
            )
        trim_curves(self.out / "curves.csv", self.c["env_steps"])
        self.log(f"resumed {self.out}: {self.c['env_steps']} env steps, "
                 f"{self.c['updates']} updates, replay {len(self.replay)}")  # fmt: skip

    def _check_resumable(self, old: TrainConfig) -> None:
        """ValueError when a setting the saved state depends on differs from the run's."""
        for name in ("ablation", "baseline", "ego_fusion", "bp_dqn", "replay_capacity", "workers"):
            if getattr(old, name) != getattr(self.cfg, name):
                raise ValueError(
                    f"--resume: {name}={getattr(self.cfg, name)!r} differs from the run in "
                    f"{self.out} ({getattr(old, name)!r})"
                )

    def _init_from(self, path: Path) -> None:
        """Start from ``path``'s networks; its provenance goes into this run's (``init``)."""
        _, meta = load_checkpoint(path, learner=self.learner, widen=True)
        self.learner.steps = 0  # this run's update counter (resume checks they agree)
        keys = ("commands", "git_revision", "env_steps", "updates", "wall_time")
        self.c["init"] = {"path": str(path), **{k: meta.get(k) for k in keys}}
        self.log(f"initialised from {path} ({meta.get('env_steps')} env steps)")

    def save(self, snapshot: bool = False) -> None:
        """Commit checkpoint, replay and counters as one unit (:mod:`agents.training.commit`);
        then copy the checkpoint to ``out/checkpoint.pt`` (and a snapshot), each atomically."""
        payload = checkpoint_payload(self.learner, self._meta())
        replay = self.replay.state_dict()
        state = {"config": self.cfg.to_dict(), "counters": self.c,
                 "rng": self.rng.bit_generator.state}  # fmt: skip
        folder = commit(self.out, {
            "checkpoint.pt": lambda f: torch.save(payload, f),
            "replay.pt": lambda f: torch.save(replay, f),
            "state.json": lambda f: f.write(json.dumps(state, indent=2).encode()),
        })  # fmt: skip
        copies = [self.out / "checkpoint.pt"]
        if snapshot:
            copies.append(self.out / "snapshots" / f"{self.c['env_steps']:09d}.pt")
        data = (folder / "checkpoint.pt").read_bytes()
        for path in copies:
            atomic_write(path, lambda f: f.write(data))

    def _meta(self) -> dict[str, Any]:
        """Provenance and counters stored with every checkpoint."""
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
        """One spec per worker: its exploration rung, demonstration quota and seeds."""
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
                learner=self.learner.cfg, reward_scale=cfg.reward_scale,
                bootstrap_arrival=cfg.bootstrap_arrival, n_step=cfg.n_step,
                explore_hold=cfg.explore_hold, wave_share=cfg.wave_share,
                wave_kinds=cfg.wave_kinds,
                crash_after_chunks=cfg.crash_after_chunks if i == 0 and self.c["run"] == 0 else 0,
            )
            for i in range(cfg.workers)
        ]  # fmt: skip

    def make_collector(self) -> Any:
        """The backend's collector (:mod:`agents.training.collectors`), weights published."""
        vec = self.weights()
        return make_collector(self.cfg, self.worker_specs(), vec, self.log)

    def weights(self) -> np.ndarray:
        """The learner's actor and critic as one flat vector (the broadcast format)."""
        return weight_vector(self.learner.actor, self.learner.critic)

    # -------------------------------------------------------------- learner loop
    def ingest(self, chunk: Chunk, window: Window) -> None:
        """Chunk → replay, counters, curve window."""
        self.replay.add_batch(chunk["obs"], chunk["decision"], chunk["params"], chunk["reward"],
                              chunk["next_obs"], chunk["done"], chunk["labelled"],
                              chunk["label_decision"], chunk["label_params"],
                              chunk["discount"])  # fmt: skip
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
        """One learner update at the scheduled rate; broadcast every ``sync_every`` updates."""
        self.learner.set_lr(self.lr_now())
        batch = self.replay.sample(self.cfg.batch_size, self.rng)
        losses = self.learner.update(batch)
        window.c_loss.append(losses["critic_loss"])
        window.a_loss.append(losses["actor_loss"])
        self.c["updates"] += 1
        if self.c["updates"] % self.cfg.sync_every == 0:
            collector.publish(self.weights())

    def budget_left(self, t_start: float) -> bool:
        """Neither the env-steps nor the wall-time budget (from ``t_start``) is spent."""
        cfg = self.cfg
        if cfg.env_steps and self.c["env_steps"] >= cfg.env_steps:
            return False
        return not (cfg.minutes and time.monotonic() - t_start >= 60 * cfg.minutes)

    def run(self) -> dict[str, Any]:
        """Train until the budget is spent; checkpoint; write auto.pt/auto.json → summary."""
        self.out.mkdir(parents=True, exist_ok=True)
        tb = tensorboard(self.out)
        t0 = time.monotonic()
        wall0 = self.c["wall_time"]
        window = Window()
        bar = progress(self.cfg.env_steps, self.c["env_steps"], self.cfg.progress)
        loop = _Loop(tb=tb, t0=t0, wall0=wall0, last_ckpt=t0, last_bar=t0, window=window, bar=bar)
        collector = self.make_collector()
        self.collector = collector
        try:
            while self.budget_left(loop.t0):
                self._iterate(loop, collector)
        finally:
            collector.close()
            loop.bar.close()
        if loop.window.transitions:
            self._log_row(loop.window, loop.tb, loop.bar)
        self.c["wall_time"] = loop.wall0 + time.monotonic() - loop.t0
        self.save()
        info = self.finish()
        if loop.tb is not None:
            loop.tb.close()
        return info

    def _iterate(self, loop: _Loop, collector: Any) -> None:
        """One pass of the learner loop: pretraining when due, the owed updates, the chunks
        that arrived, then progress, curves and checkpoints when due."""
        if self.pretrain_due():
            self.pretrain(loop.window, collector)
        chunks = self._update_and_poll(loop.window, collector)
        for chunk in chunks:
            before = self.c["env_steps"]
            self.ingest(chunk, loop.window)
            loop.bar.update(self.c["env_steps"] - before)
        if chunks and time.monotonic() - loop.last_bar >= 1.0:
            self._postfix(loop.bar, loop.window)
            loop.last_bar = time.monotonic()
        self.c["worker_restarts"] = self.restart_base + collector.restarts
        self.c["wall_time"] = loop.wall0 + time.monotonic() - loop.t0
        if self.c["env_steps"] >= self.c["next_log"]:
            self._log_row(loop.window, loop.tb, loop.bar)
            loop.window = Window()
            while self.c["next_log"] <= self.c["env_steps"]:
                self.c["next_log"] += self.cfg.log_every
        if time.monotonic() - loop.last_ckpt >= self.cfg.checkpoint_every:
            self.save(snapshot=self.cfg.keep_snapshots)
            loop.last_ckpt = time.monotonic()

    def _update_and_poll(self, window: Window, collector: Any) -> list[Chunk]:
        """The owed updates, then the chunks that arrived: a synchronous collector does all
        owed updates and collects one chunk; an asynchronous one does at most one update and
        stops reading while the learner lags more than ``max_lag`` updates (back-pressure)."""
        owed = self.owed_updates()
        if collector.synchronous:
            for _ in range(owed):
                self.update_once(window, collector)
            return collector.poll(0)
        if owed > 0:
            self.update_once(window, collector)
        return [] if owed > self.cfg.max_lag else collector.poll(0 if owed else 0.2)

    def _log_row(self, window: Window, tb: Any, bar: Any) -> None:
        """Append a curves row (and TensorBoard scalars) for ``window``."""
        row = {"env_steps": self.c["env_steps"], "wall_time": round(self.c["wall_time"], 3),
               "episodes": self.c["episodes"], "updates": self.c["updates"],
               "replay_size": len(self.replay), **window.row()}  # fmt: skip
        write_curves(self.out / "curves.csv", [row])
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
