"""``python -m mixed_traffic.study``: the paper's comparison studies (§V), one command each.

- ``--baselines``: ACC-LC, AUTO and AUTO's pipeline at the study budget (rbp-dqn) beside
  TransFuser, DRL-MF, HEAD, BP-DQN, P-DDPG and Q-PAMDP;
- ``--rl-models``: RBP-DQN against BP-DQN, P-DDPG and Q-PAMDP, with learning curves;
- ``--ablations``: rbp-dqn against NoIMP, NoVEC, NoSTAR, NoLANE, NoHIS and NoMUL;
- ``--robustness``: PT-RT under the four weathers, rbp-dqn against NoHIS (and AUTO);
- ``--detection-range``: the LiDAR and camera ranges as a share of nominal (AUTO, rbp-dqn,
  ACC-LC).

Each trained method without a checkpoint in agents/checkpoints/study/ at the budget is trained
first (:mod:`mixed_traffic.experiments.study_methods`: one budget, seed and scenario set for
all) into ``results/study-checkpoints`` (the shipped folder only with ``--update-reference``),
then the evaluation cells run through the sweep machinery (parallel, resumable, Ray with
``--backend ray``) into ``results/study`` (``results/study-<study>`` for the sweeps) and the
PDF goes beside them (over ``reports/<study>.pdf`` with ``--update-reference``).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from agents.policies import STUDY_CHECKPOINTS
from mixed_traffic.experiments.cli import add_config_args, config_dest, config_from_args
from mixed_traffic.experiments.study_methods import (
    METHOD_FLAGS,
    RUNS,
    STUDIES,
    Budget,
    installed_steps,
)
from mixed_traffic.paths import RESULTS, reference
from mixed_traffic.provenance import FolderBusyError, check_writable

TRAINED_HERE = RESULTS / "study-checkpoints"
"""Where methods trained by a study go unless it updates the shipped ones."""

KINDS = ("baselines", "rl-models", "ablations", "robustness", "detection-range")
SWEEP_STUDIES = {
    "robustness": ("weather", ("rbp-dqn", "auto-nohis", "auto")),
    "detection-range": ("detection_range", ("auto", "rbp-dqn", "acc-lc-tuned", "acc-lc")),
}
"""Studies that are sweeps: (axis, policies)."""


@dataclass(frozen=True)
class StudyConfig:
    """One study; the CLI is built from it."""

    study: str = "baselines"
    """baselines | rl-models | ablations | robustness | detection-range."""
    policies: tuple[str, ...] = ()
    """Policies to run (default: the study's own, docs/studies.md)."""
    reference: str = "rbp-dqn"
    """Table studies: the policy each other one is tested against (default: AUTO's pipeline
    at the study's budget)."""
    scenario: str = "straight-eval"
    """Held-out evaluation scenario (name or .net.xml/.sumocfg path)."""
    at_density: float | None = None
    """Traffic density [veh/km, all lanes] (default: the scenario's)."""
    at_penetration: float = 0.2
    """AV penetration [0-1]."""
    seeds: tuple[int, ...] = (0, 1, 2, 3, 4)
    """Evaluation seeds (at least 5 for the 95 % CIs the report quotes)."""
    episode_length: float = 150.0
    """Simulated time per evaluation episode [s]."""
    warmup: float = 30.0
    """Time before metrics are averaged [s]."""
    train: bool = True
    """Train the study's methods that have no checkpoint yet (False: a missing one is an error)."""
    env_steps: int = Budget.env_steps
    """Training budget of every method [transitions]; a method trained on less is resumed to it."""
    train_seed: int = Budget.seed
    """Training seed of every method."""
    runs: Path = RUNS
    """Folder of the training runs (resumable)."""
    checkpoints: Path | None = None
    """Folder of the trained methods' checkpoints, lineage and curves (<policy>.pt/.json/.csv)
    (default: the shipped agents/checkpoints/study while it has every method at the budget;
    else results/study-checkpoints, where a method missing there starts from the shipped
    weights)."""
    workers: int = 2
    """Parallel evaluation workers (training uses 2 rollout workers; NoMUL 1)."""
    backend: str = "process"
    """Evaluation cells as local processes or Ray tasks (ray)."""
    address: str = ""
    """With backend ray: cluster address for ray.init."""
    out: Path | None = None
    """Results folder (default: results/study for the table studies, which share their cells;
    results/study-<study> for the sweeps)."""
    pdf: Path | None = None
    """Report path (default: <results folder>/<study>.pdf)."""
    update_reference: bool = False
    """Write the report over the committed reference, reports/<study>.pdf, and train what is
    missing into the shipped agents/checkpoints/study."""

    def __post_init__(self) -> None:
        if self.study not in KINDS:
            raise ValueError(f"--study={self.study!r}: choose from {KINDS}")
        if len(self.seeds) < 2 or len(set(self.seeds)) != len(self.seeds) or min(self.seeds) < 0:
            raise ValueError(f"--seeds={list(self.seeds)}: give at least 2 distinct seeds >= 0")
        if not self.env_steps > 0:
            raise ValueError(f"--env-steps={self.env_steps}: the training budget must be > 0")
        if self.update_reference and self.pdf is not None:
            raise ValueError("--update-reference writes the reference report: drop --pdf")
        if self.checkpoints is None:
            object.__setattr__(self, "checkpoints", self._default_checkpoints())
        self.sweep()  # the evaluation's own checks (scenario, policies, density, episode, ...)
        if self.study not in SWEEP_STUDIES and self.reference not in self.run_policies:
            raise ValueError(f"--reference={self.reference!r}: not among the policies "
                             f"{list(self.run_policies)}")  # fmt: skip

    def _default_checkpoints(self) -> Path:
        """The shipped folder, unless a method must be trained and the references stay."""
        if self.update_reference:
            return reference("agents/checkpoints/study")
        shipped = [
            p for p in self.trained if installed_steps(p, STUDY_CHECKPOINTS) >= self.env_steps
        ]
        return STUDY_CHECKPOINTS if len(shipped) == len(self.trained) else TRAINED_HERE

    @property
    def run_policies(self) -> tuple[str, ...]:
        """``policies``, or the study's own."""
        if self.policies:
            return self.policies
        return SWEEP_STUDIES[self.study][1] if self.study in SWEEP_STUDIES else STUDIES[self.study]

    @property
    def trained(self) -> tuple[str, ...]:
        """The study's policies that its training pipeline makes."""
        return tuple(p for p in self.run_policies if p in METHOD_FLAGS)

    @property
    def results(self) -> Path:
        """Records folder: the table studies share results/study (a policy's cells run once
        for every study it is in), the sweeps have their own."""
        default = f"study-{self.study}" if self.study in SWEEP_STUDIES else "study"
        return self.out or RESULTS / default

    @property
    def report_pdf(self) -> Path:
        if self.update_reference:
            return reference(f"reports/{self.study}.pdf")
        return self.pdf or self.results / f"{self.study}.pdf"

    def budget(self) -> Budget:
        return Budget(env_steps=self.env_steps, seed=self.train_seed)

    def sweep(self):  # -> SweepConfig (imported late: the sweep module pulls in the world)
        """The evaluation cells as a sweep (its records, resume and parallelism)."""
        from mixed_traffic.experiments.sweep import SweepConfig

        axis, values = "penetration", (self.at_penetration,)
        if self.study in SWEEP_STUDIES:
            axis, values = SWEEP_STUDIES[self.study][0], ()
        return SweepConfig(
            axis=axis, scenario=self.scenario, at_density=self.at_density,
            at_penetration=self.at_penetration, values=values, reference=False,
            policies=self.run_policies, seeds=self.seeds, episode_length=self.episode_length,
            warmup=self.warmup, workers=self.workers, backend=self.backend,
            address=self.address, out=self.results, report=False, traffic=False,
            checkpoints=self.checkpoints,
        )  # fmt: skip


def missing_checkpoints(cfg: StudyConfig) -> list[str]:
    """The study's trained policies without a checkpoint trained on the full budget."""
    return [p for p in cfg.trained if installed_steps(p, cfg.checkpoints) < cfg.env_steps]


def check_trained(cfg: StudyConfig) -> None:
    """With ``--no-train``, ValueError naming the methods that are not trained on the budget."""
    missing = missing_checkpoints(cfg)
    if missing and not cfg.train:
        raise ValueError(f"{missing} in {cfg.checkpoints} are not trained on {cfg.env_steps} "
                         "transitions: drop --no-train")  # fmt: skip


def train_missing(cfg: StudyConfig, log=print) -> None:
    """Train every method of ``cfg`` without a checkpoint (each resumable in ``cfg.runs``)."""
    from mixed_traffic.experiments.study_methods import copy_installed, train_method

    for name in missing_checkpoints(cfg):
        copy_installed(name, STUDY_CHECKPOINTS, cfg.checkpoints)
        log(f"training {name} ({cfg.env_steps} transitions) in {cfg.runs / name} ...")
        t0 = time.time()
        cfg.runs.mkdir(parents=True, exist_ok=True)
        train_method(name, cfg.budget(), cfg.checkpoints, cfg.runs, cfg.runs / f"{name}.log")
        log(f"  {name}: {time.time() - t0:.0f} s")


def setup_text(cfg: StudyConfig) -> str:
    """The report's description of the study's setup."""
    return (
        f"Policies: {', '.join(cfg.run_policies)}. Evaluation: {cfg.scenario}, seeds "
        f"{', '.join(map(str, cfg.seeds))}, {cfg.episode_length:g} s episodes after "
        f"{cfg.warmup:g} s warm-up. Every trained method ran the same pipeline "
        "(python -m mixed_traffic.train) on the same train-split scenarios, densities, "
        "penetrations, weathers and training seed, for the same number of transitions (see "
        "'Training lineage'); rbp-dqn is AUTO's own pipeline at that budget, and "
        f"{cfg.reference} the reference of the paired tests. 'auto' is the shipped AUTO, trained longer (agents/checkpoints/"
        "auto.json): not a same-budget comparison. Learned policies run behind the same safety "
        "module; its share of changed decisions is the 'safety module' column."
    )


def run_study(cfg: StudyConfig) -> Path:
    """Train what is missing, run the cells, write the report; returns the PDF."""
    from analysis.report import build_report
    from analysis.study_report import build_study_report
    from mixed_traffic.experiments.sweep import run_sweep

    check_trained(cfg)
    train_missing(cfg)
    run_sweep(cfg.sweep())
    if cfg.study in SWEEP_STUDIES:
        return build_report(cfg.results, cfg.report_pdf, title=f"Mixed-traffic study: {cfg.study}")
    return build_study_report(cfg.results, cfg.report_pdf, cfg.study, cfg.reference,
                              cfg.checkpoints, setup_text(cfg), cfg.run_policies)  # fmt: skip


def parse_args(argv: list[str] | None) -> StudyConfig:
    p = argparse.ArgumentParser(
        prog="python -m mixed_traffic.study",
        description="The paper's comparison studies: trains each method on one budget, "
        "evaluates them (resumable, parallel) and writes a PDF report in the paper's style.",
    )
    kind = p.add_mutually_exclusive_group()
    for k in KINDS:
        kind.add_argument(f"--{k}", dest=config_dest("study"), action="store_const", const=k,
                          help=f"the {k} study" + (" (default)" if k == "baselines" else ""))  # fmt: skip
    add_config_args(p, StudyConfig, only=[f.name for f in dataclasses.fields(StudyConfig)
                                          if f.name != "study"])  # fmt: skip
    try:
        cfg = config_from_args(p.parse_args(argv), StudyConfig)
        check_writable(cfg.results / "records.jsonl")
        check_writable(cfg.report_pdf, what="report")
        check_trained(cfg)
    except ValueError as e:
        p.error(str(e))
    return cfg


def main(argv: list[str] | None = None) -> int:
    cfg = parse_args(argv)
    try:
        pdf = run_study(cfg)
    except (FolderBusyError, ValueError, RuntimeError) as e:
        print(f"python -m mixed_traffic.study: error: {e}", file=sys.stderr)
        return 2
    print(f"report: {pdf}")
    from mixed_traffic.experiments.sweep import cells, failed_cells

    failed = failed_cells(cfg.sweep())
    if failed:
        print(f"{len(failed)} of {len(cells(cfg.sweep()))} cells failed (errors in "
              f"{cfg.results / 'records.jsonl'}); run the study again to retry them",
              file=sys.stderr)  # fmt: skip
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
