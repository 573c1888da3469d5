"""Shared fixtures: a real SUMO simulation on the bundled straight scenario."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from mixed_traffic.config import EnvConfig
from mixed_traffic.world.backend import SumoBackend
from mixed_traffic.world.boundary import PeriodicBoundary
from mixed_traffic.world.demand import Demand, make_demand, write_demand
from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.registry import load_scenario
from mixed_traffic.world.scenario import Scenario, sumo_args


@dataclass
class Sim:
    config: EnvConfig
    scenario: Scenario
    hdmap: HDMap
    demand: Demand
    backend: SumoBackend
    boundary: PeriodicBoundary
    route_file: Path

    def step(self, n: int = 1):
        snap = None
        for _ in range(n):
            snap = self.backend.step()
            self.boundary.step(snap, self.backend)
        return snap


def start_sim(
    tmp_path: Path, kind: str = "libsumo", config: EnvConfig | None = None, **overrides
) -> Sim:
    """Start a real SUMO simulation of ``config`` (default ``EnvConfig(**overrides)``)."""
    defaults = {"density": 60.0, "penetration": 0.2, "episode_length": 60.0}
    cfg = config if config is not None else EnvConfig(**{**defaults, **overrides})
    sc = load_scenario(cfg.scenario)
    cfg = sc.configure(cfg)  # the scenario's defaults, as the env fills them in
    hd = sc.hdmap
    demand = make_demand(sc, cfg, np.random.default_rng(cfg.seed))
    rf = tmp_path / f"demand_{kind}.rou.xml"
    write_demand(demand, cfg, rf)
    backend = SumoBackend(kind, cfg.second_instance)
    backend.set_lane_table(hd.lane_ids, hd.lane_edge)
    backend.start(sumo_args(sc, cfg, rf, seed=cfg.seed))
    boundary = PeriodicBoundary.for_demand(sc, demand, cfg.human, cfg.step_length, cfg.fixed_fleet)
    return Sim(cfg, sc, hd, demand, backend, boundary, rf)


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[Sim]:
    s = start_sim(tmp_path)
    yield s
    s.backend.close()


#: (env kwargs, steps) of the episodes the step-stage kernel tests run, and their test ids.
STEP_CASES = [
    ({"scenario": "ring", "penetration": 1 / 22}, 150),
    ({"scenario": "straight", "penetration": 0.5, "density": 120.0}, 120),
    ({"scenario": "merge", "penetration": 0.3}, 150),
    ({"scenario": "urban", "penetration": 0.3}, 200),
]
STEP_IDS = [c[0]["scenario"] for c in STEP_CASES]


def random_episode(
    steps: int, seed: int = 3, action_seed: int = 0, end_metrics: bool = False,
    policy: str = "random", **env_kw,
) -> list:  # fmt: skip
    """Up to ``steps`` env steps of a real SUMO episode (``parallel_env(**env_kw)``, 60 s) with
    ``bench_actions``' ``policy`` (random actions seeded with ``action_seed``, or ``keep``),
    the env seeded with ``seed``: the episodes the kernel tests compare the compiled stages on.
    Returns every step's (obs, rewards, terminations, truncations, infos), then
    ``episode_metrics()`` with ``end_metrics``."""
    from mixed_traffic.env import parallel_env
    from mixed_traffic.experiments.bench_env import bench_actions

    env = parallel_env(seed=seed, episode_length=60.0, **env_kw)
    try:
        rng = np.random.default_rng(action_seed)
        obs, _ = env.reset(seed=seed)
        out = []
        for _ in range(steps):
            if not env.agents:
                break
            out.append(env.step(bench_actions(env, obs, env.action_space(None), rng, policy)))
            obs = out[-1][0]
        if end_metrics:
            out.append(env.episode_metrics())
    finally:
        env.close()
    return out


def same_bits(a, b, where: str = "") -> None:
    """``a`` and ``b`` equal in structure, types, dtypes and bits (-0.0 is not 0.0)."""
    assert type(a) is type(b), where
    if isinstance(a, dict):
        assert list(a) == list(b), where
        for k in a:
            same_bits(a[k], b[k], f"{where}/{k}")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            same_bits(x, y, f"{where}[{i}]")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, where
        if a.dtype == object:
            assert a.tolist() == b.tolist(), where
        else:
            assert a.tobytes() == b.tobytes(), where
    elif isinstance(a, float | np.floating):
        assert np.array(a).tobytes() == np.array(b).tobytes(), where
    else:
        assert a == b, where
