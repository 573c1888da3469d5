"""``acc-lc-tuned``: the best ACC-LC of a documented grid, per scenario family.

The choice is made by ``python -m mixed_traffic.experiments.tune_acc_lc`` on the families'
train variants and stored in ``TUNED_FILE`` (a small JSON beside the checkpoints)::

    {"criterion": ..., "grid": {"T": [...], "speed_factor": [...], "a": [...]},
     "families": {"straight": {"params": {"T": 1.0, "speed_factor": 1.0, "a": 2.0}, ...}},
     "default": {"params": {...}, ...}, "seeds": [...], "git_revision": ..., ...}

A family the file does not name (a user's own network) gets its ``default``: the setting that is
best over all tuned families together (docs/agent.md, "The tuned baseline").
"""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path
from typing import Any

TUNED_FILE = Path(__file__).resolve().parents[1] / "checkpoints" / "acc_lc_tuned.json"
TUNED_FIELDS = ("T", "speed_factor", "a")
"""The AccLcConfig fields the grid tunes."""
TEACHERS = ("acc-lc", "acc-lc-tuned")
"""The rules a residual policy can correct (``LearnerConfig.teacher``)."""


def tuned_params(family: str | None, path: Path = TUNED_FILE) -> dict[str, Any]:
    """The tuned ACC-LC fields of scenario ``family`` (its own choice, else the default), and
    where they came from: ``{"T": .., "speed_factor": .., "a": .., "tuned_for": family or
    "default"}``. ``ValueError`` naming the file when it is missing or malformed."""
    data = _read(str(path))
    own = data["families"].get(family or "")
    chosen = own if own is not None else data["default"]
    return {**chosen["params"], "tuned_for": family if own is not None else "default"}


def cap_factor(family: str | None, path: Path = TUNED_FILE) -> float:
    """The speed cap of a learned policy's governors, as a share of the speed limit: the one
    ``acc-lc-tuned`` drives at in ``family`` (1.0, the limit, when nothing is tuned)."""
    if not path.is_file():
        return 1.0
    return float(tuned_params(family, path)["speed_factor"])


def teacher_rule(name: str, family: str | None, dt: float) -> Any:
    """The :class:`AccLcPolicy` that a residual policy corrects: the default ACC-LC, or the
    one tuned for ``family`` (``name`` one of ``TEACHERS``); ``dt`` its step [s]."""
    from agents.rules.acc_lc import AccLcPolicy
    from agents.rules.acc_lc_config import AccLcConfig

    if name not in TEACHERS:
        raise ValueError(f"teacher {name!r}: a residual policy corrects one of {TEACHERS}")
    tuned = {} if name == "acc-lc" else tuned_params(family)
    tuned.pop("tuned_for", None)
    return AccLcPolicy(AccLcConfig(dt=dt, **tuned))


@cache
def _read(path: str) -> dict[str, Any]:
    file = Path(path)
    if not file.is_file():
        raise ValueError(f"acc-lc-tuned: {file} is missing; make it with "
                         "python -m mixed_traffic.experiments.tune_acc_lc")  # fmt: skip
    try:
        data = json.loads(file.read_text())
        for entry in (*data["families"].values(), data["default"]):
            if set(entry["params"]) != set(TUNED_FIELDS):
                raise KeyError(f"params {sorted(entry['params'])}")
    except (json.JSONDecodeError, KeyError, TypeError, AttributeError) as e:
        raise ValueError(f"acc-lc-tuned: {file} is malformed ({type(e).__name__}: {e}); "
                         "make it again with python -m mixed_traffic.experiments.tune_acc_lc") from None  # fmt: skip
    return data
