"""Benchmarks (speed only; tests never assert wall-clock times).

    python -m mixed_traffic.bench [--section snapshot] [--steps N] [--densities 60 120 180]

Section ``snapshot``: on ``straight`` at each density, one simulation alternates blocks of
steps in two modes, both doing identical work so the traffic is the same:

* *raw*: ``backend.raw_step()`` is timed (bare ``simulationStep``), then ``backend.collect()``
  runs untimed so the boundary condition can keep the density;
* *step*: ``backend.step()`` (simulationStep + events + full snapshot) is timed.

Blocks come in adjacent (raw, step) pairs; per pair the mean ms/step of each mode, their ratio
and the snapshot cost per vehicle are computed, and the median over pairs is reported (robust to
load from other processes on a small machine). Target: the
snapshot adds ≤ 30 % to a raw step. Sections are functions in ``SECTIONS`` so others can add
theirs.

Section ``env``: ``MixedTrafficEnv.step`` with random actions (decision sampled under the
observation's ``action_mask``, params uniform in the Box; sampling is not timed) on ``straight``
at ``--env-density`` (120 veh/km) and each ``--penetrations`` value (0.2, 0.5, 1.0). In the same
simulation, blocks of env steps alternate with blocks of the *physical limit*: ``backend.step()``
(simulationStep + reading every vehicle into the snapshot), the density boundary, and one
``setSpeed`` per AV (holding its speed), i.e. the least any env must do per step. After a limit
block the env re-synchronises its per-agent state from the snapshot (untimed; histories restart).
Random actions crash and stop AVs, so the traffic degrades (at 100 % AVs about a quarter of
them remain): the env is reset (untimed) every ``--env-episode`` seconds of simulated time, and
a second policy ``keep`` (follow, zero steering and accel_brake) keeps the full traffic, the
load the target refers to. Reported per penetration: medians over block pairs of
ms/step, steps/s, agent-steps/s (agents = AVs in the network), the limit's ms/step and the ratio
env/limit (target ≤ 2). A separate profiling pass prints where an env step's time goes
(exclusive time per stage).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mixed_traffic.config import EnvConfig
from mixed_traffic.world.backend import SumoBackend
from mixed_traffic.world.boundary import PeriodicBoundary
from mixed_traffic.world.registry import load_scenario, make_demand, sumo_args, write_demand

DENSITIES = (60.0, 120.0, 180.0)
TARGET_OVERHEAD = 0.30
PENETRATIONS = (0.2, 0.5, 1.0)
TARGET_ENV_RATIO = 2.0


@dataclass
class SnapshotResult:
    density: float
    """Target density [veh/km]."""
    raw_ms: float
    """Median over blocks of the bare simulationStep [ms/step]."""
    step_ms: float
    """Median over blocks of backend.step() [ms/step]."""
    ratio: float
    """Median over block pairs of step / raw [-]."""
    us_per_vehicle: float
    """Median over block pairs of (step - raw) / vehicles: snapshot cost per vehicle [µs]."""
    vehicles: float
    """Mean vehicles in the network."""
    blocks: int


def start_straight(
    density: float, backend_kind: str = "libsumo", seed: int = 0, episode_length: float = 3600.0
) -> tuple[SumoBackend, PeriodicBoundary]:
    """A running ``straight`` simulation at ``density`` with its periodic boundary (sublane on)."""
    cfg = EnvConfig(
        scenario="straight", density=density, penetration=0.0, seed=seed,
        episode_length=episode_length, backend=backend_kind,
    )  # fmt: skip
    sc = load_scenario(cfg.scenario)
    hd = sc.hdmap
    demand = make_demand(sc, cfg, np.random.default_rng(seed))
    route_file = Path(tempfile.mkdtemp(prefix="mixed_traffic_bench_")) / "demand.rou.xml"
    write_demand(demand, cfg, route_file)
    backend = SumoBackend(cfg.backend, cfg.second_instance)
    backend.set_lane_table(hd.lane_ids, hd.lane_edge)
    backend.start(sumo_args(sc, cfg, route_file, seed=seed))
    boundary = PeriodicBoundary.for_demand(sc, demand, cfg.vehicle, cfg.step_length, False)
    return backend, boundary


def bench_snapshot_density(
    density: float, steps: int, block: int = 20, warm: int = 100, backend_kind: str = "libsumo"
) -> SnapshotResult:
    """Alternate raw/step blocks of ``block`` steps for ``steps`` timed steps in total."""
    backend, boundary = start_straight(density, backend_kind)
    clock = time.perf_counter
    try:
        for _ in range(warm):
            boundary.step(backend.step(), backend)
        raw_blocks: list[float] = []
        step_blocks: list[float] = []
        n_veh: list[int] = []
        veh_blocks: list[float] = []
        n_blocks = max(2, steps // block) // 2 * 2
        for b in range(n_blocks):
            timed = 0.0
            if b % 2 == 0:
                for _ in range(block):
                    t0 = clock()
                    backend.raw_step()
                    timed += clock() - t0
                    snap = backend.collect()
                    boundary.step(snap, backend)
                raw_blocks.append(timed / block)
            else:
                for _ in range(block):
                    t0 = clock()
                    snap = backend.step()
                    timed += clock() - t0
                    boundary.step(snap, backend)
                    n_veh.append(snap.n)
                step_blocks.append(timed / block)
                veh_blocks.append(float(np.mean(n_veh[-block:])))
    finally:
        backend.close()
    pairs = list(zip(raw_blocks, step_blocks, veh_blocks))
    return SnapshotResult(
        density=density,
        raw_ms=statistics.median(raw_blocks) * 1e3,
        step_ms=statistics.median(step_blocks) * 1e3,
        ratio=statistics.median(s / r for r, s, _ in pairs),
        us_per_vehicle=statistics.median((s - r) * 1e6 / max(v, 1.0) for r, s, v in pairs),
        vehicles=float(np.mean(n_veh)),
        blocks=n_blocks,
    )


def section_snapshot(args: argparse.Namespace) -> list[SnapshotResult]:
    """Raw simulationStep vs backend step()+snapshot on straight at each density."""
    print(
        f"snapshot: straight, sublane on, {args.backend}, {args.steps} timed steps per density "
        f"in alternating blocks of {args.block} (median of blocks)"
    )
    head = f"{'veh/km':>7} {'vehicles':>9} {'raw ms':>8} {'step ms':>8} {'ratio':>6} {'us/veh':>7}  target"
    print(head)
    print("-" * len(head))
    results = []
    for density in args.densities:
        r = bench_snapshot_density(density, args.steps, args.block, backend_kind=args.backend)
        ok = "ok" if r.ratio <= 1 + TARGET_OVERHEAD else f"MISSED (> {1 + TARGET_OVERHEAD:.2f})"
        print(
            f"{r.density:>7.0f} {r.vehicles:>9.0f} {r.raw_ms:>8.3f} {r.step_ms:>8.3f} "
            f"{r.ratio:>6.3f} {r.us_per_vehicle:>7.2f}  {ok}",
            flush=True,
        )
        results.append(r)
    return results


@dataclass
class EnvResult:
    policy: str
    """``random`` or ``keep`` (see ``_random_actions``)."""
    penetration: float
    """AV share [-]."""
    env_ms: float
    """Median over blocks of env.step [ms/step]."""
    limit_ms: float
    """Median over blocks of the physical limit [ms/step]."""
    ratio: float
    """Median over block pairs of env / limit [-]."""
    agents: float
    """Mean AVs in the network during env blocks (the agents that act)."""
    vehicles: float
    """Mean vehicles in the network during env blocks."""
    agent_steps_per_s: float
    """Median over env blocks of agents·steps / s."""
    blocks: int

    @property
    def steps_per_s(self) -> float:
        return 1e3 / self.env_ms


def _random_actions(
    env, obs: dict, space, rng: np.random.Generator, policy: str = "random"
) -> dict:
    """Actions for every live agent. ``random``: decision uniform over the allowed ones, params
    uniform in the Box. ``keep``: follow (or the allowed decision) with zero steering and
    accel_brake, i.e. hold lane and speed, so the traffic keeps its density."""
    box = space["params"]
    out = {}
    if policy == "keep":
        zero = np.zeros(box.shape, np.float32)
        for a in env.agents:
            mask = obs[a]["action_mask"]
            out[a] = {"decision": 1 if mask[1] else int(np.flatnonzero(mask)[0]), "params": zero}
        return out
    for a in env.agents:
        allowed = np.flatnonzero(obs[a]["action_mask"])
        out[a] = {
            "decision": int(allowed[rng.integers(len(allowed))]),
            "params": rng.uniform(box.low, box.high).astype(np.float32),
        }
    return out


def _resync(env) -> dict:
    """Rebuild the env's per-agent state from the backend's current snapshot after a limit block
    (agents that left are finished, every AV in the network is (re)admitted); the observations."""
    snap = env._last_limit_snap
    env._tls = dict(zip(env._perception.tls_ids, env._backend.tls_states(env._perception.tls_ids)))
    index = snap.index_of()
    env._finished.update(a for a in env.agents if a not in index)
    env._controller.reset()
    env.agents = [] if not env.config.fixed_fleet else env.agents
    return env._start_from(snap)


def _limit_step(env) -> float:
    """One physical-limit step on the env's simulation; returns its time [s]."""
    backend, clock = env._backend, time.perf_counter
    t0 = clock()
    snap = backend.step()
    env._boundary.step(snap, backend)
    av = np.flatnonzero(snap.is_av)
    backend.set_speeds([snap.ids[i] for i in av], snap.speed[av])
    dt = clock() - t0
    env._last_limit_snap = snap
    return dt


