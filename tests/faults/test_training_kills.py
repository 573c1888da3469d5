"""Issue 25 D1: kill -9 a training run at random moments; each resume continues from a whole
commit (checkpoint, replay and counters agree) and the final run loses and repeats nothing."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from agents.checkpoint import load_checkpoint
from agents.training.commit import committed

ROOT = Path(__file__).resolve().parents[2]
BUDGET = 4000
ARGS = ["--workers", "1", "--scenarios", "straight-3lane", "--densities", "120",
        "--penetrations", "0.5", "--episode-length", "2", "--env-steps", str(BUDGET),
        "--demo-steps", "400", "--demo-policy", "acc-lc", "--learning-starts", "400",
        "--update-ratio", "0.02", "--log-every", "250", "--no-progress",
        "--replay-capacity", "20000", "--checkpoint-every", "0.2"]  # fmt: skip


def _train(out: Path, resume: bool) -> subprocess.Popen:
    argv = [sys.executable, "-m", "mixed_traffic.train", *ARGS, "--out", str(out)]
    return subprocess.Popen(argv + ["--resume"] * resume, cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip


def _check_commit(out: Path) -> int:
    """The env steps of ``out``'s last commit, after checking that its parts agree."""
    folder = committed(out)
    if folder is None:
        return 0
    counters = json.loads((folder / "state.json").read_text())["counters"]
    learner, meta = load_checkpoint(folder / "checkpoint.pt")
    replay = torch.load(folder / "replay.pt", weights_only=True)
    assert learner.steps == meta["updates"] == counters["updates"]
    assert meta["env_steps"] == counters["env_steps"] == replay["size"]
    return counters["env_steps"]


def _curve_steps(out: Path) -> list[int]:
    with (out / "curves.csv").open(newline="") as f:
        return [int(r["env_steps"]) for r in csv.DictReader(f)]


def _await_commit(out: Path, beyond: int, proc: subprocess.Popen, patience: float = 300) -> None:
    """Wait until ``out`` holds a commit of more than ``beyond`` env steps (or ``proc`` ends,
    or ``patience`` s pass): on a slow machine a fixed delay never reached the first one."""
    deadline = time.time() + patience
    while time.time() < deadline and proc.poll() is None:
        try:
            folder = committed(out)
            if folder is not None:
                state = json.loads((folder / "state.json").read_text())
                if state["counters"]["env_steps"] > beyond:
                    return
        except (OSError, ValueError):  # a commit replaced while read
            pass
        time.sleep(0.2)


def test_four_kills_at_random_moments_each_resume_cleanly(tmp_path: Path) -> None:
    """Legs 0 and 1 die 2-9 s after they start (often before any commit: the resume then
    starts afresh); legs 2 and 3 at a random moment within 3 s after their next commit."""
    rng = np.random.default_rng(25)
    out, committed_steps = tmp_path / "run", []
    for leg in range(4):
        proc = _train(out, resume=leg > 0)
        if leg >= 2:
            _await_commit(out, max(committed_steps, default=0), proc)
        time.sleep(rng.uniform(2.0, 9.0) if leg < 2 else rng.uniform(0.0, 3.0))
        assert proc.poll() is None, f"leg {leg} ended before its kill: {proc.stderr.read()[-800:]}"
        proc.kill()
        proc.wait()
        committed_steps.append(_check_commit(out))
        assert committed_steps[-1] >= max(committed_steps[:-1], default=0)  # nothing lost
    assert committed_steps[-1] > 0, "no kill came after a commit: the legs are too short"
    last = _train(out, resume=True)
    _, err = last.communicate(timeout=600)
    assert last.returncode == 0, err[-2000:]
    assert "resumed" in err
    info = json.loads((out / "auto.json").read_text())
    assert info["env_steps"] == _check_commit(out) >= BUDGET
    # a leg killed before it committed left no trace, not even its command
    assert 2 <= len(info["commands"]) <= 5 and info["commands"][-1].endswith("--resume")
    steps = _curve_steps(out)
    assert steps == sorted(set(steps)) and steps[-1] == info["env_steps"]
    assert not list(out.rglob("*.tmp"))
