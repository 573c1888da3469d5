"""Edie's sums on the space-time grid and the wave-speed estimate (pure math, hand values)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mixed_traffic.env.space_time import SpaceTimeField, smoothed_speed, wave_speed


def _travelling_wave(c_kmh: float, period: float = 60.0) -> tuple[np.ndarray, np.ndarray]:
    """(dist, time) of a 1 km x 200 s grid whose speed is 10 + 4 sin(2π (t - x/c) / period)."""
    t = np.arange(200)[:, None] + 0.5
    x = (np.arange(100)[None, :] + 0.5) * 10.0
    v = 10.0 + 4.0 * np.sin(2 * np.pi * (t - x / (c_kmh / 3.6)) / period)
    time = np.full(v.shape, 2.0)  # two vehicle-seconds in every cell
    return v * time, time


@pytest.mark.parametrize("c_kmh", [-12.0, -15.0, -20.0, 30.0])
def test_wave_speed_recovers_a_travelling_wave(c_kmh: float) -> None:
    dist, time = _travelling_wave(c_kmh)
    assert wave_speed(dist, time, 10.0, 1.0) == pytest.approx(c_kmh, rel=0.05)


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
    assert field.time.sum() == pytest.approx(2 * 1.1)
    assert field.distance.shape[1] == 10
