"""Evaluate a policy over episodes and record flow and safety metrics (DESIGN §9, §11).

    python -m mixed_traffic.evaluate --policy idm --scenario straight --density 120 \\
        --penetration 0 --seeds 0 1 2 [--episode-length 120] [--warmup 30] [--json]

prints a metrics table (one column per seed, plus the mean), appends one record per episode to
``--out`` (JSON lines, layout in ``mixed_traffic.schema``, atomic writes) and, with ``--json``,
prints the records as JSON lines on stdout (the table then goes to stderr).

Policies: ``idm`` is the all-IDM reference: no policy acts, and AV-typed vehicles are handed
back to SUMO (default speed and lane-change modes), so they drive by SUMO's IDM and lane-change
model with the AV vType's parameters. Env-driven policies (auto, acc-lc, random) plug in as
``Policy`` objects (see ``POLICIES``) once the env exists.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from tqdm import tqdm

from mixed_traffic.config import EnvConfig
from mixed_traffic.env.metrics import FlowRecorder
from mixed_traffic.experiments.cli import add_config_args, config_from_args
from mixed_traffic.provenance import json_safe, record_meta, write_record_atomic
from mixed_traffic.schema import CELL_KEYS, METRICS, TERMINAL_REASONS
from mixed_traffic.world.backend import SumoBackend, SumoError
from mixed_traffic.world.boundary import PeriodicBoundary
from mixed_traffic.world.registry import (
    Scenario,
    check_density,
    load_scenario,
    make_demand,
    sumo_args,
    write_demand,
)
from mixed_traffic.world.snapshot import TrafficSnapshot

DEFAULT_OUT = Path("results/evaluate/records.jsonl")
DEFAULT_WARMUP = 30.0
#: EnvConfig fields exposed as options, in help order.
CONFIG_OPTIONS = [
    "scenario", "density", "penetration", "weather", "episode_length", "step_length",
    "lateral_resolution", "backend",
]  # fmt: skip


# --------------------------------------------------------------------------- policies
class Policy(Protocol):
    """What ``run_episode`` needs from a policy driving the AVs."""

    name: str

    def reset(self, backend: SumoBackend, config: EnvConfig) -> None:
        """Called once after SUMO started, before the first step."""

    def after_step(self, snap: TrafficSnapshot, backend: SumoBackend) -> None:
        """Called after every step with its snapshot; issue commands for the next step here."""

    def metrics(self) -> dict[str, Any]:
        """Policy-side metrics for the record (keys of ``schema.METRICS``)."""


class IdmPolicy:
    """All-IDM reference: AVs are handed back to SUMO's IDM and lane changing; nothing acts."""

    name = "idm"

    def reset(self, backend: SumoBackend, config: EnvConfig) -> None:
        self._released: set[str] = set()

    def after_step(self, snap: TrafficSnapshot, backend: SumoBackend) -> None:
        new = [v for v, av in zip(snap.ids, snap.is_av.tolist()) if av and v not in self._released]
        if new:
            backend.release_control(new)
            self._released.update(new)

    def metrics(self) -> dict[str, Any]:
        # no policy can terminate an AV: every terminal count is 0 by construction
        return {f"terminal_{r}": 0 for r in TERMINAL_REASONS}


#: Policies that drive the AVs through the env (observations -> parameterized actions).
ENV_POLICIES = ("auto", "auto-raw", "acc-lc", "random")
#: Policy name -> factory for the SUMO-only loop (env-driven policies are made by ``agents``).
POLICIES: dict[str, Any] = {"idm": IdmPolicy}


def make_policy(name: str, **kwargs: Any) -> Policy:
    """A fresh policy object by name."""
    if name not in POLICIES:
        raise ValueError(
            f"policy {name!r} is not available; choose from {sorted([*POLICIES, *ENV_POLICIES])}"
        )
    return POLICIES[name](**kwargs)


# --------------------------------------------------------------------------- episodes
def check_run(config: EnvConfig, warmup: float) -> Scenario:
    """Validate what SUMO cannot check early: scenario, density vs. jam density, warm-up."""
    scenario = load_scenario(config.scenario)
    check_density(scenario, config.density)
    if not 0 <= warmup < config.episode_length:
        raise ValueError(
            f"warmup={warmup} s must be in [0, episode_length={config.episode_length}) s"
        )
    return scenario


