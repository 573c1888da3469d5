"""Where the project's files live: the shipped scenarios and checkpoint, the committed
references, where commands write by default, and the per-user cache."""

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
RESULTS = Path("results")
"""Where commands write by default, relative to the working folder (ignored by git in a
checkout): no command changes a tracked file unless asked to (``--update-reference``)."""


def reference(relative: str) -> Path:
    """A committed reference file of the checkout (``reports/penetration.pdf``, ...), which
    only ``--update-reference`` rewrites; ``ValueError`` when there is no checkout (an
    installed wheel has no references to update)."""
    if not (REPO_ROOT / "reports").is_dir():
        raise ValueError(f"--update-reference rewrites the references of a checkout, and "
                         f"{REPO_ROOT} is none (run it in a clone of the repository)")  # fmt: skip
    return REPO_ROOT / relative


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
