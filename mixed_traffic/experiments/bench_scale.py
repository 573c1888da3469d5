"""Section ``scale`` of ``python -m mixed_traffic.bench``: how far one simulation scales.

* **AVs at real time.** A straight road of ``--scale-lanes`` lanes at ``--scale-density``
  veh/km per lane, all AVs, driven by AUTO (batched inference, torch on one thread) through the
  whole pipeline; its length grows along ``--scale-avs`` so that it holds that many AVs. Each
  size runs ``--scale-steps`` timed env steps (policy included) after 5 s untimed; its real-time
  factor is simulated over wall time. The largest size at ≥ 1× real time is reported (the
  ladder stops at the first size below it).
* **A city.** A generated ``--city-grid`` x ``--city-grid`` signalised grid (netgenerate, 2
  lanes, 150 m blocks) filled at ``--city-density`` veh/km per lane, ``--city-penetration`` of
  them AVs under AUTO, runs one ``--city-episode`` s episode; then the same episode with SUMO
  driving everyone gives the ratio.

Both networks are generated with SUMO's own tools and cached by their parameters.
"""

from __future__ import annotations

import argparse
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

from mixed_traffic.config import EnvConfig
from mixed_traffic.paths import cache_dir
from mixed_traffic.world.backend import binary
from mixed_traffic.world.network import SPLIT_ARGS, build_network

AV_LADDER = (250, 500, 1000, 1500, 2000, 2100, 2250, 2500, 3000, 4000)
"""Rungs of the ladder [AVs the road is sized for]; a rung reports the AVs actually in the
network, about 96 % of its size (2,100 is the first rung with 2,000 AVs in it)."""
CITY_BLOCK = 150.0
"""Block length of the city grid [m]."""
CITY_LANES = 2
"""Lanes of every city street (each direction)."""


@dataclass
class ScaleResult:
    max_avs_realtime: int
    """Largest AV count run at >= 1x real time on the long road (0: none)."""
    ladder: list[dict]
    """Per size: AVs, vehicles, road km, real-time factor."""
    city_vehicles: int
    """Distinct vehicles that drove in the city episode (the env's ``vehicles_seen``)."""
    city_completed: bool
    """The city episode ran to its end."""
    city_wall_s: float
    """Wall time of the city episode, reset included [s]."""
    city_sumo_s: float
    """The same episode with SUMO driving everyone [s]."""

    def record(self) -> dict:
        return {"section": "scale", "max_avs_realtime": self.max_avs_realtime,
                "city_vehicles": self.city_vehicles, "city_completed": self.city_completed,
                "city_wall_s": round(self.city_wall_s, 1), "city_sumo_s": round(self.city_sumo_s, 1),
                "city_ratio": round(self.city_wall_s / self.city_sumo_s, 3), "ladder": self.ladder}  # fmt: skip


def long_road(length_km: float, lanes: int) -> Path:
    """A straight ``lanes``-lane 100 km/h road of ``length_km``, cut into short edges by
    netconvert (``SPLIT_ARGS``; cached)."""
    folder = cache_dir("bench-scale") / f"road-{length_km:.3f}km-{lanes}l"
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "netconvert.args").write_text(" ".join(SPLIT_ARGS) + "\n")
    (folder / "road.nod.xml").write_text(
        f'<nodes>\n  <node id="a" x="0" y="0"/>\n  <node id="b" x="{length_km * 1000:.1f}" y="0"/>\n</nodes>\n'
    )
    (folder / "road.edg.xml").write_text(
        f'<edges>\n  <edge id="road" from="a" to="b" numLanes="{lanes}" speed="27.78"/>\n</edges>\n'
    )
    return build_network(folder)


def city_grid(n: int) -> Path:
    """An ``n`` x ``n`` grid of ``CITY_LANES``-lane 50 km/h streets with traffic lights
    (netgenerate, cached)."""
    out = cache_dir("bench-scale") / f"grid-{n}x{n}.net.xml"
    if out.exists():
        return out
    tmp = out.with_suffix(".tmp.xml")
    cmd = [binary("netgenerate"), "--grid", f"--grid.number={n}", f"--grid.length={CITY_BLOCK}",
           f"--default.lanenumber={CITY_LANES}", "--default.speed=13.89", "--tls.guess",
           "--no-turnarounds", "--no-warnings", "--output-file", str(tmp)]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0 or not tmp.exists():
        raise ValueError(f"netgenerate failed: {proc.stderr.strip() or proc.stdout.strip()}")
    tmp.replace(out)
    return out


