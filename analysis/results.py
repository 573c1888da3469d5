"""Load episode records into a tidy table and summarise them with 95 % confidence intervals.

Reads result files only (``records.jsonl``, optionally ``records.parquet``); never imports SUMO
or torch. One row per episode; columns are the cell keys, the provenance fields and one column
per metric key of :data:`mixed_traffic.schema.METRICS`. Intervals: Student t for signed
quantities (:func:`mean_ci`), log-scale (delta-method) t for non-negative ones
(:func:`nonneg_mean_ci`, never below 0); the t critical values come from
:func:`analysis.stats.t_quantile_975` (scipy), also importable from here.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from analysis.stats import log_interval, t_quantile_975
from mixed_traffic.schema import CELL_KEYS, METRICS

JSONL_NAME = "records.jsonl"
PARQUET_NAME = "records.parquet"

#: Provenance columns of the tidy table (besides the cell keys and the metrics).
INFO_COLUMNS = (
    "status",
    "error",
    "sumo_version",
    "git_revision",
    "code",
    "created",
    "wall_time",
    "warmup",
    "ring_length",
    "episode_length",
    "step_length",
    "config",
)
"""``config`` is the record's full EnvConfig as a JSON string (so the table stays columnar);
``ring_length`` the circumference of a ring episode [m] (drawn per episode from a range)."""

METRIC_KEYS = tuple(METRICS)
COLUMNS = (*CELL_KEYS, *INFO_COLUMNS, *METRIC_KEYS)
#: The condition of a cell without its seed: episodes of one group differ only by seed.
CONDITION_KEYS = tuple(k for k in CELL_KEYS if k not in ("seed", "copy"))
"""What an episode was run under: its cell without the replicate (seed, copy)."""


class ResultsError(ValueError):
    """A results directory or file that cannot be read as episode records."""


def _finite(values: Iterable[float]) -> np.ndarray:
    """The finite values (None, NaN and inf dropped) as a float array of shape (n,)."""
    arr = np.asarray([v for v in values if v is not None], dtype=float)
    return arr[np.isfinite(arr)]


def mean_ci(values: Iterable[float]) -> tuple[float, float, int]:
    """Mean, 95 % Student t-interval half-width and count of the finite ``values``.

    The interval of a signed quantity. The half-width is NaN when fewer than two finite values
    exist (no interval from one seed).
    """
    arr = _finite(values)
    n = int(arr.size)
    if n == 0:
        return math.nan, math.nan, 0
    mean = float(arr.mean())
    if n < 2:
        return mean, math.nan, n
    half = t_quantile_975(n - 1) * float(arr.std(ddof=1)) / math.sqrt(n)
    return mean, half, n


def nonneg_mean_ci(values: Iterable[float]) -> tuple[float, float, float, int]:
    """Mean, 95 % interval ``(lo, hi)`` and count of the finite ``values`` of a non-negative
    quantity (same unit as the values).

    The interval is the log-scale (delta-method) t-interval of :func:`analysis.stats.log_interval`:
    it stays >= 0 where the t-interval of :func:`mean_ci` may cross 0 (few seeds, large spread).
    Should a value be negative (the quantity is not non-negative after all) the t-interval is
    returned. ``lo`` and ``hi`` are NaN with fewer than two finite values.
    """
    arr = _finite(values)
    mean, half, n = mean_ci(arr)
    if n and arr.min() < 0:
        return mean, mean - half, mean + half, n
    lo, hi = log_interval(mean, half)
    return mean, lo, hi, n


def metric_ci(key: str, values: Iterable[float]) -> tuple[float, float, float, int]:
    """Mean, 95 % interval ``(lo, hi)`` and count of the values of metric ``key``: the
    log-scale interval of :func:`nonneg_mean_ci` for a non-negative metric (schema
    ``Metric.nonnegative``), else the Student t-interval of :func:`mean_ci`."""
    if METRICS[key].nonnegative:
        return nonneg_mean_ci(values)
    mean, half, n = mean_ci(values)
    return mean, mean - half, mean + half, n


def _flatten(record: dict[str, Any]) -> dict[str, Any]:
    """One tidy row from one schema record (missing fields become None/NaN)."""
    cell = record.get("cell") or {}
    config = record.get("config") or {}
    metrics = record.get("metrics") or {}
    row: dict[str, Any] = {k: cell.get(k) for k in CELL_KEYS}
    if row["seed"] is None:
        row["seed"] = record.get("seed")
    row["copy"] = row["copy"] or 0  # records before batched worlds: one copy
    # a record without its status or code hash cannot be trusted as an ok episode
    row["status"] = record.get("status") if "code" in record else None
    row["status"] = row["status"] or "invalid"
    row["error"] = record.get("error")
    row["sumo_version"] = record.get("sumo_version")
    row["git_revision"] = record.get("git_revision")
    row["code"] = record.get("code")
    row["created"] = record.get("created")
    row["wall_time"] = record.get("wall_time")
    row["warmup"] = record.get("warmup")
    row["ring_length"] = record.get("ring_length")  # a ring's circumference [m], else None
    row["episode_length"] = config.get("episode_length")
    row["step_length"] = config.get("step_length")
    row["config"] = json.dumps(config, sort_keys=True) if config else None
    for key in METRIC_KEYS:
        row[key] = metrics.get(key)
    return row


def read_jsonl(path: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """Records of one JSON-lines file.

    A malformed *last* line (an interrupted append) is skipped with a warning; a malformed line
    elsewhere is also skipped with a warning naming its line number. Blank lines are ignored.
    """
    path = Path(path)
    lines = path.read_text(encoding="utf-8").splitlines()
    last = max((i for i, line in enumerate(lines) if line.strip()), default=-1)
    out: list[dict[str, Any]] = []
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError as exc:
            what = "truncated last line" if i == last else f"malformed line {i + 1}"
            warnings.warn(f"{path}: skipping {what} ({exc.msg})", stacklevel=2)
            continue
        if not isinstance(rec, dict):
            warnings.warn(f"{path}: skipping line {i + 1}: not a JSON object", stacklevel=2)
            continue
        out.append(rec)
    return out


def records_to_frame(records: Sequence[dict[str, Any]]) -> pd.DataFrame:
    """Tidy table (one row per record) in the column order of :data:`COLUMNS`."""
    return _normalise(pd.DataFrame([_flatten(r) for r in records], columns=list(COLUMNS)))


def _normalise(df: pd.DataFrame) -> pd.DataFrame:
    """Add missing columns and coerce dtypes (numeric cell keys and metrics)."""
    for col in COLUMNS:
        if col not in df.columns:
            df[col] = None
    extra = [c for c in df.columns if c not in COLUMNS]
    df = df[list(COLUMNS) + extra].copy()
    for col in (
        "density",
        "penetration",
        "wall_time",
        "warmup",
        "ring_length",
        "episode_length",
        "step_length",
        *METRIC_KEYS,
    ):
        df[col] = pd.to_numeric(df[col], errors="coerce").astype(float)
    df["seed"] = pd.to_numeric(df["seed"], errors="coerce").astype("Int64")
    df["copy"] = pd.to_numeric(df["copy"], errors="coerce").fillna(0).astype("Int64")
    # records before the detection-range axis ran at the nominal ranges
    df["detection_range"] = pd.to_numeric(df["detection_range"], errors="coerce").fillna(1.0)
    df["status"] = df["status"].fillna("invalid").astype(str)
    for col in ("policy", "scenario", "weather"):
        df[col] = df[col].astype(object)
    return df.reset_index(drop=True)


def _dedupe(df: pd.DataFrame) -> pd.DataFrame:
    """Drop repeated records and failed attempts superseded by a successful one.

    The same record read from both jsonl and parquet appears once. A cell that failed and was
    later re-run successfully keeps only the successful row; two successful rows for one cell keep
    the latest (by ``created``) with a warning.
    """
    if df.empty:
        return df
    key = list(CELL_KEYS)
    df = df.drop_duplicates(subset=[*key, "created", "status"], keep="last")
    df = df.sort_values("created", kind="stable", na_position="first")
    ok_cells = set(map(tuple, df.loc[df["status"] == "ok", key].astype(str).to_numpy()))
    cell_str = [tuple(r) for r in df[key].astype(str).to_numpy()]
    superseded = np.array([(c in ok_cells) for c in cell_str]) & (df["status"] != "ok").to_numpy()
    df = df.loc[~superseded]
    ok = df["status"] == "ok"
    dup = ok & df.duplicated(subset=key, keep="last")
    if dup.any():
        warnings.warn(
            f"{int(dup.sum())} duplicate successful record(s) for the same cell; keeping the latest",
            stacklevel=3,
        )
        df = df.loc[~dup]
    return df.sort_index().reset_index(drop=True)


def load_results(results_dir: str | os.PathLike[str]) -> pd.DataFrame:
    """Tidy table of all episode records under ``results_dir``.

    ``results_dir`` is a folder holding ``records.jsonl`` and/or ``records.parquet`` (written by
    :func:`to_parquet`), or one such file. Failed episodes are kept (``status == "failed"`` with
    their ``error``). A truncated last line is skipped with a warning.

    Raises:
        FileNotFoundError: the folder or file does not exist, or holds no records file.
    """
    path = Path(results_dir)
    if not path.exists():
        raise FileNotFoundError(f"results path {str(path)!r} does not exist")
    if path.is_file():
        files = [path]
    else:
        files = [p for p in (path / JSONL_NAME, path / PARQUET_NAME) if p.is_file()]
        if not files:
            raise FileNotFoundError(
                f"no {JSONL_NAME} or {PARQUET_NAME} in {str(path)!r}: is this a results folder?"
            )
    frames = []
    for f in files:
        if f.suffix == ".parquet":
            frames.append(_normalise(pd.read_parquet(f)))
        elif f.suffix in (".jsonl", ".json"):
            frames.append(records_to_frame(read_jsonl(f)))
        else:
            raise ResultsError(f"{str(f)!r}: expected a .jsonl or .parquet records file")
    frames = [f for f in frames if not f.empty]
    if not frames:
        return records_to_frame([])
    return _dedupe(pd.concat(frames, ignore_index=True))


def to_parquet(df: pd.DataFrame, path: str | os.PathLike[str]) -> Path:
    """Write the tidy table as parquet atomically (temporary file + rename); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        _normalise(df.copy()).to_parquet(tmp, index=False)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def summarise(
    df: pd.DataFrame, by: Sequence[str], metrics: Sequence[str] | None = None
) -> pd.DataFrame:
    """Mean and 95 % confidence interval across seeds of each metric, per group.

    Only successful episodes enter the statistics. Returns one row per group with the ``by``
    columns, ``n_ok``, ``n_failed`` and for each metric ``{m}_mean``, ``{m}_lo``, ``{m}_hi``
    (the interval of :func:`metric_ci`: log-scale for a non-negative metric, so never below 0,
    Student t for a signed one; NaN with fewer than two values) and ``{m}_n``.
    """
    by = list(by)
    metrics = list(metrics) if metrics is not None else list(METRIC_KEYS)
    for col in by:
        if col not in df.columns:
            raise KeyError(f"summarise: unknown column {col!r}")
    rows: list[dict[str, Any]] = []
    groups = df.groupby(by, dropna=False, sort=True) if by else [((), df)]
    for key, group in groups:
        key = key if isinstance(key, tuple) else (key,)
        row: dict[str, Any] = dict(zip(by, key))
        is_ok = group["status"] == "ok"
        row["n_ok"] = int(is_ok.sum())
        row["n_failed"] = int((~is_ok).sum())
        group = group[is_ok]
        for m in metrics:
            values = group[m].tolist() if m in group else []
            row[f"{m}_mean"], row[f"{m}_lo"], row[f"{m}_hi"], row[f"{m}_n"] = metric_ci(m, values)
        rows.append(row)
    return pd.DataFrame(rows)


