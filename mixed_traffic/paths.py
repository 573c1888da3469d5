"""Where the project's files live: the shipped scenarios and checkpoint, and the per-user cache."""

from __future__ import annotations

import os
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