def _env_and_policy(config: EnvConfig, policy: str):
    """The env of ``config`` and the runner's batched policy (None: SUMO drives the AVs)."""
    from mixed_traffic.env.parallel import MixedTrafficEnv
    from mixed_traffic.experiments.runner import batch_policy, sumo_drives

    env = MixedTrafficEnv(config=config, sumo_drives_avs=sumo_drives(policy))
    return env, batch_policy(policy, config, None, env.scenario.family)


def _step(env, agent) -> None:
    from mixed_traffic.experiments.runner import decide

    env.step_batch(*decide(env, agent)[:2])


def realtime_factor(avs: int, args: argparse.Namespace) -> dict:
    """One size of the ladder: AUTO drives ``avs`` AVs; its real-time factor."""
    km = avs / (args.scale_density * args.scale_lanes)
    warm, timed = 50, args.scale_steps
    cfg = EnvConfig(scenario=str(long_road(km, args.scale_lanes)), penetration=1.0,
                    density=args.scale_density * args.scale_lanes, seed=0,
                    episode_length=(warm + timed + 1) * EnvConfig.step_length)  # fmt: skip
    env, agent = _env_and_policy(cfg, "auto")
    try:
        env.reset(seed=0, options={"allow_no_agents": True})
        for _ in range(warm):
            _step(env, agent)
        n = len(env.agents)
        t0 = time.perf_counter()
        for _ in range(timed):
            _step(env, agent)
        wall = time.perf_counter() - t0
    finally:
        env.close()
    factor = timed * cfg.step_length / wall
    print(f"scale: {n} AVs on {km:.1f} km x {args.scale_lanes} lanes: {1000 * wall / timed:.0f} "
          f"ms per step, {factor:.2f}x real time", flush=True)  # fmt: skip
    return {"avs": n, "road_km": round(km, 2), "ms_per_step": round(1000 * wall / timed, 1),
            "realtime_factor": round(factor, 3)}  # fmt: skip


def city_episode(args: argparse.Namespace, policy: str) -> tuple[int, bool, float]:
    """(distinct vehicles, ran to the end, wall time [s]) of one city episode."""
    cfg = EnvConfig(scenario=str(city_grid(args.city_grid)), penetration=args.city_penetration,
                    density=args.city_density * CITY_LANES, seed=0, episode_length=args.city_episode)  # fmt: skip
    t0 = time.perf_counter()
    env, agent = _env_and_policy(cfg, policy)
    vehicles = 0
    try:
        env.reset(seed=0, options={"allow_no_agents": True})
        while env.sim_time < cfg.episode_length - 1e-9:
            _step(env, agent)
        vehicles, done = int(env.flow_diagnostics()["vehicles_seen"]), True
    except Exception as e:  # a city that fails is the finding; report it, do not crash the bench
        print(f"scale: the city episode under {policy} failed: {type(e).__name__}: {e}", flush=True)
        done = False
    finally:
        env.close()
    return vehicles, done, time.perf_counter() - t0


def section_scale(args: argparse.Namespace) -> list[ScaleResult]:
    import torch

    torch.set_num_threads(1)  # one core
    ladder = []
    for avs in args.scale_avs:
        ladder.append(realtime_factor(avs, args))
        if ladder[-1]["realtime_factor"] < 1.0:
            break
    fast = [r["avs"] for r in ladder if r["realtime_factor"] >= 1.0]
    vehicles, done, wall = city_episode(args, "auto")
    _, _, sumo = city_episode(args, "idm")
    result = ScaleResult(max(fast, default=0), ladder, vehicles, done, wall, sumo)
    print(f"scale: max AVs at >= 1x real time {result.max_avs_realtime} (target >= 2000); city "
          f"{args.city_grid}x{args.city_grid} grid, {vehicles} vehicles, {args.city_episode:g} s "
          f"episode {'completed' if done else 'FAILED'} in {wall:.0f} s, SUMO alone {sumo:.0f} s "
          f"(ratio {wall / sumo:.2f})", flush=True)  # fmt: skip
    return [result]
