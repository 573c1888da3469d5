"""The env as a benchmark: versioned tasks with a system-level reward and a normalised score.

    from mixed_traffic.benchmark import TASKS, parallel_env
    env = parallel_env("ring-v2")                    # the task's training config
    env = parallel_env("ring-v2", split="eval", index=1)   # its second held-out config
    env = parallel_env("merge-v1", fixed_fleet=True) # any EnvConfig field overrides
    env = parallel_env("ring-v2", copies=16)         # 16 rings in one simulation
    venv = vec_env("ring-v2", copies=16)             # as Stable-Baselines3's VecEnv

- ``tasks``: ``Task``, ``TASKS``, ``get_task``, the task reward.
- ``score``: the score's references (the ring's uniform-flow speed) and normalisation.
- ``batch_vec``: a task's batched worlds as SB3's ``VecEnv`` (``vec_env``).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from mixed_traffic.benchmark.tasks import TASKS, Task, get_task
from mixed_traffic.config import EnvConfig
from mixed_traffic.env.parallel import MixedTrafficEnv

__all__ = ["TASKS", "Task", "get_task", "parallel_env", "task_config", "vec_env"]


def task_config(task: str, split: str = "train", index: int = 0, **overrides: Any) -> EnvConfig:
    """The ``EnvConfig`` of ``task``'s ``split`` ("train", "eval" or "validate"; the split's
    ``index``-th config), with ``overrides`` (EnvConfig fields) applied. ``ValueError`` on a bad name,
    split or index."""
    t = get_task(task)
    splits = {"train": (t.train,), "eval": t.eval, "validate": t.validation}
    if split not in splits:
        raise ValueError(f"split={split!r}: give one of {list(splits)}")
    configs = splits[split]
    if not 0 <= index < len(configs):
        raise ValueError(f"index={index}: task {t.name} has {len(configs)} {split} config(s)")
    return replace(configs[index], **overrides)


def parallel_env(
    task: str, split: str = "train", index: int = 0, **overrides: Any
) -> MixedTrafficEnv:
    """The PettingZoo ParallelEnv of a task (see :func:`task_config`)."""
    return MixedTrafficEnv(config=task_config(task, split, index, **overrides))


def vec_env(task: str, copies: int = 1, split: str = "train", index: int = 0,
            **overrides: Any) -> Any:  # fmt: skip
    """Stable-Baselines3's ``VecEnv`` of ``copies`` copies of a task in one simulation, one
    row per agent (:mod:`mixed_traffic.benchmark.batch_vec`; needs the ``ppo`` extra)."""
    from mixed_traffic.benchmark.batch_vec import vec_env as make

    return make(task, copies, split, index, **overrides)
