"""The methods of the paper's comparison studies (§V-A) and how each is trained: one table of
``python -m mixed_traffic.train`` flags on a shared budget, so every method runs the same
pipeline, scenarios, seed and number of transitions (docs/studies.md).

Training a method runs ``train`` in a subprocess into ``RUNS/<name>`` (``--resume`` continues a
killed or shorter run: the budget counts every leg's transitions), then copies its policy,
lineage and curves into ``agents/checkpoints/study/<name>.{pt,json,csv}``.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from mixed_traffic.provenance import atomic_write
from mixed_traffic.schema import ABLATIONS, BASELINES, STUDY_POLICIES

RUNS = Path("runs/study")
"""Default folder of the study's training runs (one subfolder per method)."""

METHOD_FLAGS: dict[str, tuple[str, ...]] = {
    "rbp-dqn": (),
    "bp-dqn": ("--bp-dqn",),
    "p-ddpg": ("--baseline", "p-ddpg"),
    "q-pamdp": ("--baseline", "q-pamdp"),
    "head": ("--baseline", "head"),
    "transfuser": ("--baseline", "transfuser", "--no-residual"),
    "drl-mf": ("--baseline", "drl-mf", "--no-residual"),
    "auto-noimp": ("--ablation", "noimp"),
    "auto-novec": ("--ablation", "novec"),
    "auto-nostar": ("--ablation", "nostar"),
    "auto-nolane": ("--ablation", "nolane"),
    "auto-nohis": ("--ablation", "nohis"),
    "auto-nomul": ("--ablation", "nomul", "--workers", "1"),
}
"""What sets each study policy apart from AUTO's pipeline (rbp-dqn)."""
assert set(METHOD_FLAGS) == set(STUDY_POLICIES)

STUDIES: dict[str, tuple[str, ...]] = {
    "baselines": ("acc-lc", "auto", "rbp-dqn", *BASELINES),
    "rl-models": ("rbp-dqn", "bp-dqn", "p-ddpg", "q-pamdp"),
    "ablations": ("rbp-dqn", *ABLATIONS),
}
"""Policies of each table study (``--robustness`` and ``--detection-range`` are sweeps)."""


@dataclass(frozen=True)
class Budget:
    """The training budget and settings every method shares."""

    env_steps: int = 150_000
    """Transitions (AV actions) per method, demonstrations included [-]."""
    seed: int = 23
    """Training seed of every method."""
    workers: int = 2
    """Rollout workers (NoMUL: 1)."""

    def flags(self) -> tuple[str, ...]:
        """``train`` flags shared by every method: AUTO's leg-1b settings (agents/checkpoints/
        legs/leg1b-mpdqn.json) but this budget and no ``--learner-compile`` (its one-off
        compile would cost the CNN encoders more than the others)."""
        return (
            "--workers", str(self.workers), "--env-steps", str(self.env_steps),
            "--seed", str(self.seed), "--lr", "3e-4", "--noise-std", "0.5",
            "--ladder-spread", "1", "--penetrations", "0.05", "0.2", "0.5", "1.0",
            "--episode-length", "60", "--learning-starts", "10000", "--update-ratio", "0.0625",
            "--replay-capacity", "400000", "--checkpoint-every", "300", "--log-every", "10000",
            "--no-progress",
        )  # fmt: skip


def train_command(name: str, budget: Budget, runs: Path = RUNS) -> list[str]:
    """The ``python -m mixed_traffic.train`` argv that trains study policy ``name``."""
    flags = list(budget.flags())
    extra = list(METHOD_FLAGS[name])
    if "--workers" in extra:  # the method's own worker count wins
        i = flags.index("--workers")
        del flags[i : i + 2]
    return [sys.executable, "-m", "mixed_traffic.train", *flags, *extra,
            "--out", str(runs / name)]  # fmt: skip


def trained_steps(name: str, runs: Path = RUNS) -> int:
    """Transitions the run of ``name`` in ``runs`` has finished (0 without a final policy)."""
    info = runs / name / "auto.json"
    if not (runs / name / "auto.pt").is_file() or not info.is_file():
        return 0
    return int(json.loads(info.read_text()).get("env_steps", 0))


def train_method(name: str, budget: Budget, dest: Path, runs: Path = RUNS,
                 log: Path | None = None) -> Path:  # fmt: skip
    """Train (or resume) ``name`` to ``budget`` and install it as ``dest/<name>.pt`` with its
    lineage (.json) and curves (.csv); returns the checkpoint. RuntimeError if train fails."""
    argv = train_command(name, budget, runs)
    if (runs / name / "COMMIT").is_file():
        argv.append("--resume")
    if trained_steps(name, runs) < budget.env_steps:
        with open(log or "/dev/null", "ab") as out:
            rc = subprocess.call(argv, stdout=out, stderr=subprocess.STDOUT)
        if rc != 0:
            raise RuntimeError(f"training {name} failed (exit {rc}); see {log or runs / name}")
    return install(name, dest, runs, argv)


def install(name: str, dest: Path, runs: Path, argv: list[str]) -> Path:
    """Copy the run's policy, lineage and curves into ``dest`` (each atomically)."""
    src = runs / name
    dest.mkdir(parents=True, exist_ok=True)
    info = json.loads((src / "auto.json").read_text())
    info["study_command"] = " ".join(["python", *argv[1:]])
    for suffix, source in ((".pt", src / "auto.pt"), (".csv", src / "curves.csv")):
        atomic_write(dest / f"{name}{suffix}", lambda f, s=source: f.write(s.read_bytes()))
    atomic_write(dest / f"{name}.json", lambda f: f.write(json.dumps(info, indent=1).encode()))
    return dest / f"{name}.pt"


def clear_run(name: str, runs: Path = RUNS) -> None:
    """Remove the run folder of ``name`` (a fresh start)."""
    shutil.rmtree(runs / name, ignore_errors=True)
