"""The sensor stages' compiled kernels (``mixed_traffic.sensing.sensing_kernel``: weather
ranges and noise, LiDAR and GNSS features) against their numpy references on real SUMO states,
bit for bit, with the same random draws."""

from __future__ import annotations

import numpy as np
import pytest

from mixed_traffic import compiled
from mixed_traffic.sensing import camera, gnss, lidar, neighbours, noise, perception
from mixed_traffic.sensing.camera import NO_LIGHT
from mixed_traffic.sensing.frame import PerceptionFrame

from .conftest import random_episode

needs_numba = pytest.mark.skipif(compiled.numba is None, reason="numba is not installed")

CASES = [
    ("ring", 1 / 22, "normal", 80),
    ("straight", 0.5, "normal", 80),
    ("merge", 0.3, "normal", 100),
    ("urban", 0.3, "normal", 100),
    ("urban", 0.3, "fog", 100),
    ("urban", 0.3, "rain", 100),
]


def _same_bits(out: tuple, ref: tuple) -> None:
    """Equal dtypes, shapes and bits (``np.array_equal`` alone takes -0.0 for 0.0)."""
    assert len(out) == len(ref)
    for k, (x, y) in enumerate(zip(out, ref)):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape, k
        if x.dtype == np.float64:
            x, y = x.view(np.int64), y.view(np.int64)
        assert np.array_equal(x, y), k


def _arrays(f: PerceptionFrame) -> tuple:
    nb = f.neighbours
    return (nb.lane, nb.vehicle, nb.distance, nb.on_path, nb.path_geometry, f.vehicles, f.ego,
            f.light_state, f.light_dist, f.give_way)  # fmt: skip


def _both(monkeypatch, fn):
    """``fn`` with the numpy stage and with the kernel on the same inputs: (out, ref)."""
    monkeypatch.setattr(compiled, "ENABLED", False)
    ref = fn()
    monkeypatch.setattr(compiled, "ENABLED", True)
    return fn(), ref


@needs_numba
@pytest.mark.parametrize(("scenario", "penetration", "weather", "steps"), CASES[:4])
def test_neighbour_setup_kernel_equals_numpy(monkeypatch, scenario: str, penetration: float,
                                             weather: str, steps: int) -> None:  # fmt: skip
    """The neighbour search's inputs (lane sort, query lanes and positions, successors towards
    the route and SUMO's choices, predecessors), bit for bit; also without a route."""
    seen = {"calls": 0, "missing": 0, "routed": 0}
    setup = neighbours._setup

    def both(snap, hdmap, rows, next_edge, via):
        args = (snap, hdmap, rows)
        out, ref = _both(monkeypatch, lambda: setup(*args, None, None))
        _same_bits((*out[0], *out[1:]), (*ref[0], *ref[1:]))
        # SUMO's choices where lanes fan out are rare: also some other lane on every other agent
        other = np.where(np.arange(len(rows)) % 2 == 0, (rows * 7) % hdmap.n_lanes, -1)
        out, ref = _both(monkeypatch, lambda: setup(*args, next_edge, other))
        _same_bits((*out[0], *out[1:]), (*ref[0], *ref[1:]))
        out, ref = _both(monkeypatch, lambda: setup(*args, next_edge, via))
        _same_bits((*out[0], *out[1:]), (*ref[0], *ref[1:]))
        lanes, succ = ref[1], ref[3]
        seen["calls"] += 1
        seen["missing"] += int((lanes < 0).sum())
        seen["routed"] += int((succ != hdmap.lane_next[np.maximum(lanes, 0)]).sum())
        return out

    monkeypatch.setattr(neighbours, "_setup", both)
    random_episode(steps, scenario=scenario, penetration=penetration, weather=weather)
    assert seen["calls"] >= steps // 2 and seen["missing"] > 0, "the stage ran"
    if scenario == "urban":
        assert seen["routed"] > 0, (
            "some lane continues towards its route, not its primary successor"
        )


@needs_numba
@pytest.mark.parametrize(("scenario", "penetration", "weather", "steps"), CASES[:4])
def test_traffic_lights_kernel_equals_numpy(monkeypatch, scenario: str, penetration: float,
                                            weather: str, steps: int) -> None:  # fmt: skip
    """Every agent's next signal on each lane (state code and stop-line distance), bit for bit;
    also without a route (each lane's own way on) and for every light's string turned red."""
    seen = {"calls": 0, "lights": 0, "states": set()}

    def both(g, hd, snap, rows, lanes, next_edge, tls_states):
        for nxt, states in ((np.full_like(next_edge, -1), tls_states),
                            (next_edge, ["r" * len(t) for t in tls_states])):  # fmt: skip
            args = (g, hd, snap, rows, lanes, nxt, states)
            out, ref = _both(monkeypatch, lambda a=args: camera.traffic_lights(*a))
            _same_bits(out, ref)
        out, ref = _both(monkeypatch, lambda: camera.traffic_lights(g, hd, snap, rows, lanes,
                                                                    next_edge, tls_states))  # fmt: skip
        _same_bits(out, ref)
        seen["calls"] += 1
        seen["lights"] += int((ref[0] != NO_LIGHT).sum())
        seen["states"] |= set(np.unique(ref[0]).tolist())
        return out

    monkeypatch.setattr(perception, "traffic_lights", both)
    random_episode(steps, scenario=scenario, penetration=penetration, weather=weather)
    assert seen["calls"] >= steps // 2, "the stage ran"
    if scenario == "urban":
        assert seen["lights"] > 0 and len(seen["states"]) >= 3, "lights in several states"