def _make_env(penetration: float, density: float, episode: float, seed: int):
    from mixed_traffic.env import parallel_env

    return parallel_env(
        scenario="straight", density=density, penetration=penetration, seed=seed,
        episode_length=episode,
    )  # fmt: skip


def bench_env_penetration(
    penetration: float, density: float, steps: int, block: int = 20, warm: int = 50,
    episode: float = 40.0, seed: int = 0, policy: str = "random",
) -> EnvResult:  # fmt: skip
    """Alternate (env, limit) block pairs of ``block`` steps until ``steps`` env steps are timed."""
    env = _make_env(penetration, density, episode, seed)
    rng = np.random.default_rng(seed)
    space = env.action_space(None)
    clock = time.perf_counter
    env_blocks: list[float] = []
    limit_blocks: list[float] = []
    rates: list[float] = []
    n_agents: list[int] = []
    n_veh: list[int] = []
    episode_steps = int(round(episode / env.config.step_length))
    try:
        k = 0
        while len(env_blocks) * block < steps:
            obs, _ = env.reset(seed=seed + k)
            k += 1
            done = 0
            for _ in range(warm):
                obs, *_ = env.step(_random_actions(env, obs, space, rng, policy))
                done += 1
            while done + 2 * block < episode_steps and len(env_blocks) * block < steps:
                timed, agent_steps = 0.0, 0
                for _ in range(block):
                    act = _random_actions(env, obs, space, rng, policy)
                    live = int(env._snap.is_av.sum())
                    t0 = clock()
                    obs, *_ = env.step(act)
                    timed += clock() - t0
                    agent_steps += live
                    n_agents.append(live)
                    n_veh.append(env._snap.n)
                env_blocks.append(timed / block)
                rates.append(agent_steps / timed)
                limit_blocks.append(sum(_limit_step(env) for _ in range(block)) / block)
                obs = _resync(env)
                done += 2 * block
    finally:
        env.close()
    return EnvResult(
        policy=policy,
        penetration=penetration,
        env_ms=statistics.median(env_blocks) * 1e3,
        limit_ms=statistics.median(limit_blocks) * 1e3,
        ratio=statistics.median(e / max(lim, 1e-12) for e, lim in zip(env_blocks, limit_blocks)),
        agents=float(np.mean(n_agents)),
        vehicles=float(np.mean(n_veh)),
        agent_steps_per_s=statistics.median(rates),
        blocks=len(env_blocks),
    )


