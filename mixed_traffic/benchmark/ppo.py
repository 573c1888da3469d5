"""Train Stable-Baselines3's PPO on a benchmark task, in legs that resume.

    python -m mixed_traffic.benchmark.ppo --task ring-v2 --seed 0 --steps 400000
    python -m mixed_traffic.evaluate --policy ppo --checkpoint results/ppo/ring-v2-s0/best.zip

One policy is shared by every AV: the training env is ``copies`` copies of the task in one
simulation as SB3's ``VecEnv`` (:mod:`mixed_traffic.benchmark.batch_vec`), each AV of each
copy one row of SB3's batch. The AVs act through the longitudinal interface
(:mod:`mixed_traffic.benchmark.interface`: 8 features, one acceleration held for 0.5 s) and
are rewarded with the task's reward. After every leg of ``leg`` decisions the weights and
the optimiser go to ``out/model.zip`` (atomically; no rollout buffer is kept, PPO has no replay),
the reward scaler's statistics to ``reward_norm.pkl``, its metadata to ``model.json``, and one
row to ``curves.csv``: the leg's training returns and a greedy validation on the task's
validation configs (never its eval configs) through the one episode runner: fleet speed std and
mean speed against all-human traffic on the same episodes. The best leg so far is kept as
``best.zip`` (:mod:`mixed_traffic.benchmark.selection`): the run's output. A re-run continues
from ``model.zip`` (also after kill -9: at most one leg is lost) until ``steps`` decisions.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import pickle
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agents.longitudinal import LongitudinalConfig
from agents.ppo_policy import meta_path, read_meta
from mixed_traffic.benchmark import get_task, selection, task_config
from mixed_traffic.experiments.cli import add_config_args, config_from_args
from mixed_traffic.paths import RESULTS
from mixed_traffic.provenance import atomic_write, git_revision, sumo_version

#: The reward scaler's running statistics, beside ``model.zip``.
NORM_FILE = "reward_norm.pkl"
CURVE_FIELDS = ("leg", "timesteps", "env_steps", "train_seconds", "decisions_per_s", "episodes",
                "mean_return", *selection.FIELDS)  # fmt: skip


@dataclass(frozen=True)
class PpoConfig:
    """One training run. The CLI is built from it; SB3's PPO defaults where not named."""

    task: str = "ring-v2"
    """Benchmark task id (``mixed_traffic.benchmark.TASKS``)."""
    seed: int = 0
    """Seeds the env (its episodes' demand, SUMO, noise, ring lengths), numpy and torch."""
    steps: int = 400_000
    """Decisions (SB3 timesteps, one per AV and 0.5 s) to train in all legs together."""
    leg: int = 20_480
    """Decisions per leg: a checkpoint and a curve row after each."""
    n_steps: int = 2048
    """Decisions per rollout before each PPO update, over all rows (each row, one AV of the
    batch, takes n_steps / rows of them)."""
    copies: int = 32
    """Copies of the task in the training simulation (batched worlds: one row per AV of each
    copy; 32 the fastest per core measured on ring-v2, docs/marl.md)."""
    batch_size: int = 256
    """Minibatch size of the updates."""
    n_epochs: int = 10
    """Passes over each rollout."""
    learning_rate: float = 3e-4
    """Adam step size."""
    gamma: float = 0.99
    """Discount per decision (0.5 s): a horizon of about 50 s, longer than a ring wave's period
    (about 30 s)."""
    gae_lambda: float = 0.95
    """GAE lambda."""
    normalize_reward: bool = True
    """Scale rewards by a running std of the discounted return (SB3's ``VecNormalize``, as RL
    Zoo's PPO): the critic then fits returns of order 1. Unscaled, ring-v2's returns are about
    250 per decision, and after 164k decisions the critic still predicted 114 (RMSE 150)."""
    explore_hold: float = 30.0
    """Time an exploration draw is held [s] (SB3's gSDE: the noise is a random linear function
    of the policy's last hidden layer, redrawn this often, so an exploring AV drives one
    perturbed policy for about a ring wave's period and its effect on the waves shows in the
    return); 0 = independent Gaussian noise every decision."""
    log_std_init: float = -2.2
    """Initial log std of the exploration: per hidden feature with gSDE (e^-2.2 gives an action
    std of about 0.37, 1.1 m/s²), of the action without (e^-1 for the same)."""
    hidden: tuple[int, ...] = (64, 64)
    """Hidden layer widths of the actor and of the critic (tanh)."""
    episode_length: float = 0.0
    """Simulated time per training and evaluation episode [s]; 0 = the task's horizon."""
    val_seed: int = 1000
    """First seed of the per-leg validation (the same every leg; the eval uses 0, 1, 2 …)."""
    val_seeds: int = 2
    """Validation episodes per validation config (seeds ``val_seed`` onwards)."""
    out: Path | None = None
    """Folder of the run (default: results/ppo/<task>-s<seed>; the shipped runs are in
    agents/checkpoints/ppo)."""
    init: Path | None = None
    """A curriculum: a new run starts from this ``model.zip`` (weights, optimiser and decision
    count of another run, e.g. of an earlier task version) instead of random weights."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "task", get_task(self.task).name)
        if self.out is None:
            object.__setattr__(self, "out", RESULTS / "ppo" / f"{self.task}-s{self.seed}")
        for name in ("steps", "leg", "n_steps", "batch_size", "n_epochs", "val_seeds"):
            if getattr(self, name) < 1:
                raise ValueError(f"--{name.replace('_', '-')}={getattr(self, name)} must be >= 1")
        if self.episode_length < 0 or self.explore_hold < 0:
            raise ValueError(f"--episode-length={self.episode_length} and --explore-hold="
                             f"{self.explore_hold} must be >= 0")  # fmt: skip
        if (
            min(self.seed, self.val_seed) < 0
            or not 0 < self.gamma <= 1
            or not 0 < self.learning_rate < 1
        ):
            raise ValueError("--seed and --val-seed must be >= 0, --gamma in (0, 1], "
                             "--learning-rate in (0, 1)")  # fmt: skip
        if self.init is not None:
            read_meta(self.init)  # ValueError naming a --init that is not a PPO run's model.zip
        if not self.hidden or min(self.hidden) < 1:
            raise ValueError(f"--hidden={list(self.hidden)}: give layer widths >= 1")


def _config(cfg: PpoConfig, split: str = "train", index: int = 0, **overrides: Any):
    """The task's config with the run's seed and episode length."""
    if cfg.episode_length:
        overrides["episode_length"] = cfg.episode_length
    return task_config(cfg.task, split, index, seed=cfg.seed, **overrides)


def interface_config(cfg: PpoConfig) -> LongitudinalConfig:
    """The learner interface of the run: the task's step and interface settings."""
    return LongitudinalConfig(dt=_config(cfg).step_length, **dict(get_task(cfg.task).learner))


