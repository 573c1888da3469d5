"""Checkpoint selection on a task's validation configs (never its eval configs).

After every training leg the greedy policy drives one episode per validation config and seed;
its fleet speed std and mean speed are taken as ratios to all-human traffic on the same
episodes (all-human metrics are cached in the run folder). The leg that ranks best is kept as
``best.zip`` beside ``model.zip``, with ``best.json`` naming the leg and its validation numbers:
that file is the run's output.

Rank (:func:`rank`): legs without a collision that keep at least the humans' mean speed come
first (a policy that slows the traffic does not damp it), and among them the lowest speed std
ratio; the other legs follow by their number of collisions, then by the std ratio.
"""

from __future__ import annotations

import json
import multiprocessing
import shutil
import tempfile
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from mixed_traffic.benchmark import get_task, task_config
from mixed_traffic.config import EnvConfig
from mixed_traffic.experiments.runner import run_episode
from mixed_traffic.provenance import atomic_write

#: The curve columns the validation fills.
FIELDS = ("val_std_ratio", "val_speed_ratio", "val_collisions")
#: All-human metrics of the validation episodes, beside ``model.zip``.
HUMAN_FILE = "validation_human.json"
BEST, BEST_META = "best.zip", "best.json"


def validation_configs(task: str, seed: int, seeds: int, **overrides: Any) -> list[EnvConfig]:
    """Every validation config of ``task`` at seeds ``seed .. seed + seeds - 1``."""
    n = len(get_task(task).validation)
    return [replace(task_config(task, "validate", i, **overrides), seed=seed + k)
            for i in range(n) for k in range(seeds)]  # fmt: skip


def _metrics(configs: list[EnvConfig], policy: str, checkpoint: Path | None,
             warmup: float) -> list[dict[str, float]]:  # fmt: skip
    """Speed std, mean speed and collisions of one episode per config (a missing speed metric
    raises rather than read as a perfect 0)."""
    runs = [run_episode(c, policy, warmup, checkpoint=checkpoint)["metrics"] for c in configs]
    return [{"speed_std": float(m["speed_std"]), "mean_speed": float(m["mean_speed"]),
             "collisions": float(m.get("collisions") or 0)} for m in runs]  # fmt: skip


def episode_metrics(configs: list[EnvConfig], policy: str, checkpoint: Path | None,
                    warmup: float) -> list[dict[str, float]]:  # fmt: skip
    """:func:`_metrics` in a fresh process: libsumo runs one simulation per process, and a
    training env holds this one's."""
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=1, mp_context=ctx) as pool:
        return pool.submit(_metrics, configs, policy, checkpoint, warmup).result()


def human(out: Path, configs: list[EnvConfig], warmup: float) -> list[dict[str, float]]:
    """All-human metrics of ``configs``, cached in ``out`` (re-run when the configs change)."""
    path = Path(out) / HUMAN_FILE
    key = [repr(c) for c in configs]
    if path.is_file():
        cached = json.loads(path.read_text())
        if cached.get("configs") == key:
            return cached["metrics"]
    metrics = episode_metrics(configs, "idm", None, warmup)
    text = json.dumps({"configs": key, "metrics": metrics}).encode()
    atomic_write(path, lambda f: f.write(text))
    return metrics


def ratios(runs: list[dict[str, float]], base: list[dict[str, float]]) -> dict[str, float]:
    """The curve columns (``FIELDS``): mean ratios to all human, and the collisions."""
    std = [m["speed_std"] / max(b["speed_std"], 1e-9) for m, b in zip(runs, base)]
    speed = [m["mean_speed"] / max(b["mean_speed"], 1e-9) for m, b in zip(runs, base)]
    return {"val_std_ratio": float(np.mean(std)), "val_speed_ratio": float(np.mean(speed)),
            "val_collisions": int(sum(m["collisions"] for m in runs))}  # fmt: skip


def rank(row: dict[str, float]) -> tuple[int, float, float]:
    """Sort key of a curve row, best first (module docstring)."""
    fails = int(row["val_collisions"] > 0 or row["val_speed_ratio"] < 1.0)
    return fails, float(row["val_collisions"]), float(row["val_std_ratio"])


def keep_best(out: Path, row: dict[str, float], rows: list[dict[str, float]],
              meta: dict[str, Any]) -> bool:  # fmt: skip
    """Copy ``out/model.zip`` (the leg of ``row``) to ``best.zip`` if ``row`` ranks above
    every earlier row in ``rows`` that has validation numbers; True if it did."""
    earlier = [r for r in rows if r is not row and _measured(r)]
    if earlier and min(map(rank, earlier)) <= rank(row):
        return False
    out = Path(out)
    with tempfile.TemporaryDirectory(dir=out) as tmp:  # the copy lands whole or not at all
        shutil.copyfile(out / "model.zip", Path(tmp) / BEST)
        Path(tmp, BEST).replace(out / BEST)
    text = json.dumps({**meta, "leg": row["leg"], **{k: row[k] for k in FIELDS}}, indent=1)
    atomic_write(out / BEST_META, lambda f: f.write(text.encode()))
    return True


def _measured(row: dict[str, float]) -> bool:
    return all(np.isfinite(float(row.get(k, np.nan))) for k in FIELDS)