#: Stages of ``MixedTrafficEnv.step`` timed by ``profile_env_stages`` (exclusive times).
STAGES = (
    ("action validation", "stack_actions"), ("control", "_control"), ("SUMO step", "backend.step"),
    ("boundary+flow+lights", "_advance"), ("perception", "_sense"), ("events", "_events"),
    ("rewards", "_rewards"), ("metrics", "_record"), ("memory", "_remember"),
    ("observation", "builder.build"), ("dict packing", "_observe|_finish"),
)  # fmt: skip


def profile_env_stages(
    penetration: float, density: float, steps: int, warm: int = 50, episode: float = 40.0,
    seed: int = 0, policy: str = "random",
) -> tuple[dict[str, float], float]:  # fmt: skip
    """Exclusive ms/step of each stage of env.step (instrumented pass), and the total ms/step."""
    import mixed_traffic.env.parallel as env_mod

    env = _make_env(penetration, density, episode, seed)
    rng = np.random.default_rng(seed)
    space = env.action_space(None)
    clock = time.perf_counter
    acc: dict[str, float] = {}
    stack: list[float] = []  # child time accumulated per open frame

    def timed(label: str, fn):
        def wrapper(*a, **kw):
            stack.append(0.0)
            t0 = clock()
            try:
                return fn(*a, **kw)
            finally:
                dt = clock() - t0
                child = stack.pop()
                acc[label] = acc.get(label, 0.0) + dt - child
                if stack:
                    stack[-1] += dt

        return wrapper

    saved = env_mod.stack_actions, env_mod.to_physical
    env_mod.stack_actions = timed("stack_actions", env_mod.stack_actions)
    env_mod.to_physical = timed("stack_actions", env_mod.to_physical)
    try:
        for name in ("_control", "_advance", "_sense", "_events", "_rewards", "_record",
                     "_remember", "_observe", "_finish"):  # fmt: skip
            label = "_observe|_finish" if name in ("_observe", "_finish") else name
            setattr(env, name, timed(label, getattr(env, name)))
        env._backend.step = timed("backend.step", env._backend.step)
        env._builder.build = timed("builder.build", env._builder.build)
        total, n, k = 0.0, 0, 0
        episode_steps = int(round(episode / env.config.step_length))
        while n < steps:
            obs, _ = env.reset(seed=seed + k)
            k += 1
            for _ in range(warm):
                obs, *_ = env.step(_random_actions(env, obs, space, rng, policy))
            acc.clear()
            for _ in range(min(episode_steps - warm - 1, steps - n)):
                act = _random_actions(env, obs, space, rng, policy)
                t0 = clock()
                obs, *_ = env.step(act)
                total += clock() - t0
                n += 1
            break  # one episode is enough for the shares
    finally:
        env_mod.stack_actions, env_mod.to_physical = saved
        env.close()
    per = {stage: acc.get(key, 0.0) * 1e3 / n for stage, key in STAGES}
    per["other (step glue)"] = total * 1e3 / n - sum(per.values())
    return per, total * 1e3 / n