def ok_rows(df: pd.DataFrame) -> pd.DataFrame:
    """Successful episodes only."""
    return df[df["status"] == "ok"]


def filter_condition(df: pd.DataFrame, condition: dict[str, Any]) -> pd.DataFrame:
    """Rows whose columns equal every value in ``condition`` (floats compared with tolerance)."""
    mask = pd.Series(True, index=df.index)
    for col, value in condition.items():
        if value is None or (isinstance(value, float) and math.isnan(value)):
            mask &= df[col].isna()
        elif isinstance(value, float):
            mask &= np.isclose(df[col].astype(float), value)
        else:
            mask &= df[col] == value
    return df[mask]


def sweep_condition(df: pd.DataFrame, vary: str) -> dict[str, Any] | None:
    """The fixed condition (other than policy and ``vary``) under which ``vary`` takes most values.

    Returns ``None`` when ``vary`` never takes two distinct values under one condition (the data
    has no sweep along it). Ties prefer more episodes, then 120 veh/km and normal weather.
    """
    ok = ok_rows(df)
    fixed = [k for k in CONDITION_KEYS if k not in ("policy", vary)]
    if ok.empty or ok[vary].nunique(dropna=True) < 2:
        return None
    best: tuple[Any, ...] | None = None
    best_cond: dict[str, Any] | None = None
    for key, group in ok.groupby(fixed, dropna=False):
        key = key if isinstance(key, tuple) else (key,)
        cond = dict(zip(fixed, key))
        n_values = group[vary].nunique(dropna=True)
        if n_values < 2:
            continue
        score = (n_values, len(group), *_preference(cond))
        if best is None or score > best:
            best, best_cond = score, cond
    return best_cond