def training_env(cfg: PpoConfig) -> Any:
    """SB3 VecEnv of the task's training config on ``cfg.copies`` batched worlds
    (:mod:`mixed_traffic.benchmark.batch_vec`): one row per AV. A ring keeps its one AV per
    copy; elsewhere the fleet is fixed (AVs re-enter upstream) so the batch keeps its width."""
    from stable_baselines3.common.vec_env import VecMonitor

    from mixed_traffic.benchmark.batch_vec import vec_env

    extra = {"episode_length": cfg.episode_length} if cfg.episode_length else {}
    venv = vec_env(cfg.task, copies=cfg.copies, seed=cfg.seed, **extra)
    return _normalised(cfg, VecMonitor(venv))


def _normalised(cfg: PpoConfig, venv: Any) -> Any:
    """``venv`` with rewards scaled (``cfg.normalize_reward``; returns stay unscaled in the
    monitor's episode records), resuming the run's running statistics where saved."""
    from stable_baselines3.common.vec_env import VecNormalize

    if not cfg.normalize_reward:
        return venv
    path = cfg.out / NORM_FILE
    if not path.is_file():  # a new run, or one resumed from its weights alone
        return VecNormalize(venv, norm_obs=False, norm_reward=True, gamma=cfg.gamma)
    try:
        return VecNormalize.load(str(path), venv)
    except Exception as e:  # pickle raises many types for a corrupt file
        raise ValueError(
            f"{path}: unreadable reward statistics ({e}); delete it to re-estimate "
            "them from the next rollouts"
        ) from e


