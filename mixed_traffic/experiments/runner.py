"""The one episode runner: evaluate, sweep, compare and the safety table run every policy here,
the all-human reference included, with the same seeding, warm-up and metrics path.

    record = run_episode(EnvConfig(scenario="straight", penetration=0.5, seed=0), "acc-lc")

A policy maps the batched observations of all agents of a step to their actions in one call
(``agents.policies``). The ``idm`` reference is no policy: the env hands the AV-typed vehicles
back to SUMO (``sumo_drives_avs``), so they drive by SUMO's car-following and lane-change
models with the AV vType's parameters, and at 0 % AVs every vehicle is a human driver.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from agents.policies import checkpoint_path, make_policy, with_inputs
from agents.rules.spec import parse_policy
from mixed_traffic.config import EnvConfig
from mixed_traffic.env.action import no_actions
from mixed_traffic.env.checks import check_warmup
from mixed_traffic.env.parallel import MixedTrafficEnv
from mixed_traffic.paths import cache_dir
from mixed_traffic.provenance import atomic_write, file_digest, json_safe, record_meta
from mixed_traffic.schema import CELL_KEYS, METRICS
from mixed_traffic.world.episode import check_batch
from mixed_traffic.world.registry import load_scenario

DEFAULT_WARMUP = 30.0
"""Simulated time before density and speed are averaged [s], where the scenario's spec gives
no warm-up of its own."""
SUMO_DRIVEN = ("idm",)
"""Policies under which SUMO drives the AVs (no agent acts)."""


def sumo_drives(policy: str) -> bool:
    """Whether SUMO drives the AVs under ``policy`` (a name or spec such as ``idm``)."""
    return parse_policy(policy).base in SUMO_DRIVEN


def validate(
    config: EnvConfig, warmup: float | None, policy: str | None = None
) -> tuple[EnvConfig, float]:
    """Everything an episode needs checked before any work starts: the policy name, the
    scenario (and that it can be copied), the density against its jam density and the warm-up. Raises ``ValueError``.
    Returns ``config`` with the scenario's defaults (density, episode length) where it gives
    none, and the warm-up [s]: ``warmup``, else the scenario's, else ``DEFAULT_WARMUP``."""
    if policy is not None:
        check_policy(policy)
    scenario = load_scenario(config.scenario)
    config = scenario.configure(config)
    check_batch(scenario, config)
    warmup = scenario.default_warmup(warmup, DEFAULT_WARMUP, config.episode_length)
    check_warmup(warmup, config.episode_length)
    return config, warmup


def check_policy(policy: str) -> str:
    """``policy``'s canonical spec (:mod:`agents.rules.spec`); ``ValueError`` unless it names
    one of ``schema.POLICIES`` with valid parameters (and ``acc-lc-tuned`` its readable file)."""
    spec = parse_policy(policy)
    if spec.base == "acc-lc-tuned":
        from agents.rules.tuned import tuned_params

        tuned_params(None)
    return str(spec)


def check_checkpoint(path: str | Path) -> None:
    """Raise ``ValueError`` naming ``path`` unless it is a readable RBP-DQN checkpoint (or, for
    a ``.zip``, a PPO one)."""
    if Path(path).suffix == ".zip":
        from agents.ppo_policy import check_ppo_checkpoint

        return check_ppo_checkpoint(path)
    from agents.checkpoint import read_checkpoint  # torch only when a checkpoint is named

    read_checkpoint(path)


