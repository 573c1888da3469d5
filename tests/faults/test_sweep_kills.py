"""Issue 25 fault suite: kill -9 of a sweep's worker process (or Ray worker) mid-cell. The sweep
records that cell as failed, finishes the others, exits 1, and a re-run retries only that cell."""

from __future__ import annotations

import importlib.util
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mixed_traffic.provenance import read_records


def _children(pid: int) -> list[int]:
    """Live child processes of ``pid`` (from /proc)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:  # it ended meanwhile
        return b""


def _kill_one_cell_and_rerun(out: Path, extra: list[str], workers_of, patience: float,
                             pause: float, error: str) -> None:  # fmt: skip
    """Run a two-cell sweep (``extra`` arguments), kill -9 the first process ``workers_of(proc)``
    finds ``pause`` s after it appears (within ``patience`` s), then check: exit 1 with a
    summary, one failed record naming ``error``, and a re-run that retries only that cell."""
    args = [sys.executable, "-m", "mixed_traffic.sweep", "--penetration", "--values", "0.5",
            "--policies", "random", "--seeds", "0", "1", "--warmup", "2", "--workers", "1",
            "--no-report", "--no-traffic", "--no-reference", "--out", str(out), *extra]  # fmt: skip
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline, workers = time.time() + patience, []
    while time.time() < deadline and not workers and proc.poll() is None:
        workers = workers_of(proc)
        time.sleep(0.1)
    assert workers, "no worker process ran a cell"
    time.sleep(pause)  # mid-cell
    os.kill(workers[0], signal.SIGKILL)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 1 and "1 of 2 cells failed" in err, err[-1000:]
    records = read_records(out / "records.jsonl")
    assert sorted(r["status"] for r in records) == ["failed", "ok"]
    (failed,) = [r for r in records if r["status"] == "failed"]
    assert error in failed["error"]
    again = subprocess.run(args, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr[-1000:]
    records = read_records(out / "records.jsonl")
    assert len(records) == 3 and sum(r["status"] == "ok" for r in records) == 2


def _cell_workers(proc: subprocess.Popen) -> list[int]:
    """The sweep's cell processes: children of its fork server (or spawned children; both
    start methods also start a resource tracker)."""
    out = []
    for c in _children(proc.pid):
        line = _cmdline(c)
        if b"forkserver" in line:
            out += _children(c)
        elif b"spawn_main" in line and b"resource_tracker" not in line:
            out.append(c)
    return out


def _ray_task_pids(name: bytes) -> list[int]:
    """Processes whose title (Ray sets it to ``ray::<task>`` while a task runs) names ``name``."""
    return [int(p.name) for p in Path("/proc").glob("[0-9]*") if name in _cmdline(int(p.name))]


def test_a_killed_sweep_worker_is_a_failed_cell_that_the_next_run_retries(tmp_path: Path) -> None:
    # 90 s episodes: a cell lasts several seconds (a 30 s cell ended before the kill)
    _kill_one_cell_and_rerun(tmp_path / "res", ["--episode-length", "90"], _cell_workers,
                             patience=60, pause=1.0,
                             error="worker process died with exit code -9")  # fmt: skip


@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="ray is not installed")
def test_a_killed_ray_worker_is_a_failed_cell_that_the_next_run_retries(tmp_path: Path) -> None:
    """The same with ``--backend ray``: kill -9 of the Ray worker running a cell (a cell takes
    several seconds)."""
    _kill_one_cell_and_rerun(tmp_path / "res", ["--episode-length", "15", "--backend", "ray"],
                             lambda _: _ray_task_pids(b"ray::episode_records"), patience=120,
                             pause=0.5, error="Ray task failed")  # fmt: skip
