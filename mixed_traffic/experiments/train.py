"""``python -m mixed_traffic.train``: multi-worker RBP-DQN training (paper §IV-F, DESIGN §10).

The options are built from :class:`agents.training.trainer.TrainConfig` (field docstrings carry the
units). This module composes: it resolves and validates the scenarios (train split only) and
the density range per scenario before any worker starts, then runs :class:`Trainer` and, with
``--fleet-iterations``, the fleet-return search stage on its result (``--resume`` continues
whichever stage the run is in).

Examples::

    python -m mixed_traffic.train --workers 2 --env-steps 2000000 --out runs/auto
    python -m mixed_traffic.train --workers 2 --minutes 60 --out runs/auto --resume
    python -m mixed_traffic.train --workers 10 --backend ray --address auto --env-steps 5e6
    python -m mixed_traffic.train --env-steps 2e6 --fleet-iterations 40 --out runs/auto
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mixed_traffic.config import EnvConfig
from mixed_traffic.experiments import cli
from mixed_traffic.experiments.cli import add_config_args

FLEET_DIR = "fleet"
"""Subfolder of OUT where the fleet-return search stage runs."""
_SHORT = {"workers", "backend", "address", "scenarios", "densities", "penetrations", "weathers",
          "env_steps", "minutes", "out", "seed", "demo_steps", "ablation", "baseline", "bp_dqn",
          "fleet_iterations"}  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    from agents.training.config import TrainConfig

    p = argparse.ArgumentParser(
        prog="python -m mixed_traffic.train",
        description="Train the AUTO agent (LCA + RBP-DQN) with N rollout workers and one learner. "
        "Writes OUT/curves.csv; commits checkpoint, replay and counters together into "
        "OUT/commits/ (the manifest OUT/COMMIT names the last) and copies the checkpoint to "
        "OUT/checkpoint.pt and OUT/snapshots/; at the end OUT/auto.pt + OUT/auto.json.",
    )
    names = [f.name for f in dataclasses.fields(TrainConfig)]
    add_config_args(p, TrainConfig, only=[n for n in names if n in _SHORT])
    add_config_args(p, TrainConfig, only=[n for n in names if n not in _SHORT],
                    group_title="advanced")  # fmt: skip
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue the run in --out from its last commit (checkpoint, replay and "
        "counters); a run killed before its first commit starts afresh",
    )
    sensors = EnvConfig().sensors
    p.add_argument("--history", type=int, default=sensors.history,
                   help=f"observation history z [steps] (default: {sensors.history})")  # fmt: skip
    p.add_argument("--waypoints", type=int, default=sensors.waypoints,
                   help=f"lane waypoints m per lane [count] (default: {sensors.waypoints})")  # fmt: skip
    return p


def config_from_args(args: argparse.Namespace, parser: argparse.ArgumentParser) -> Any:
    """TrainConfig from the options; validates scenarios and densities (parser.error on bad)."""
    from agents.training.config import TrainConfig
    from mixed_traffic.provenance import check_folder
    from mixed_traffic.world.registry import list_scenarios, train_scenarios, train_split_scenario

    try:
        cfg = cli.config_from_args(args, TrainConfig)
    except ValueError as e:
        parser.error(str(e))
    try:
        check_folder(cfg.out)
    except ValueError as e:
        parser.error(f"--out: {e}")
    scen = tuple(s for s in cfg.scenarios if s) or tuple(train_scenarios())
    for s in scen:
        if s not in list_scenarios():
            parser.error(
                f"--scenarios: unknown scenario {s!r}; known: {', '.join(list_scenarios())}"
            )
        try:
            sc = train_split_scenario(s)
        except ValueError as e:
            parser.error(f"--scenarios: {e}")
        try:
            sc.feasible_densities(cfg.densities)
        except ValueError as e:
            parser.error(f"--densities: {e}")
    return dataclasses.replace(cfg, scenarios=scen)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    cfg = config_from_args(args, parser)
    base = EnvConfig()
    try:
        sensors = dataclasses.replace(base.sensors, history=args.history, waypoints=args.waypoints)
    except ValueError as e:
        parser.error(str(e))
    env_base = dataclasses.replace(base, sensors=sensors)
    from agents.training.trainer import Trainer

    argv_list = list(sys.argv[1:] if argv is None else argv)
    command = shlex.join(["python", "-m", "mixed_traffic.train", *argv_list])
    fleet_started = args.resume and (Path(cfg.out) / FLEET_DIR / "state.json").exists()
    if not fleet_started:  # else the RBP-DQN stage is done: go on with the fleet search
        try:
            trainer = Trainer(cfg, env_base=env_base, resume=args.resume, command=command)
        except (FileExistsError, FileNotFoundError, ValueError) as e:
            parser.error(str(e))
        info = trainer.run()
        print(f"done: {info['env_steps']} env steps, {info['updates']} updates, "
              f"{info['episodes']} episodes in {info['wall_time_s']:.0f} s; "
              f"worker restarts {info['worker_restarts']}; wrote {cfg.out}/auto.pt")  # fmt: skip
    if cfg.fleet_iterations:
        fleet_stage(cfg)
    return 0


def fleet_stage(cfg: Any) -> None:
    """Fleet-return search from OUT/auto.pt in OUT/fleet (resumed if there), for the run's
    ``fleet_iterations`` in all, on episodes sampled like the RBP-DQN stage's; its policy then
    replaces OUT/auto.pt."""
    from agents.training.trainer import atomic_write_json
    from mixed_traffic.experiments.fleet import FleetConfig, FleetSearch
    from mixed_traffic.provenance import atomic_write

    out = Path(cfg.out)
    fleet = FleetConfig(
        init=out / "auto.pt", out=out / FLEET_DIR, minutes=0.0, iterations=cfg.fleet_iterations,
        workers=cfg.workers, seed=cfg.seed, scenarios=cfg.scenarios, densities=cfg.densities,
        penetrations=cfg.penetrations, weathers=cfg.weathers, episode_length=cfg.episode_length,
        warmup=min(FleetConfig.warmup, cfg.episode_length / 4), progress=cfg.progress,
        speed_governor=cfg.speed_governor, rss_governor=cfg.rss_governor,
    )  # fmt: skip
    search = FleetSearch(fleet)
    policy = search.run().read_bytes()
    atomic_write(out / "auto.pt", lambda f: f.write(policy))
    info = json.loads((out / "auto.json").read_text())
    info["fleet_search"] = {k: search.state[k] for k in ("iteration", "episodes", "minutes")}
    atomic_write_json(out / "auto.json", info)
    print(f"fleet search: {cfg.fleet_iterations} iterations; wrote {out}/auto.pt")


if __name__ == "__main__":
    sys.exit(main())
