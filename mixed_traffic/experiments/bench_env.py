"""Benchmark section ``env`` (see ``bench``): ``MixedTrafficEnv.step`` with random actions (decision sampled under the
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
env/limit (target ≤ 1.3). The same rows on the 22-vehicle ``ring`` with one AV (its own
density; target ≤ 1.5) show the fixed per-step cost of small scenarios. A separate profiling pass prints where an env step's time goes
(exclusive time per stage).
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import dataclass

import numpy as np

PENETRATIONS = (0.2, 0.5, 1.0)
TARGET_ENV_RATIO = 1.3
"""Issue 25's target for env step / physical limit."""
RING_PENETRATION = 1 / 22
"""The ring row: 22 vehicles at the ring's own density, one of them an AV."""
TARGETS = {"straight": TARGET_ENV_RATIO, "ring": 1.5}
"""Issue 45's targets for env step / physical limit per scenario."""


@dataclass
class EnvResult:
    scenario: str
    """``straight`` (at ``--env-density``) or ``ring`` (22 vehicles, one AV)."""
    policy: str
    """``random`` or ``keep`` (see ``bench_actions``)."""
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

    def record(self) -> dict[str, float | str]:
        """The ``--json`` object (issue 25's keys first)."""
        return {
            "scenario": self.scenario, "env_policy": self.policy, "penetration": self.penetration,
            "ratio": self.ratio,
            "agent_steps_per_s": self.agent_steps_per_s, "ms_per_step": self.env_ms,
            "limit_ms_per_step": self.limit_ms, "agents": self.agents, "vehicles": self.vehicles,
            "blocks": self.blocks, "target_ratio": TARGETS[self.scenario],
        }  # fmt: skip


def bench_actions(env, obs: dict, space, rng: np.random.Generator, policy: str = "random") -> dict:
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


def _resync(env, snap) -> dict:
    """Rebuild the env's per-agent state from ``snap`` (the last limit step's) after a limit
    block (agents that left are finished, every AV in the network is (re)admitted); the
    observations."""
    table = env._table
    env._tls = dict(zip(env._perception.tls_ids, env._backend.tls_states(env._perception.tls_ids)))
    index = snap.index_of()
    table.finished.update(a for a in env.agents if a not in index)
    env._controller.reset()
    if not env.config.fixed_fleet:
        table.agents = []
    return env._start_from(snap)


def _limit_step(env) -> tuple[float, object]:
    """One physical-limit step on the env's simulation: its time [s] and snapshot."""
    backend, clock = env._backend, time.perf_counter
    t0 = clock()
    snap = backend.step()
    env._boundary.step(snap, backend)
    av = np.flatnonzero(snap.is_av)
    backend.set_speeds([snap.ids[i] for i in av], snap.speed[av])
    return clock() - t0, snap


def _limit_block(env, block: int) -> tuple[float, object]:
    """``block`` physical-limit steps, then the env re-synchronised; mean time per step [s]."""
    total, snap = 0.0, None
    for _ in range(block):
        dt, snap = _limit_step(env)
        total += dt
    return total / block, snap


def make_bench_env(penetration: float, density: float | None, episode: float, seed: int,
                   scenario: str = "straight"):  # fmt: skip
    """The benched env; ``density`` None: the scenario's own."""
    from mixed_traffic.env import parallel_env

    return parallel_env(
        scenario=scenario, density=density, penetration=penetration, seed=seed,
        episode_length=episode,
    )  # fmt: skip


def bench_env_penetration(
    penetration: float, density: float | None, steps: int, block: int = 20, warm: int = 50,
    episode: float = 40.0, seed: int = 0, policy: str = "random", scenario: str = "straight",
) -> EnvResult:  # fmt: skip
    """Alternate (env, limit) block pairs of ``block`` steps until ``steps`` env steps are timed."""
    env = make_bench_env(penetration, density, episode, seed, scenario)
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
                obs, *_ = env.step(bench_actions(env, obs, space, rng, policy))
                done += 1
            while done + 2 * block < episode_steps and len(env_blocks) * block < steps:
                timed, agent_steps = 0.0, 0
                for _ in range(block):
                    act = bench_actions(env, obs, space, rng, policy)
                    live = int(env._snap.is_av.sum())
                    t0 = clock()
                    obs, *_ = env.step(act)
                    timed += clock() - t0
                    agent_steps += live
                    n_agents.append(live)
                    n_veh.append(env._snap.n)
                env_blocks.append(timed / block)
                rates.append(agent_steps / timed)
                limit_ms, snap = _limit_block(env, block)
                limit_blocks.append(limit_ms)
                obs = _resync(env, snap)
                done += 2 * block
    finally:
        env.close()
    return EnvResult(
        scenario=scenario,
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

    env = make_bench_env(penetration, density, episode, seed)
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
                obs, *_ = env.step(bench_actions(env, obs, space, rng, policy))
            acc.clear()
            for _ in range(min(episode_steps - warm - 1, steps - n)):
                act = bench_actions(env, obs, space, rng, policy)
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
    """env.step vs the physical limit on straight per penetration, and on the ring (one AV)."""
    print(
        f"env: straight {args.env_density:.0f} veh/km and the 22-vehicle ring with one AV, "
        f"sublane on, libsumo, {args.env_steps} timed env steps per row in alternating "
        f"(env, limit) blocks of {args.block} (medians over blocks; reset every "
        f"{args.env_episode:.0f} s)"
    )  # fmt: skip
    head = (
        f"{'scenario':>8} {'policy':>6} {'pen':>5} {'AVs':>6} {'veh':>6} {'env ms':>8} "
        f"{'steps/s':>8} {'agent-st/s':>11} {'limit ms':>9} {'ratio':>6}  target"
    )  # fmt: skip
    print(head)
    print("-" * len(head))
    rows = [
        (pol, "straight", p, args.env_density) for pol in args.env_policy for p in args.penetrations
    ]
    rows += [(pol, "ring", RING_PENETRATION, None) for pol in args.env_policy]
    results = []
    for policy, scenario, p, density in rows:
        r = bench_env_penetration(
            p, density, args.env_steps, args.block, episode=args.env_episode, policy=policy,
            scenario=scenario,
        )  # fmt: skip
        target = TARGETS[scenario]
        ok = "ok" if r.ratio <= target else f"MISSED (> {target}x)"
        print(
            f"{r.scenario:>8} {r.policy:>6} {r.penetration:>5.2f} {r.agents:>6.1f} "
            f"{r.vehicles:>6.1f} {r.env_ms:>8.3f} {r.steps_per_s:>8.0f} "
            f"{r.agent_steps_per_s:>11.0f} {r.limit_ms:>9.3f} {r.ratio:>6.2f}  {ok}",
            flush=True,
        )  # fmt: skip
        results.append(r)
    p, policy = max(args.penetrations), args.env_policy[-1]
    per, total = profile_env_stages(p, args.env_density, min(args.env_steps, 300),
                                    episode=args.env_episode, policy=policy)  # fmt: skip
    print(f"\nstage breakdown, {policy} policy, penetration {p:.2f} (instrumented pass, exclusive ms/step, "
          f"total {total:.3f} ms/step incl. instrumentation):")  # fmt: skip
    for stage, ms in per.items():
        print(f"  {stage:<22} {ms:>7.3f} ms  {100 * ms / total:>5.1f} %")
    return results
