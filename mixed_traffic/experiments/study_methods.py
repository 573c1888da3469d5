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
from dataclasses import dataclass, replace
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
    "baselines": ("acc-lc-tuned", "acc-lc", "auto", "rbp-dqn", *BASELINES),
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


def copy_installed(name: str, source: Path, dest: Path) -> None:
    """Copy the installed ``name`` (checkpoint, lineage, curves) from ``source`` into ``dest``
    when ``dest`` has none, so that training there continues from those weights as it would
    in ``source``."""
    if (dest / f"{name}.pt").exists() or not (source / f"{name}.pt").is_file():
        return
    dest.mkdir(parents=True, exist_ok=True)
    for suffix in (".json", ".csv", ".pt"):  # the checkpoint last: it marks the copy complete
        src = source / f"{name}{suffix}"
        if src.is_file():
            atomic_write(dest / src.name, lambda f, src=src: f.write(src.read_bytes()))


def installed_steps(name: str, dest: Path) -> int:
    """Transitions the installed policy ``dest/<name>.pt`` was trained on (0 if none)."""
    info = dest / f"{name}.json"
    if not (dest / f"{name}.pt").is_file() or not info.is_file():
        return 0
    return int(json.loads(info.read_text()).get("env_steps", 0))


def train_method(name: str, budget: Budget, dest: Path, runs: Path = RUNS,
                 log: Path | None = None) -> Path:  # fmt: skip
    """Train ``name`` up to ``budget`` transitions and install it as ``dest/<name>.pt`` with
    its lineage (.json) and curves (.csv); returns the checkpoint. A run folder with a commit
    is resumed; without one, an installed policy trained on less is continued from its
    weights (``--init``: fresh replay and optimiser counters). RuntimeError if train fails."""
    done = installed_steps(name, dest)
    if done >= budget.env_steps:
        return dest / f"{name}.pt"
    run = runs / name
    base_file = run / "base.json"  # transitions before this run's --init leg
    if not (run / "COMMIT").is_file():
        shutil.rmtree(run, ignore_errors=True)
        run.mkdir(parents=True)
        atomic_write(base_file, lambda f: f.write(json.dumps({"init_steps": done}).encode()))
    base = int(json.loads(base_file.read_text())["init_steps"]) if base_file.is_file() else 0
    argv = train_command(name, replace(budget, env_steps=budget.env_steps - base), runs)
    if (run / "COMMIT").is_file():
        argv.append("--resume")
    elif base:
        argv += ["--init", str(dest / f"{name}.pt")]
    with open(log or "/dev/null", "ab") as out:
        rc = subprocess.call(argv, stdout=out, stderr=subprocess.STDOUT)
    if rc != 0:
        raise RuntimeError(f"training {name} failed (exit {rc}); see {log or run}")
    return install(name, dest, run, argv, base)


def install(name: str, dest: Path, run: Path, argv: list[str], base: int = 0) -> Path:
    """Copy the run's policy, lineage and curves into ``dest`` (each atomically); the
    lineage counts ``base`` transitions of earlier legs."""
    dest.mkdir(parents=True, exist_ok=True)
    info = json.loads((run / "auto.json").read_text())
    if base:
        earlier = json.loads((dest / f"{name}.json").read_text())
        info["earlier_legs"] = [*earlier.pop("earlier_legs", []), earlier]
        info["env_steps"] = int(info["env_steps"]) + base
    info["study_command"] = " ".join(["python", *argv[1:]])
    curves = (run / "curves.csv").read_text()
    if base:  # earlier legs' rows first, this leg's transitions (column 1) counted after them
        rows = [r.split(",", 1) for r in curves.splitlines()[1:]]
        shifted = [f"{int(n) + base},{r}" for n, r in rows]
        curves = "\n".join([(dest / f"{name}.csv").read_text().rstrip("\n"), *shifted]) + "\n"
    atomic_write(dest / f"{name}.pt", lambda f: f.write((run / "auto.pt").read_bytes()))
    atomic_write(dest / f"{name}.csv", lambda f: f.write(curves.encode()))
    atomic_write(dest / f"{name}.json", lambda f: f.write(json.dumps(info, indent=1).encode()))
    return dest / f"{name}.pt"