def section_env(args: argparse.Namespace) -> list[EnvResult]:
    """env.step with random actions vs the physical limit on straight, per penetration."""
    print(
        f"env: straight {args.env_density:.0f} veh/km, sublane on, libsumo, random masked "
        f"actions, {args.env_steps} timed env steps per penetration in alternating (env, limit) "
        f"blocks of {args.block} (medians over blocks; reset every {args.env_episode:.0f} s)"
    )
    head = (
        f"{'policy':>6} {'pen':>5} {'AVs':>6} {'veh':>6} {'env ms':>8} {'steps/s':>8} {'agent-st/s':>11} "
        f"{'limit ms':>9} {'ratio':>6}  target"
    )
    print(head)
    print("-" * len(head))
    results = []
    for policy, p in [(pol, p) for pol in args.env_policy for p in args.penetrations]:
        r = bench_env_penetration(
            p, args.env_density, args.env_steps, args.block, episode=args.env_episode,
            policy=policy,
        )  # fmt: skip
        ok = "ok" if r.ratio <= TARGET_ENV_RATIO else f"MISSED (> {TARGET_ENV_RATIO:.0f}x)"
        print(
            f"{r.policy:>6} {r.penetration:>5.2f} {r.agents:>6.1f} {r.vehicles:>6.1f} {r.env_ms:>8.3f} "
            f"{r.steps_per_s:>8.0f} {r.agent_steps_per_s:>11.0f} {r.limit_ms:>9.3f} "
            f"{r.ratio:>6.2f}  {ok}",
            flush=True,
        )
        results.append(r)
    p, policy = max(args.penetrations), args.env_policy[-1]
    per, total = profile_env_stages(p, args.env_density, min(args.env_steps, 300),
                                    episode=args.env_episode, policy=policy)  # fmt: skip
    print(f"\nstage breakdown, {policy} policy, penetration {p:.2f} (instrumented pass, exclusive ms/step, "
          f"total {total:.3f} ms/step incl. instrumentation):")  # fmt: skip
    for stage, ms in per.items():
        print(f"  {stage:<22} {ms:>7.3f} ms  {100 * ms / total:>5.1f} %")
    return results