def run_episode(
    config: EnvConfig,
    policy: str = "idm",
    warmup: float | None = None,
    *,
    checkpoint: str | Path | None = None,
    gif: str | Path | None = None,
    trace: str | Path | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Run one episode of ``config`` (one copy) under ``policy`` and return its record
    (``schema`` layout); ``run_copies`` runs a batch of copies.

    Inference is one batched call per step for all agents; AvgIT is its wall time per decision.

    Args:
        config: the environment; ``config.seed`` seeds demand, SUMO and sensor noise.
        policy: a name from ``schema.POLICIES`` or a rule's spec (``acc-lc:T=1.0``); the
            record's cell carries its canonical text, ``policy_params`` what it resolved to.
        warmup: simulated time before flow metrics are averaged [s] (None: the scenario's,
            else ``DEFAULT_WARMUP``).
        checkpoint: AUTO checkpoint for ``auto``/``auto-raw`` (default: the shipped one).
        gif: record the episode as an animated GIF here.
        trace: write every vehicle's trajectory in the measurement segment here (``.npz``:
            ``t`` [s], ``s`` [m], ``v`` [m/s], every 0.5 s after warm-up, and a ``title``).
        progress: show a per-step progress bar.

    Raises:
        ValueError: bad policy, scenario, density, warm-up or checkpoint (before SUMO starts),
            or ``config.copies`` > 1.
        SumoError: SUMO failed to start.
    """
    if config.copies != 1:
        raise ValueError(f"run_episode runs one copy, and copies={config.copies}: use run_copies")
    return run_copies(config, policy, warmup, checkpoint=checkpoint, gif=gif, trace=trace,
                      progress=progress)[0]  # fmt: skip


def run_copies(
    config: EnvConfig,
    policy: str = "idm",
    warmup: float | None = None,
    *,
    checkpoint: str | Path | None = None,
    gif: str | Path | None = None,
    trace: str | Path | None = None,
    progress: bool = False,
) -> list[dict[str, Any]]:
    """``run_episode`` of the ``config.copies`` copies of a batch in one simulation: one record
    per copy, each with its ``copy`` index and the batch's seed (a copy is reproducible
    within its batch, not as a solo episode). The policy's inference time, safety-module
    shares and parameter statistics are the batch's."""
    policy = check_policy(policy)
    config = with_inputs(config, policy, checkpoint)  # the opt-in keys it was trained with
    # before this episode's simulation: the reference runs its own (one per process)
    fixed_u = reference_u(checkpoint) if parse_policy(policy).base == "auto-mean" else None
    t0 = time.perf_counter()
    # the env validates the config against its scenario before anything else is done
    config, warmup = validate(config, warmup)
    env = MixedTrafficEnv(config=config, warmup=warmup, sumo_drives_avs=sumo_drives(policy),
                          render_mode="rgb_array" if gif else None, trace=trace is not None)  # fmt: skip
    config, meta = env.config, record_meta(env.config)  # the scenario's defaults filled in
    frames = _Gif(gif)
    n = config.copies
    try:
        agent = batch_policy(policy, config, checkpoint, env.scenario.family)
        if fixed_u is not None:
            agent.driver.fixed_u = fixed_u
        infer_s, decisions = _drive(env, agent, frames, progress)
        metrics = [{**dict.fromkeys(METRICS), **env.episode_metrics(c)} for c in range(n)]
        diagnostics = [env.flow_diagnostics(None if n == 1 else c) for c in range(n)]
        ring_lengths = env.ring_lengths  # drawn at reset when config.ring_length is a range
        if trace is not None:
            _save_trace(Path(trace), env.trajectories(), f"{policy}, {describe(config)}")
    finally:
        env.close()
    frames.save(fps=1.0 / config.step_length)
    shared_metrics, shared = _policy_figures(agent, infer_s, decisions)
    wall = round(time.perf_counter() - t0, 3)
    return [
        _record(config, policy, meta, warmup, c, ring_lengths[c], wall,
                {**metrics[c], **shared_metrics}, {**diagnostics[c], **shared}, agent)
        for c in range(n)
    ]  # fmt: skip


def _policy_figures(agent: Any, infer_s: float, decisions: int) -> tuple[dict, dict]:
    """(metrics, diagnostics) of the policy over the whole batch: inference time per
    decision, the safety module's shares, the network's parameter statistics."""
    metrics: dict[str, Any] = {"avg_it": 1000.0 * infer_s / decisions if decisions else None}
    diagnostics: dict[str, Any] = {}
    if getattr(agent, "safety", None) is not None:
        metrics["sm_share"] = agent.safety.share
        diagnostics.update(agent.safety.shares)
    if getattr(agent, "driver", None) is not None:
        diagnostics["hold_share"] = agent.driver.hold_share
        for name in ("u_mean", "u_std"):
            u = getattr(agent.driver, name)
            diagnostics[name] = None if u is None else u.ravel().tolist()
        diagnostics["u_decisions"] = agent.driver.u_decisions
    return metrics, diagnostics


def _record(config: EnvConfig, policy: str, meta: dict, warmup: float, copy: int,
            ring_length: float | None, wall: float, metrics: dict, diagnostics: dict,
            agent: Any) -> dict[str, Any]:  # fmt: skip
    """One copy's record."""
    record = {
        "cell": {**cell_of(config, policy), "copy": copy},
        "status": "ok",
        "error": None,
        **meta,
        "warmup": warmup,
        "ring_length": ring_length,
        "wall_time": wall,
        "metrics": json_safe(metrics),
        "diagnostics": json_safe(diagnostics),
    }
    if getattr(agent, "params", None):
        record["policy_params"] = json_safe(agent.params)
    source = getattr(agent, "checkpoint", None)  # weights, or the tuned parameters' file
    if source is not None:
        record["checkpoint"] = str(source)
        record["checkpoint_sha"] = file_digest(source)
    return record


REFERENCE_STATES = (
    EnvConfig(scenario="straight", density=120.0, penetration=0.5, episode_length=60.0),
    EnvConfig(scenario="merge", penetration=0.5, episode_length=60.0),
    EnvConfig(scenario="ring", ring_vehicles=22, ring_length=(260.0,), penetration=1 / 22,
              episode_length=300.0),
    EnvConfig(scenario="wave-highway", penetration=0.05, episode_length=120.0),
)  # fmt: skip
"""The reference set of ``auto-mean``: the states AUTO visits in these episodes (seed 0, the
training split's road, merge, ring and wave road), every decision weighing the same."""