def run_episode(
    config: EnvConfig,
    policy: str | Policy = "idm",
    warmup: float = DEFAULT_WARMUP,
    *,
    progress: bool = False,
    **policy_kwargs: Any,
) -> dict[str, Any]:
    """Run one episode of ``config`` under ``policy`` and return its record (``schema`` layout).

    Args:
        config: the environment; ``config.seed`` seeds demand and SUMO.
        policy: a name from ``POLICIES`` or a ``Policy`` object.
        warmup: simulated time before density and speed are averaged [s].
        progress: show a per-step progress bar.
        policy_kwargs: passed to the policy factory; ones it does not take (e.g. a
            ``checkpoint`` for learned policies) are ignored by ``idm``.

    Raises:
        ValueError: bad scenario, density or warm-up (before SUMO starts).
        SumoError: SUMO failed to start.
    """
    if isinstance(policy, str) and policy in ENV_POLICIES:
        return run_env_episode(config, policy, warmup, progress=progress, **policy_kwargs)
    scenario = check_run(config, warmup)
    if isinstance(policy, str):
        kwargs = {k: v for k, v in policy_kwargs.items() if v is not None and policy != "idm"}
        policy = make_policy(policy, **kwargs)
    meta = record_meta(config)
    t0 = time.perf_counter()
    hd = scenario.hdmap
    demand = make_demand(scenario, config, np.random.default_rng(config.seed))
    recorder = FlowRecorder(hd, scenario.measurement, config.step_length, warmup)
    backend = SumoBackend(config.backend, config.second_instance)
    try:
        with tempfile.TemporaryDirectory(prefix="mixed_traffic_eval_") as tmp:
            route_file = Path(tmp) / "demand.rou.xml"
            write_demand(demand, config, route_file)
            backend.set_lane_table(hd.lane_ids, hd.lane_edge)
            backend.start(sumo_args(scenario, config, route_file, seed=config.seed))
            boundary = PeriodicBoundary.for_demand(
                scenario, demand, config.vehicle, config.step_length, config.fixed_fleet
            )
            policy.reset(backend, config)
            steps = range(config.steps_per_episode)
            for k in tqdm(steps, desc="steps", leave=False, disable=not progress):
                snap = backend.step()
                if k == 0:
                    backend.drop_pending(demand.placed_ids)
                boundary.step(snap, backend)
                recorder.update(snap)
                policy.after_step(snap, backend)
    finally:
        backend.close()
    metrics: dict[str, Any] = dict.fromkeys(METRICS)
    metrics.update(recorder.summary())
    metrics.update(policy.metrics())
    cell = {k: getattr(config, k) for k in CELL_KEYS if k not in ("policy", "seed")}
    return {
        "cell": {"policy": policy.name, **cell, "seed": config.seed},
        "status": "ok",
        "error": None,
        **meta,
        "warmup": warmup,
        "wall_time": round(time.perf_counter() - t0, 3),
        "metrics": json_safe(metrics),
        "diagnostics": json_safe(recorder.diagnostics()),
    }


def run_env_episode(
    config: EnvConfig,
    policy: str,
    warmup: float = DEFAULT_WARMUP,
    *,
    checkpoint: str | Path | None = None,
    gif: str | Path | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """One episode of the env with an observation-driven policy (auto, acc-lc, random).

    Inference is one batched call per step for all agents; AvgIT is its wall time per decision.
    """
    from agents.policies import make_policy, stack_obs, to_actions
    from mixed_traffic.env import MixedTrafficEnv

    check_run(config, warmup)
    meta = record_meta(config)
    t0 = time.perf_counter()
    agent = make_policy(policy, seed=config.seed, checkpoint=checkpoint,
                        z=config.sensors.history, m=config.sensors.waypoints)  # fmt: skip
    env = MixedTrafficEnv(config=config, warmup=warmup, render_mode="rgb_array" if gif else None)
    frames = _Gif(gif)
    infer, decisions = 0.0, 0
    try:
        obs, _ = env.reset(seed=config.seed)
        frames.add(env)
        for _ in tqdm(
            range(config.steps_per_episode), desc="steps", leave=False, disable=not progress
        ):
            agents = list(env.agents)
            actions: dict[str, Any] = {}
            if agents:
                batch = stack_obs(obs, agents)
                t = time.perf_counter()
                decision, params = agent.act(batch)
                infer += time.perf_counter() - t
                decisions += len(agents)
                actions = to_actions(agents, decision, params)
            obs, *_ = env.step(actions)
            frames.add(env)
            if env.sim_time >= config.episode_length - 1e-9:
                break
        metrics: dict[str, Any] = dict.fromkeys(METRICS)
        metrics.update(env.episode_metrics())
    finally:
        env.close()
    frames.save(fps=1.0 / config.step_length)
    metrics["avg_it"] = 1000.0 * infer / decisions if decisions else None
    if getattr(agent, "safety", None) is not None:
        metrics["sm_share"] = agent.safety.share
    cell = {k: getattr(config, k) for k in CELL_KEYS if k not in ("policy", "seed")}
    record = {
        "cell": {"policy": policy, **cell, "seed": config.seed},
        "status": "ok",
        "error": None,
        **meta,
        "warmup": warmup,
        "wall_time": round(time.perf_counter() - t0, 3),
        "metrics": json_safe(metrics),
    }
    if policy.startswith("auto"):
        record["checkpoint"] = str(getattr(agent, "checkpoint", ""))
    return record


class _Gif:
    """Collects every 2nd rendered frame of an episode and writes it as a GIF (or does nothing)."""

    def __init__(self, path: str | Path | None) -> None:
        from mixed_traffic.env.render import FrameCollector

        self.path = path
        self.frames = FrameCollector(every=2)

    def add(self, env: Any) -> None:
        if self.path is not None:
            self.frames.add(env.render())

    def save(self, fps: float) -> None:
        if self.path is not None and self.frames.frames:
            from mixed_traffic.env.render import record_gif

            record_gif(self.frames.frames, self.path, fps=fps / self.frames.every)


# --------------------------------------------------------------------------- output
def _fmt(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.3g}" if abs(value) < 1000 else f"{value:.0f}"
    return str(value)


def metrics_table(records: list[dict[str, Any]]) -> str:
    """Plain-text table: one row per metric measured in any record, one column per seed + mean."""
    keys = [k for k in METRICS if any(r["metrics"].get(k) is not None for r in records)]
    seeds = [f"seed {r['seed']}" for r in records]
    head = ["metric", "unit", *seeds, "mean"]
    rows = []
    for k in keys:
        vals = [r["metrics"].get(k) for r in records]
        nums = [v for v in vals if isinstance(v, (int, float))]
        mean = float(np.mean(nums)) if nums else None
        rows.append([METRICS[k].label, METRICS[k].unit, *map(_fmt, vals), _fmt(mean)])
    di = [r.get("diagnostics", {}).get("delay_index_crossed_mean") for r in records]
    if any(v is not None for v in di):
        nums = [v for v in di if v is not None]
        rows.append(["DI (crossed)", "-", *map(_fmt, di), _fmt(float(np.mean(nums)))])
    widths = [max(len(str(x)) for x in col) for col in zip(head, *rows)]
    line = "  ".join(
        h.ljust(w) if i < 2 else h.rjust(w) for i, (h, w) in enumerate(zip(head, widths))
    )
    out = [line, "-" * len(line)]
    for row in rows:
        cells = (c.ljust(w) if i < 2 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths)))
        out.append("  ".join(cells))
    return "\n".join(out)