def _model(cfg: PpoConfig, venv: Any) -> Any:
    """A new PPO, or the run's last checkpoint (else ``cfg.init``) with ``venv`` attached."""
    from stable_baselines3 import PPO

    path = cfg.out / "model.zip"
    if path.is_file() or cfg.init is not None:
        return PPO.load(str(path if path.is_file() else cfg.init), env=venv, device="cpu")
    arch = list(cfg.hidden)
    interface = interface_config(cfg)
    held = max(1, round(cfg.explore_hold / (interface.hold * interface.dt)))  # decisions
    n_steps = max(1, cfg.n_steps // venv.num_envs)  # per row
    return PPO("MlpPolicy", venv, n_steps=n_steps, batch_size=cfg.batch_size,
               n_epochs=cfg.n_epochs, learning_rate=cfg.learning_rate, gamma=cfg.gamma,
               gae_lambda=cfg.gae_lambda, seed=cfg.seed, device="cpu", verbose=0,
               use_sde=cfg.explore_hold > 0, sde_sample_freq=held,
               policy_kwargs={"log_std_init": cfg.log_std_init,
                              "net_arch": {"pi": arch, "vf": arch}})  # fmt: skip


def _returns_callback(returns: list[float]) -> Any:
    """An SB3 callback appending each finished episode's return (VecMonitor's) to ``returns``."""
    from stable_baselines3.common.callbacks import BaseCallback

    class Returns(BaseCallback):
        def _on_step(self) -> bool:
            returns.extend(i["episode"]["r"] for i in self.locals["infos"] if "episode" in i)
            return True

    return Returns()


def _save(cfg: PpoConfig, model: Any, meta: dict[str, Any]) -> None:
    """Write ``model.zip`` and ``model.json`` atomically (the json last: it names the zip's
    timesteps, so a crash between them leaves an older json, never a missing one)."""
    buf = io.BytesIO()
    model.save(buf)
    atomic_write(cfg.out / "model.zip", lambda f: f.write(buf.getvalue()))
    norm = model.get_vec_normalize_env()
    if norm is not None:
        stats = pickle.dumps(norm)  # VecNormalize pickles without its venv
        atomic_write(cfg.out / NORM_FILE, lambda f: f.write(stats))
    text = json.dumps(meta, indent=1).encode()
    atomic_write(meta_path(cfg.out / "model.zip"), lambda f: f.write(text))


def _validate(cfg: PpoConfig, human: list[dict[str, float]]) -> dict[str, float]:
    """The greedy policy of ``model.zip`` on the task's validation episodes against the
    all-human ``human`` metrics (``selection.FIELDS``)."""
    runs = selection.episode_metrics(_validation(cfg), "ppo", cfg.out / "model.zip", _warmup(cfg))
    return selection.ratios(runs, human)


def _validation(cfg: PpoConfig) -> list[Any]:
    extra = {"episode_length": cfg.episode_length} if cfg.episode_length else {}
    return selection.validation_configs(cfg.task, cfg.val_seed, cfg.val_seeds, **extra)


def _warmup(cfg: PpoConfig) -> float:
    return get_task(cfg.task).warmup


def read_curves(folder: Path) -> list[dict[str, float]]:
    """The rows of ``folder/curves.csv`` (none if it does not exist)."""
    path = Path(folder) / "curves.csv"
    if not path.is_file():
        return []
    with path.open() as f:
        return [{k: _number(v) for k, v in row.items()} for row in csv.DictReader(f)]


def _number(text: str) -> float:
    value = float(text) if text else float("nan")  # a column an older run did not fill
    return int(value) if value.is_integer() else value


def _append_curve(cfg: PpoConfig, row: dict[str, float]) -> None:
    rows = [*read_curves(cfg.out), row]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, CURVE_FIELDS, restval="", extrasaction="ignore",
                            lineterminator="\n")  # fmt: skip
    writer.writeheader()
    writer.writerows(rows)
    atomic_write(cfg.out / "curves.csv", lambda f: f.write(buf.getvalue().encode()))


