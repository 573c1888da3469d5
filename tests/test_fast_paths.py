"""Fast paths against their references on real SUMO states: compiled kernels
(``mixed_traffic.compiled``) against the numpy stages, and a training env without metrics
(``metrics=False``) against one that records them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mixed_traffic import compiled
from mixed_traffic.env import parallel_env, reward, traffic_terms
from mixed_traffic.experiments.bench_env import bench_actions
from mixed_traffic.sensing import neighbours, perception

from .conftest import random_episode

needs_numba = pytest.mark.skipif(compiled.numba is None, reason="numba is not installed")


def _equal(a: neighbours.Neighbours, b: neighbours.Neighbours) -> None:
    for name in ("lane", "vehicle", "distance", "on_path", "path_geometry"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and np.array_equal(x, y), name


@needs_numba
@pytest.mark.parametrize(
    ("scenario", "penetration", "steps"),
    [("ring", 1 / 22, 80), ("straight", 0.5, 80), ("merge", 0.3, 80), ("urban", 0.3, 120)],
)
def test_neighbour_kernel_equals_numpy(monkeypatch, scenario: str, penetration: float,
                                       steps: int) -> None:  # fmt: skip
    """Every agent's neighbours, with random lane changes and steering (vehicles side by side,
    straddling, junctions, successor and predecessor lanes), bit for bit."""
    calls = []

    def both(*args, **kw):
        monkeypatch.setattr(compiled, "ENABLED", False)
        ref = neighbours.find_neighbours(*args, **kw)
        monkeypatch.setattr(compiled, "ENABLED", True)
        out = neighbours.find_neighbours(*args, **kw)
        _equal(out, ref)
        calls.append(len(out.lane))
        return out

    monkeypatch.setattr(perception, "find_neighbours", both)
    random_episode(steps, scenario=scenario, penetration=penetration)
    assert sum(calls) > steps, "the search ran for the agents"


@needs_numba
@pytest.mark.parametrize(
    ("scenario", "penetration", "steps"),
    [("ring", 1 / 22, 80), ("ring", 0.5, 80), ("straight", 0.5, 80), ("merge", 0.3, 80),
     ("urban", 0.3, 100)],
)  # fmt: skip
def test_traffic_terms_kernel_equals_numpy(monkeypatch, scenario: str, penetration: float,
                                           steps: int) -> None:  # fmt: skip
    """Every agent's r5, r6 and r8 (the ring's loop, route windows across junctions, followers
    on the agent's lane index), with random actions, bit for bit; also with one follower and
    the other kind of r8 reference (a desired speed, or the lane limits), and with positions
    rounded to 5 m (followers at equal distances, vehicles at the windows' very ends)."""
    calls = []

    def run_both(cfg, hd, snap, rows, routes, route_len, ring, desired):
        monkeypatch.setattr(compiled, "ENABLED", False)
        ref = traffic_terms.traffic_terms(cfg, hd, snap, rows, routes, route_len, ring, desired)
        monkeypatch.setattr(compiled, "ENABLED", True)
        out = traffic_terms.traffic_terms(cfg, hd, snap, rows, routes, route_len, ring, desired)
        assert list(out) == list(ref) == list(traffic_terms.TRAFFIC_TERMS)
        for name in ref:
            x, y = out[name], ref[name]
            # the bits: np.array_equal alone takes -0.0 for 0.0
            assert x.dtype == y.dtype and np.array_equal(x.view(np.int64), y.view(np.int64)), name
        return out

    def both(cfg, hd, snap, rows, routes, route_len, ring, desired):
        other = (replace(cfg, followers=1), hd, snap, rows, routes, route_len, ring)
        # the other kind of reference, and one that differs by lane (as copies' rings do)
        run_both(*other, np.zeros_like(desired) if desired.any() else np.full_like(desired, 20.0))
        run_both(*other, np.linspace(0.0, 25.0, len(desired)))
        ties = replace(snap, lane_pos=np.round(snap.lane_pos / 5.0) * 5.0)
        run_both(replace(cfg, followers=2), hd, ties, rows, routes, route_len, ring, desired)
        out = run_both(cfg, hd, snap, rows, routes, route_len, ring, desired)
        calls.append(len(out["r5_local_speed"]))
        return out

    monkeypatch.setattr(reward, "traffic_terms", both)
    random_episode(steps, scenario=scenario, penetration=penetration)
    assert sum(calls) >= steps, "the terms were computed for the agents at every step"


@needs_numba
def test_warm_loads_the_kernel_the_env_calls() -> None:
    """``warm()`` (the sweep's fork server calls it) loads the specialisation a real step uses,
    so forked cells add none."""
    from mixed_traffic.env import traffic_terms_kernel
    from mixed_traffic.sensing import neighbours_kernel

    neighbours_kernel.warm()
    traffic_terms_kernel.warm()
    random_episode(1, seed=0, policy="keep", scenario="ring", penetration=1 / 22)
    assert len(neighbours_kernel.search.signatures) == 1
    assert len(traffic_terms_kernel.terms.signatures) == 1


@needs_numba
def test_kernels_switch_off() -> None:
    """``MIXED_TRAFFIC_KERNELS=numpy`` at a process's start selects the reference stages."""
    import os
    import subprocess
    import sys

    probe = "from mixed_traffic import compiled; print(compiled.enabled())"
    for value, expected in (("numpy", "False"), ("numba", "True")):
        env = dict(os.environ, **{compiled.SWITCH: value})
        out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True)
        assert out.stdout.strip() == expected, (value, out.stderr[-300:])


def _episode(metrics: bool, **kw) -> tuple[list, parallel_env]:
    """Every step's (observations, rewards, terminations, truncations, infos) of one episode
    with random actions, and the closed env."""
    env = parallel_env(**kw, metrics=metrics)
    rng, steps = np.random.default_rng(1), []
    obs, _ = env.reset(seed=kw["seed"])
    while env.agents:
        out = env.step(bench_actions(env, obs, env.action_space(None), rng))
        obs = out[0]
        steps.append(out)
    env.close()
    return steps, env


@pytest.mark.parametrize(("scenario", "penetration"), [("ring", 1 / 22), ("straight", 0.5)])
def test_env_without_metrics_steps_the_same(scenario: str, penetration: float) -> None:
    """``metrics=False`` changes no observation, reward or info (but ``"episode"``), to the
    episode's end; its ``episode_metrics()`` names why it has none."""
    kw = dict(scenario=scenario, penetration=penetration, seed=5, episode_length=12.0)
    ref, _ = _episode(True, **kw)
    fast, env = _episode(False, **kw)
    assert len(ref) == len(fast) >= 100
    for (obs, *dicts, infos), (obs2, *dicts2, infos2) in zip(ref, fast):
        assert dicts == dicts2 and list(obs) == list(obs2)
        for a in obs:
            assert all(np.array_equal(obs[a][k], obs2[a][k]) for k in obs[a])
            assert {k: v for k, v in infos[a].items() if k != "episode"} == infos2[a]
    assert "episode" in next(iter(ref[-1][-1].values()))
    with pytest.raises(RuntimeError, match="metrics=False"):
        env.episode_metrics()