# --------------------------------------------------------------------------- CLI
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m mixed_traffic.evaluate",
        description="Run episodes of a policy and report flow and safety metrics (DESIGN §9).",
    )
    parser.add_argument(
        "--policy", choices=sorted([*POLICIES, *ENV_POLICIES]), default="idm",
        help="policy driving the AVs; idm = all-IDM reference (default: idm)",
    )  # fmt: skip
    add_config_args(parser, EnvConfig, only=CONFIG_OPTIONS, group_title="environment")
    parser.add_argument(
        "--seeds", type=int, nargs="+", default=[EnvConfig.seed], metavar="SEED",
        help="root seeds, one episode each (default: 0)",
    )  # fmt: skip
    parser.add_argument(
        "--warmup", type=float, default=DEFAULT_WARMUP, metavar="S",
        help=f"simulated time before density and speed are averaged [s] (default: {DEFAULT_WARMUP})",
    )  # fmt: skip
    parser.add_argument(
        "--out", type=Path, default=DEFAULT_OUT, metavar="FILE",
        help=f"records file, one JSON line per episode, appended (default: {DEFAULT_OUT})",
    )  # fmt: skip
    parser.add_argument(
        "--json", action="store_true", help="print the records as JSON lines on stdout"
    )
    parser.add_argument(
        "--checkpoint", type=Path, default=None, metavar="FILE",
        help="AUTO checkpoint for --policy auto (default: the shipped agents/checkpoints/auto.pt)",
    )  # fmt: skip
    parser.add_argument(
        "--gif", type=Path, default=None, metavar="FILE",
        help="record the (first) episode as an animated GIF (bird's-eye view)",
    )  # fmt: skip
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        configs = [config_from_args(args, EnvConfig, seed=s) for s in args.seeds]
        check_run(configs[0], args.warmup)
    except (ValueError, KeyError) as e:
        parser.error(str(e).strip("'\""))
    if args.gif is not None and args.policy not in ENV_POLICIES:
        parser.error(f"--gif records the env's view; use an env-driven policy {ENV_POLICIES}")
    records: list[dict[str, Any]] = []
    failed = 0
    for cfg in tqdm(configs, desc="episodes", disable=len(configs) == 1 or None):
        try:
            extra = {"checkpoint": args.checkpoint, "gif": args.gif if cfg is configs[0] else None}
            record = run_episode(cfg, args.policy, args.warmup, **extra)
        except (SumoError, ValueError) as e:  # e.g. SUMO failed, or a bad checkpoint
            print(f"error: seed {cfg.seed}: {e}", file=sys.stderr)
            failed += 1
            record = {
                "cell": {"policy": args.policy, **{k: getattr(cfg, k) for k in CELL_KEYS[1:]}},
                "status": "failed",
                "error": str(e),
                **record_meta(cfg),
                "metrics": {},
            }
        write_record_atomic(args.out, record)
        if record["status"] == "ok":
            records.append(record)
    if records:
        table = metrics_table(records)
        header = (
            f"policy={args.policy} scenario={configs[0].scenario} density={configs[0].density} "
            f"veh/km penetration={configs[0].penetration} episode={configs[0].episode_length} s "
            f"warmup={args.warmup} s  records -> {args.out}"
        )
        print(header + "\n" + table, file=sys.stderr if args.json else sys.stdout)
    if args.json:
        for r in records:
            print(json.dumps(r, allow_nan=False))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
