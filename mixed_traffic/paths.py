"""Where the project's files live: the shipped scenarios and checkpoint, and the per-user cache."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]


def _shipped_scenarios() -> Path:
    """The checkout's scenarios/ folder, or its copy inside an installed wheel."""
    checkout = REPO_ROOT / "scenarios"
    return checkout if checkout.is_dir() else Path(__file__).resolve().parent / "_scenarios"


SCENARIOS_DIR = Path(os.environ.get("MIXED_TRAFFIC_SCENARIOS", _shipped_scenarios()))
CHECKPOINT = REPO_ROOT / "agents" / "checkpoints" / "auto.pt"


def cache_dir(kind: str) -> Path:
    """Per-user cache folder for generated files (networks, HD maps, demand), created on demand."""
    base = Path(os.environ.get("MIXED_TRAFFIC_CACHE", Path.home() / ".cache" / "mixed_traffic"))
    path = base / kind
    path.mkdir(parents=True, exist_ok=True)
    return path


SCRATCH_PREFIX = "mixed_traffic_pid"


def scratch_dir() -> str:
    """A new scratch folder named after this process (``mixed_traffic_pid<pid>_*`` in the
    system temp folder); first removes those of processes that are gone (kill -9 leftovers)."""
    for old in Path(tempfile.gettempdir()).glob(f"{SCRATCH_PREFIX}*_*"):
        pid = old.name.removeprefix(SCRATCH_PREFIX).split("_")[0]
        if pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(old, ignore_errors=True)
    return tempfile.mkdtemp(prefix=f"{SCRATCH_PREFIX}{os.getpid()}_")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True
