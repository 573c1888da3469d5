"""Edie's sums on the space-time grid and the wave-speed estimate (pure math, hand values)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mixed_traffic.env.space_time import SpaceTimeField, smoothed_speed, wave_speed


def _travelling_wave(c_kmh: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(dist, time) of a 1 km x 200 s grid whose speed 10 + 3 f(t - x/c) [m/s] carries a
    smooth random pattern f (std 1, correlation time 8 s) along the road at ``c_kmh``."""
    s = np.arange(-300.0, 400.0)  # time along the characteristic [s]
    kernel = np.exp(-0.5 * (np.arange(-30, 31) / 8.0) ** 2)
    noise = np.random.default_rng(seed).normal(size=len(s))
    f = np.convolve(noise, kernel / np.linalg.norm(kernel), mode="same")
    t = np.arange(200)[:, None] + 0.5
    x = (np.arange(100)[None, :] + 0.5) * 10.0
    v = 10.0 + 3.0 * np.interp(t - x / (c_kmh / 3.6), s, f)
    time = np.full(v.shape, 2.0)  # two vehicle-seconds in every cell
    return v * time, time


@pytest.mark.parametrize("c_kmh", [-12.0, -18.0, -25.0, -35.0])
def test_wave_speed_recovers_an_upstream_wave(c_kmh: float) -> None:
    dist, time = _travelling_wave(c_kmh)
    assert wave_speed(dist, time, 10.0, 1.0) == pytest.approx(c_kmh, rel=0.03)


@pytest.mark.parametrize("c_kmh", [30.0, 80.0, -60.0, -120.0])
def test_patterns_that_no_wave_can_carry_have_no_wave_speed(c_kmh: float) -> None:
    """Downstream: the vehicles carry their own speed variations (at 30 km/h in a queue, 80 in
    free flow); upstream faster than MAX_WAVE_SPEED (42 km/h): no congested branch is so steep."""
    dist, time = _travelling_wave(c_kmh)
    assert math.isnan(wave_speed(dist, time, 10.0, 1.0))


@pytest.mark.parametrize("seed", range(5))
def test_a_wave_slower_than_the_lags_searched_has_no_wave_speed(seed: int) -> None:
    """At -3 km/h the lags (36 to 84 s) lie beyond those searched (22 to 51 s): neither the edge
    of the search nor a spurious peak of the correlation is taken for the wave."""
    dist, time = _travelling_wave(-3.0, seed)
    assert math.isnan(wave_speed(dist, time, 10.0, 1.0))


def test_flat_or_empty_fields_have_no_waves() -> None:
    rng = np.random.default_rng(0)
    flat = 10.0 + rng.normal(0.0, 0.1, (200, 100))
    assert math.isnan(wave_speed(flat, np.ones_like(flat), 10.0, 1.0))
    dist, time = _travelling_wave(-15.0)
    time[:, ::2] = 0.0  # most smoothing boxes still see vehicles
    assert wave_speed(dist * (time > 0), time, 10.0, 1.0) == pytest.approx(-15.0, rel=0.05)
    assert math.isnan(wave_speed(dist[:10], time[:10], 10.0, 1.0))  # too short


def test_smoothed_speed_is_edies_box_mean() -> None:
    dist = np.array([[10.0, 0.0, 30.0]])
    time = np.array([[1.0, 0.0, 1.0]])
    v = smoothed_speed(dist, time, (3, 1))
    assert v.tolist() == [[10.0, 20.0, 30.0]]  # middle: (10 + 30) / 2 over its box


def test_flow_and_speed_spread_by_hand() -> None:
    # 100 m of 2 lanes; two vehicles at 10 and 20 m/s; the samples at t = 0.5 ... 1.5 s count
    # (11 steps of 0.1 s, from the 0.5 s warm-up on)
    field = SpaceTimeField(length=100.0, lane_metres=200.0, dt=0.1, warmup=0.5)
    for k in range(1, 16):
        t = 0.1 * k
        field.add(t, np.array([5.0 + t, 50.0, np.nan]), np.array([10.0, 20.0, 5.0]))
    assert field.speed_std() == pytest.approx(5.0)  # samples 10 and 20, equally many
    # Edie: distance (10 + 20) m/s x 1.1 s over 200 lane-m x 1.1 s -> 0.15 veh/s per lane
    assert field.flow() == pytest.approx(3600.0 * 30.0 / 200.0)
    assert field.time().sum() == pytest.approx(2 * 1.1)
    assert field.distance().shape[1] == 10