def section_inference(args: argparse.Namespace) -> float:
    """AvgIT: AUTO's batched forward (actor + critic + masked selection) per decision, 128
    agents on one core, observations already built (paper: 8.96 ms per decision on a GPU)."""
    from agents.bench_inference import avg_inference_us

    us = avg_inference_us(n_agents=128, threads=1)
    print(f"inference: AUTO batched forward, 128 agents, 1 thread: {us:.1f} us per decision "
          f"(target <= 20 us; CPU time, best of 7)")  # fmt: skip
    sm = avg_inference_us(n_agents=128, threads=1, safety=True)
    print(f"inference: the same plus the safety module (ACC-LC checks): {sm:.1f} us per decision")
    return us


#: Section name -> function(args). Other modules' sections are registered here.
SECTIONS: dict[str, Callable[[argparse.Namespace], object]] = {
    "snapshot": section_snapshot,
    "env": section_env,
    "inference": section_inference,
}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m mixed_traffic.bench",
        description="Speed benchmarks of the simulation stack.",
    )
    p.add_argument(
        "--section", choices=sorted(SECTIONS), nargs="+", default=sorted(SECTIONS),
        help="sections to run (default: all)",
    )  # fmt: skip
    p.add_argument(
        "--steps", type=int, default=2000, help="timed steps per density (default: 2000)"
    )
    p.add_argument(
        "--block", type=int, default=20, help="steps per alternating block (default: 20)"
    )
    p.add_argument(
        "--densities", type=float, nargs="+", default=list(DENSITIES), metavar="K",
        help="densities [veh/km] (default: 60 120 180)",
    )  # fmt: skip
    p.add_argument(
        "--penetrations", type=float, nargs="+", default=list(PENETRATIONS), metavar="P",
        help="env section: AV penetrations (default: 0.2 0.5 1.0)",
    )  # fmt: skip
    p.add_argument(
        "--env-policy", choices=("random", "keep"), nargs="+", default=["random", "keep"],
        help="env section: action policies (default: both; see _random_actions)",
    )  # fmt: skip
    p.add_argument(
        "--env-density", type=float, default=120.0, help="env section: veh/km (default: 120)"
    )
    p.add_argument(
        "--env-steps", type=int, default=1000,
        help="env section: timed env steps per penetration (default: 1000)",
    )  # fmt: skip
    p.add_argument(
        "--env-episode", type=float, default=40.0,
        help="env section: simulated seconds between resets (default: 40)",
    )  # fmt: skip
    p.add_argument(
        "--backend", choices=("libsumo", "traci"), default="libsumo",
        help="SUMO binding (default: libsumo)",
    )  # fmt: skip
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.steps < 2 * args.block or args.block < 1:
        parser.error(f"--steps={args.steps} must be at least 2 x --block={args.block}")
    for name in args.section:
        SECTIONS[name](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