def train(cfg: PpoConfig, progress: bool = True) -> dict[str, Any]:
    """Run legs until ``cfg.steps`` decisions; the metadata of the last checkpoint."""
    cfg.out.mkdir(parents=True, exist_ok=True)
    venv = training_env(cfg)  # names a corrupt reward_norm.pkl before the baseline episodes
    human = selection.human(cfg.out, _validation(cfg), _warmup(cfg))
    model = _model(cfg, venv)
    curves = read_curves(cfg.out)
    interface = interface_config(cfg)
    meta = _resume(cfg, model, curves, human)
    seconds = float(meta.get("train_seconds", _init_seconds(cfg)))
    while model.num_timesteps < cfg.steps:
        returns: list[float] = []
        start = time.monotonic()
        leg = min(cfg.leg, cfg.steps - model.num_timesteps)
        before = model.num_timesteps
        model.learn(leg, callback=_returns_callback(returns), reset_num_timesteps=False)
        rate = (model.num_timesteps - before) / (time.monotonic() - start)
        seconds += time.monotonic() - start
        meta = {"task": cfg.task, "seed": cfg.seed, "timesteps": int(model.num_timesteps),
                "train_seconds": round(seconds, 1), "interface": asdict(interface),
                "config": {k: (str(v) if isinstance(v, Path) else v)
                           for k, v in asdict(cfg).items()},
                "revision": git_revision(), "sumo": sumo_version(),
                "library": _library(), "decisions_per_s": round(rate, 1)}  # fmt: skip
        _save(cfg, model, meta)
        _record(cfg, curves, meta, returns, human, progress)
    venv.close()
    return meta


def _resume(cfg: PpoConfig, model: Any, curves: list[dict[str, float]],
            human: list[dict[str, float]]) -> dict[str, Any]:  # fmt: skip
    """Finish the last leg's record where a kill cut it short: a checkpoint without its curve
    row gets the row (its returns are lost), and a row whose ``best.zip`` copy was cut off gets
    the copy. The run's checkpoint metadata ({} before its first leg)."""
    if not (cfg.out / "model.zip").is_file():
        return {}
    meta = read_meta(cfg.out / "model.zip")
    if not curves or curves[-1]["timesteps"] < model.num_timesteps:
        _record(cfg, curves, meta, [], human, progress=False)
    else:
        selection.keep_best(cfg.out, curves[-1], curves, meta)
    return meta


def _record(
    cfg: PpoConfig,
    curves: list[dict[str, float]],
    meta: dict[str, Any],
    returns: list[float],
    human: list[dict[str, float]],
    progress: bool,
) -> None:
    """Validate the leg that ``model.zip`` holds, append its curve row (to ``curves`` too) and
    keep it as ``best.zip`` if it ranks first."""
    steps = int(meta["timesteps"])
    row = {"leg": len(curves) + 1, "timesteps": steps,
           "env_steps": steps * interface_config(cfg).hold, "train_seconds": meta["train_seconds"],
           "decisions_per_s": meta.get("decisions_per_s", float("nan")),
           "episodes": len(returns), "mean_return": float(np.mean(returns)) if returns else float("nan"),
           **_validate(cfg, human)}  # fmt: skip
    _append_curve(cfg, row)
    curves.append(row)
    best = selection.keep_best(cfg.out, row, curves, meta)
    if progress:
        print(f"leg {row['leg']}: {steps} decisions, {meta['train_seconds'] / 60:.1f} min, "
              f"return {row['mean_return']:.2f}, validation std x{row['val_std_ratio']:.2f} "
              f"speed x{row['val_speed_ratio']:.2f}, collisions {row['val_collisions']}"
              f"{' (best so far)' if best else ''}", file=sys.stderr)  # fmt: skip


def _init_seconds(cfg: PpoConfig) -> float:
    """Training time [s] behind ``cfg.init`` (its run's metadata), 0 without one: a curriculum's
    time counts from its first stage."""
    if cfg.init is None:
        return 0.0
    return float(read_meta(cfg.init).get("train_seconds", 0.0))


def _library() -> dict[str, str]:
    import stable_baselines3
    import torch

    return {"stable_baselines3": stable_baselines3.__version__, "torch": torch.__version__}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m mixed_traffic.benchmark.ppo",
                                description=__doc__.split("\n\n")[0])  # fmt: skip
    add_config_args(p, PpoConfig)
    try:
        cfg = config_from_args(p.parse_args(argv), PpoConfig)
        import stable_baselines3  # noqa: F401  (the named extra, before any work)
    except ImportError:
        p.error("PPO training needs Stable-Baselines3: pip install 'mixed-traffic[ppo]'")
    except ValueError as e:
        p.error(str(e))
    import torch

    torch.set_num_threads(1)  # one core per run: SUMO is single-threaded, runs go side by side
    train(cfg)
    return 0


if __name__ == "__main__":
    sys.exit(main())
