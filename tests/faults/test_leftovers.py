"""Issue 25 D14: a process killed with -9 leaves its scratch folder; the next one removes it."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

from mixed_traffic.paths import SCRATCH_PREFIX, scratch_dir


def test_scratch_folders_of_dead_processes_are_removed() -> None:
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)  # fmt: skip
    root = Path(tempfile.gettempdir())
    dead = root / f"{SCRATCH_PREFIX}{gone.stdout.strip()}_x1"
    dead.mkdir()
    (dead / "demand.rou.xml").write_text("<routes/>")
    mine = Path(scratch_dir())
    try:
        assert not dead.exists()
        assert mine.is_dir() and mine.name.startswith(f"{SCRATCH_PREFIX}{os.getpid()}_")
        live = Path(scratch_dir())  # a live process's folder (ours) is kept
        assert mine.is_dir() and live.is_dir()
        live.rmdir()
    finally:
        mine.rmdir()