def _preference(cond: dict[str, Any]) -> tuple[float, float, float]:
    """Tie-breakers: close to 120 veh/km, normal weather, low positive penetration."""
    density = cond.get("density")
    pen = cond.get("penetration")
    return (
        -abs(float(density) - 120.0) if density is not None and density == density else -1e9,
        1.0 if cond.get("weather", "normal") == "normal" else 0.0,
        -float(pen) if pen is not None and pen == pen else 0.0,
    )


def reference_condition(df: pd.DataFrame) -> dict[str, Any] | None:
    """One condition (scenario, density, penetration, weather) for the per-policy tables.

    Among conditions with AVs (penetration > 0), the one run by the most policies, then with the
    most successful episodes; ties prefer 120 veh/km, normal weather and the lowest penetration
    (the paper's tables describe a single AV in conventional traffic). ``None`` without data.
    """
    ok = ok_rows(df)
    ok = ok[ok["penetration"].fillna(1.0) > 0]
    if ok.empty:
        return None
    fixed = [k for k in CONDITION_KEYS if k != "policy"]
    best: tuple[Any, ...] | None = None
    best_cond: dict[str, Any] | None = None
    for key, group in ok.groupby(fixed, dropna=False):
        key = key if isinstance(key, tuple) else (key,)
        cond = dict(zip(fixed, key))
        score = (group["policy"].nunique(), len(group), *_preference(cond))
        if best is None or score > best:
            best, best_cond = score, cond
    return best_cond
