"""Section ``throughput`` of ``python -m mixed_traffic.bench``: learner samples per core on
batched worlds (issue 60), every batch size measured side by side in one run.

For each task and number of copies N, in this one process (one core: SUMO, the env and the
policy run in it):

* ``env``: the task's ``vec_env`` with N copies driven by a fixed policy (the zero action:
  on ``ring-v2`` a human's IDM) for ``--throughput-decisions`` decisions after a warm-up
  episode start; decisions per second count the rows that had an agent on the road.
* ``ppo``: Stable-Baselines3's PPO training on the same ``vec_env`` (rollouts and updates; a
  rollout of 2,048 decisions split over the rows, as the recipe's).
* ``sumo_ratio``: the env's time per step and copy over SUMO's own step on the same joined
  network and demand with SUMO driving every vehicle (``sumo_drives_avs``), per copy.

* ``rbpdqn`` (``ring-v2`` rows): RBP-DQN's rollout worker collecting transitions as the
  shipped ``auto-ring`` run did (its settings: wave rings with one AV and a random warm-up
  that records nothing, decisions every 0.5 s), N copies per episode; collection only, no
  learner updates.

``ratio_to_single`` divides by the copies = 1 row of the same task and mode.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np

TASKS = ("ring-v2", "wave-highway-v1", "merge-v1")
COPIES = (1, 4, 8, 16, 32)
ROLLOUT = 2048
"""Decisions per PPO rollout, over all rows (the recipe's ``n_steps`` on one row)."""


@dataclass
class ThroughputResult:
    task: str
    copies: int
    mode: str
    """env (a fixed policy) | ppo (training updates included) | rbpdqn (collection)."""
    decisions_per_s_per_core: float
    ratio_to_single: float
    """This row's decisions/s over copies = 1's, same task and mode."""
    sumo_ratio: float
    """Env step time per copy over SUMO-alone step time per copy, same N (env mode; NaN for
    the others, null in the JSON)."""

    def record(self) -> dict[str, object]:
        return {"section": "throughput", "task": self.task, "copies": self.copies,
                "mode": self.mode,
                "decisions_per_s_per_core": round(self.decisions_per_s_per_core, 1),
                "ratio_to_single": round(self.ratio_to_single, 3),
                "sumo_ratio": None if np.isnan(self.sumo_ratio) else round(self.sumo_ratio, 3)}  # fmt: skip


def env_rate(task: str, copies: int, decisions: int) -> tuple[float, float]:
    """(decisions per second, env seconds per env step) of ``task``'s vec env, zero actions."""
    from mixed_traffic.benchmark import vec_env

    venv = vec_env(task, copies=copies, seed=0)
    try:
        venv.reset()
        venv.step(np.zeros((venv.num_envs, 1)))  # kernels and caches warm
        done, steps, t0 = 0, 0, time.perf_counter()
        while done < decisions:
            _, _, _, infos = venv.step(np.zeros((venv.num_envs, 1)))
            done += sum(i["active"] for i in infos)
            steps += venv.interface.c.hold
        seconds = time.perf_counter() - t0
    finally:
        venv.close()
    return done / seconds, seconds / steps


def sumo_step(task: str, copies: int, steps: int) -> float:
    """SUMO's own step on ``task``'s joined network and demand with SUMO driving every vehicle
    [s per step]."""
    from mixed_traffic.benchmark import task_config
    from mixed_traffic.env.parallel import MixedTrafficEnv

    env = MixedTrafficEnv(config=task_config(task, copies=copies, seed=0),
                          sumo_drives_avs=True, metrics=False)  # fmt: skip
    try:
        env.reset(seed=0)
        backend = env._backend
        for _ in range(10):
            backend.raw_step()
        t0 = time.perf_counter()
        for _ in range(steps):
            backend.raw_step()
        return (time.perf_counter() - t0) / steps
    finally:
        env.close()


def ppo_rate(task: str, copies: int, rollouts: int) -> float:
    """Decisions per second of SB3's PPO training on ``task``'s vec env (rollouts and
    updates, after one to warm up)."""
    from stable_baselines3 import PPO

    from mixed_traffic.benchmark import vec_env

    venv = vec_env(task, copies=copies, seed=0)
    try:
        n_steps = max(8, ROLLOUT // venv.num_envs)
        model = PPO("MlpPolicy", venv, n_steps=n_steps, batch_size=256, seed=0, device="cpu")
        model.learn(n_steps * venv.num_envs)  # warm-up rollout
        t0 = time.perf_counter()
        model.learn(rollouts * n_steps * venv.num_envs, reset_num_timesteps=False)
        return rollouts * n_steps * venv.num_envs / (time.perf_counter() - t0)
    finally:
        venv.close()


def rbpdqn_rate(copies: int, decisions: int) -> float:
    """Transitions per second that RBP-DQN's rollout worker collects with ``auto-ring``'s
    training settings and ``copies`` copies (its untrained network driving, after one chunk
    to warm up)."""
    import json
    import tempfile

    from agents.collection.workers import RolloutWorker
    from agents.training.config import TrainConfig
    from agents.training.trainer import Trainer
    from mixed_traffic.paths import REPO_ROOT

    meta = json.loads((REPO_ROOT / "agents/checkpoints/auto_ring.json").read_text())
    with tempfile.TemporaryDirectory() as out:
        cfg = TrainConfig.from_dict({**meta["train_config"], "out": out, "workers": 1,
                                     "copies": copies, "demo_steps": 0, "seed": 0})  # fmt: skip
        trainer = Trainer(cfg)
        worker = RolloutWorker(trainer.worker_specs()[0])
        worker.set_weights(trainer.weights())
        try:
            worker.collect(copies * 8)
            t0 = time.perf_counter()
            got = len(worker.collect(decisions)["decision"])
            return got / (time.perf_counter() - t0)
        finally:
            worker.close()


def section_throughput(args: argparse.Namespace) -> list[ThroughputResult]:
    """Every (task, copies, mode) row, and a table."""
    out: list[ThroughputResult] = []
    for task in args.throughput_tasks:
        single: dict[str, float] = {}
        for n in sorted({1, *args.throughput_copies}):
            rate, env_s = env_rate(task, n, args.throughput_decisions)
            sumo_s = sumo_step(task, n, args.throughput_steps)
            rows = [("env", rate, env_s / sumo_s)]
            if task in args.throughput_ppo:
                rows.append(("ppo", ppo_rate(task, n, args.throughput_rollouts), float("nan")))
            if task == "ring-v2" and args.throughput_rbpdqn:
                rows.append(("rbpdqn", rbpdqn_rate(n, args.throughput_rbpdqn), float("nan")))
            for mode, r, sumo_ratio in rows:
                single.setdefault(mode, r)
                out.append(ThroughputResult(task, n, mode, r, r / single[mode], sumo_ratio))
                print(
                    f"{task:16s} copies {n:3d} {mode:6s} {r:8.1f} decisions/s  "
                    f"x{r / single[mode]:5.2f}  env/SUMO per copy {sumo_ratio:5.2f}",
                    flush=True,
                )
    return out


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The section's options."""
    p.add_argument("--throughput-tasks", nargs="+", default=list(TASKS),
                   help=f"throughput section: tasks (default: {' '.join(TASKS)})")  # fmt: skip
    p.add_argument("--throughput-copies", type=int, nargs="+", default=list(COPIES),
                   help="throughput section: copies per simulation (default: "
                   f"{' '.join(map(str, COPIES))}; 1 is always run)")  # fmt: skip
    p.add_argument("--throughput-decisions", type=int, default=2000,
                   help="throughput section: timed decisions per env row (default: 2000)")  # fmt: skip
    p.add_argument("--throughput-steps", type=int, default=300,
                   help="throughput section: timed SUMO-alone steps (default: 300)")  # fmt: skip
    p.add_argument("--throughput-ppo", nargs="*", default=["ring-v2"],
                   help="throughput section: tasks that also time PPO training (default: ring-v2)")  # fmt: skip
    p.add_argument("--throughput-rbpdqn", type=int, default=2000,
                   help="throughput section: timed RBP-DQN transitions on ring-v2 rows "
                   "(default: 2000; 0 = none)")  # fmt: skip
    p.add_argument("--throughput-rollouts", type=int, default=2,
                   help="throughput section: timed PPO rollouts and updates (default: 2)")  # fmt: skip