def reference_u(checkpoint: str | Path | None,
                configs: tuple[EnvConfig, ...] | None = None) -> np.ndarray:  # fmt: skip
    """(3, 2) mean of AUTO's continuous parameters u (``checkpoint``'s; None: the shipped one)
    over its decisions in ``configs`` (default ``REFERENCE_STATES``), cached per checkpoint
    content and reference set."""
    configs = configs or REFERENCE_STATES
    path = checkpoint_path("auto", checkpoint)
    key = file_digest(path)[:16] + "-" + hashlib.sha256(repr(configs).encode()).hexdigest()[:8]
    cache = cache_dir("auto_mean") / f"{key}.json"
    if cache.is_file():
        return np.array(json.loads(cache.read_text())["u_mean"])
    runs = [run_episode(c, "auto", 0.0, checkpoint=path)["diagnostics"] for c in configs]
    n = np.array([r["u_decisions"] for r in runs], np.float64)
    means = np.array([r["u_mean"] if r["u_mean"] else [0.0] * 6 for r in runs])
    u = (n @ means / max(n.sum(), 1.0)).reshape(3, 2)
    text = json.dumps({"checkpoint": str(path), "reference": [describe(c) for c in configs],
                       "decisions": n.tolist(), "u_mean": u.tolist()}, indent=1)  # fmt: skip
    atomic_write(cache, lambda f: f.write(text.encode()))
    return u


def cell_of(config: EnvConfig, policy: str) -> dict[str, Any]:
    """The record's ``cell``: the policy and the config's cell keys."""
    cell = {
        k: getattr(config, k) for k in CELL_KEYS if k not in ("policy", "detection_range", "copy")
    }
    return {"policy": policy, **cell, "detection_range": config.sensors.range_factor, "copy": 0}


def batch_policy(name: str, config: EnvConfig, checkpoint: str | Path | None, family: str) -> Any:
    """The batched policy for an episode of ``config``, or None when SUMO drives the AVs."""
    if sumo_drives(name):
        return None
    return make_policy(name, seed=config.seed, checkpoint=checkpoint, z=config.sensors.history,
                       m=config.sensors.waypoints, dt=config.step_length, family=family)  # fmt: skip


def decide(env: MixedTrafficEnv, agent: Any) -> tuple[np.ndarray, np.ndarray, float]:
    """``agent``'s stacked actions for ``env``'s live agents (one batched call: decision (A,),
    params (A, 3, 2)), and its inference time [s]; empty when no agent is live."""
    agents = list(env.agents)
    if not agents:
        return *no_actions(), 0.0
    batch = env.observation_batch(agents)
    t = time.perf_counter()
    decision, params = agent.act(batch, agents)
    return decision, params, time.perf_counter() - t


def _drive(env: MixedTrafficEnv, agent: Any, frames: _Gif, progress: bool) -> tuple[float, int]:
    """Step ``env`` to its time limit under ``agent``; (inference time [s], decisions)."""
    config = env.config
    infer, decisions = 0.0, 0
    env.reset(seed=config.seed, options={"allow_no_agents": True})  # all-human draws count
    frames.add(env)
    steps = range(config.steps_per_episode)
    for _ in tqdm(steps, desc="steps", leave=False, disable=not progress):
        decision, params, seconds = decide(env, agent)
        infer += seconds
        decisions += len(decision)
        env.step_batch(decision, params)
        frames.add(env)
        if env.sim_time >= config.episode_length - 1e-9:
            break
    return infer, decisions


def describe(config: EnvConfig) -> str:
    """'straight, 120 veh/km, 20 % AVs, normal, seed 0' for titles ('its density' where the
    config leaves the density to the scenario)."""
    density = "its density" if config.density is None else f"{config.density:g} veh/km"
    return (f"{config.scenario}, {density}, {100 * config.penetration:g} % AVs, "
            f"{config.weather}, seed {config.seed}")  # fmt: skip


def _save_trace(path: Path, traces: dict[str, np.ndarray], title: str) -> None:
    """Write a trajectory file atomically (a temporary file, then a rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp.npz")
    try:
        np.savez_compressed(tmp, title=np.array(title), **traces)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


class _Gif:
    """Collects every 2nd rendered frame of an episode and writes it as a GIF (or does nothing)."""

    def __init__(self, path: str | Path | None) -> None:
        from mixed_traffic.env.render import FrameCollector

        self.path = path
        self.frames = FrameCollector(every=2)

    def add(self, env: MixedTrafficEnv) -> None:
        if self.path is not None:
            self.frames.add(env.render())

    def save(self, fps: float) -> None:
        if self.path is not None and self.frames.frames:
            from mixed_traffic.env.render import record_gif

            record_gif(self.frames.frames, self.path, fps=fps / self.frames.every)