@needs_numba
@pytest.mark.parametrize(("scenario", "penetration", "weather", "steps"), CASES)
def test_features_kernels_equal_numpy(monkeypatch, scenario: str, penetration: float,
                                      weather: str, steps: int) -> None:  # fmt: skip
    """Every agent's LiDAR vehicle features (leaders across the path included) and GNSS ego
    features, with random actions, bit for bit."""
    seen = {"calls": 0, "vehicles": 0, "on_path": 0}

    def vehicle_features(snap, rows, nb):
        out, ref = _both(monkeypatch, lambda: lidar.vehicle_features(snap, rows, nb))
        _same_bits((out,), (ref,))
        seen["vehicles"] += int((nb.vehicle >= 0).sum())
        seen["on_path"] += int(nb.on_path.sum())
        return out

    def ego_features(snap, hdmap, rows):
        out, ref = _both(monkeypatch, lambda: gnss.ego_features(snap, hdmap, rows))
        _same_bits((out,), (ref,))
        seen["calls"] += 1
        return out

    monkeypatch.setattr(perception, "vehicle_features", vehicle_features)
    monkeypatch.setattr(perception, "ego_features", ego_features)
    random_episode(steps, scenario=scenario, penetration=penetration, weather=weather)
    assert seen["calls"] >= steps // 2 and seen["vehicles"] > 0, "the stages ran"
    if scenario in ("urban", "merge"):
        assert seen["on_path"] > 0, "some leader was measured in the path's frame"


@needs_numba
@pytest.mark.parametrize(("scenario", "penetration", "weather", "steps"), CASES)
def test_noise_kernels_equal_numpy(monkeypatch, scenario: str, penetration: float,
                                   weather: str, steps: int) -> None:  # fmt: skip
    """The sensed frame (ranges, feature noise, misdetected lights), bit for bit on the same
    draws, the generator left in the same state; and ``within_range`` at the weather's ranges
    and at the nominal ones."""
    seen = {"calls": 0, "cut": 0, "lights": 0, "wrong": 0}

    def degrade(truth, w, sensors, rng):
        start = rng.bit_generator.state
        monkeypatch.setattr(compiled, "ENABLED", False)
        ref = noise.degrade(truth, w, sensors, rng)
        end = rng.bit_generator.state
        rng.bit_generator.state = start
        monkeypatch.setattr(compiled, "ENABLED", True)
        out = noise.degrade(truth, w, sensors, rng)
        assert rng.bit_generator.state == end, "the same draws"
        _same_bits(_arrays(out), _arrays(ref))
        for factors in ((w.lidar_range_factor, w.camera_range_factor), (1.0, 1.0)):
            cut, cut_ref = _both(
                monkeypatch, lambda f=factors: noise.within_range(truth, sensors, *f)
            )
            _same_bits(_arrays(cut), _arrays(cut_ref))
        cut = noise.within_range(truth, sensors, w.lidar_range_factor, w.camera_range_factor)
        seen["calls"] += 1
        seen["cut"] += int(((truth.neighbours.vehicle >= 0) & (cut.neighbours.vehicle < 0)).sum())
        seen["lights"] += int((cut.light_state != NO_LIGHT).sum())
        seen["wrong"] += int((ref.light_state != cut.light_state).sum())
        return out

    monkeypatch.setattr(perception, "degrade", degrade)
    random_episode(steps, scenario=scenario, penetration=penetration, weather=weather)
    assert seen["calls"] >= steps // 2, "the noise stage ran"
    if weather != "normal":
        assert seen["cut"] > 0, "some vehicle was beyond the sensed range"
    if scenario == "urban":
        assert seen["lights"] > 0 and seen["wrong"] > 0, "some light was misdetected"


@needs_numba
def test_sensing_kernel_warm_loads_the_specialisation_the_env_calls() -> None:
    """``warm()`` loads the specialisations a real step uses, so forked cells add none."""
    from mixed_traffic.sensing import sensing_kernel

    sensing_kernel.warm()
    random_episode(1, seed=0, policy="keep", scenario="urban", penetration=0.3)
    kernels = (sensing_kernel.degrade, sensing_kernel.vehicle_features,
               sensing_kernel.ego_features, sensing_kernel.lane_sort,
               sensing_kernel.query_lanes, sensing_kernel.traffic_lights)  # fmt: skip
    for kernel in kernels:
        assert len(kernel.signatures) == 1, kernel
