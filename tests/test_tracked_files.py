"""No command changes a tracked file unless asked (issue 59): the benchmark table and the sweep
run as documented in a fresh copy of the checkout leave ``git status`` clean, and rewrite the
committed references only with ``--update-reference``."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from mixed_traffic.paths import REPO_ROOT

pytestmark = pytest.mark.slow

BENCHMARK = ["mixed_traffic.benchmark", "--tasks", "ring-v2", "--policies", "follower-stopper",
             "--seeds", "0", "--episode-length", "10", "--workers", "1"]  # fmt: skip
SWEEP = ["mixed_traffic.sweep", "--penetration", "--values", "1.0", "--policies", "acc-lc",
         "--at-density", "60",
         "--seeds", "0", "--episode-length", "60", "--warmup", "5", "--workers", "1"]  # fmt: skip


def _git(cwd: Path, *args: str) -> str:
    run = subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args], cwd=cwd,
                         capture_output=True, text=True, check=True)  # fmt: skip
    return run.stdout


@pytest.fixture
def clone(tmp_path: Path) -> Path:
    """A fresh repository holding the checkout's files as they are now (committed or not)."""
    if not (REPO_ROOT / ".git").exists():
        pytest.fail(f"{REPO_ROOT} is not a git checkout: this test needs one")
    listed = _git(REPO_ROOT, "ls-files", "-z", "--cached", "--others", "--exclude-standard")
    root = tmp_path / "clone"
    for name in filter(None, listed.split("\0")):
        if (REPO_ROOT / name).is_file():  # a file deleted but not yet staged is gone
            (root / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO_ROOT / name, root / name)
    _git(root, "init", "-q")
    _git(root, "add", "-A")
    _git(root, "commit", "-q", "-m", "snapshot")
    return root


def _run(root: Path, argv: list[str]) -> None:
    """``python -m argv`` in ``root``, importing that copy's code (numpy stages: no compile)."""
    env = {**os.environ, "PYTHONPATH": str(root), "MIXED_TRAFFIC_KERNELS": "numpy",
           "MPLBACKEND": "Agg"}  # fmt: skip
    done = subprocess.run([sys.executable, "-m", *argv], cwd=root, env=env, capture_output=True,
                          text=True, timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]


def _changed(root: Path) -> set[str]:
    """Paths git reports as changed or new (ignored files excluded)."""
    return {line[3:] for line in _git(root, "status", "--porcelain", "-uall").splitlines()}


@pytest.mark.parametrize(("argv", "references"), [
    (BENCHMARK, {"docs/benchmark.md", "reports/benchmark.pdf"}),
    (SWEEP, {"reports/penetration.pdf", "reports/penetration-dt_tf_vs_penetration.png"}),
])  # fmt: skip
def test_commands_write_results_and_rewrite_references_only_on_request(
    clone: Path, argv: list[str], references: set[str]
) -> None:
    _run(clone, argv)
    assert _changed(clone) == set()
    assert any((clone / "results").rglob("*.pdf")), "the report goes under results/"
    _run(clone, [*argv, "--update-reference"])  # the episodes are recorded: it resumes
    assert _changed(clone) == references
