"""AV metrics: hand-computed values for a constructed two-step history (pure math)."""

from __future__ import annotations

import numpy as np
import pytest

from mixed_traffic.env.av_metrics import AVMetrics, AVStep


def _step(**kw) -> AVStep:
    base = dict(
        ids=["av_0", "av_1"],
        speed=np.array([10.0, 20.0]),
        accel=np.array([1.0, -1.0]),
        prev_accel=np.array([0.0, 0.0]),
        lateral=np.array([0.2, -0.4]),
        following=np.array([True, False]),
        lane_changed=np.array([False, False]),
        ttc=np.array([np.inf, 3.0]),
        rear_ids=["hv_0", ""],
        rear_speed=np.array([9.0, 0.0]),
        rear_prev_speed=np.array([9.5, np.nan]),
        reward=np.array([1.0, 0.5]),
    )
    base.update(kw)
    return AVStep(**base)


def test_hand_computed_summary() -> None:
    m = AVMetrics(dt=0.1)
    m.step(_step(), time=0.1, speeds={"hv_0": 9.0})
    # second step: av_0 brakes hard -> a DEC-C event on hv_0, which then slows to 8 m/s
    m.step(
        _step(
            accel=np.array([-2.0, -1.0]),
            prev_accel=np.array([1.0, -1.0]),
            rear_prev_speed=np.array([9.0, np.nan]),
        ),
        time=0.2,
        speeds={"hv_0": 9.0},
    )
    for k in range(3, 14):
        m.step(_step(ids=[], speed=np.zeros(0), accel=np.zeros(0), prev_accel=np.zeros(0), lateral=np.zeros(0),
                     following=np.zeros(0, bool), lane_changed=np.zeros(0, bool), ttc=np.zeros(0), rear_ids=[],
                     rear_speed=np.zeros(0), rear_prev_speed=np.zeros(0), reward=np.zeros(0)),
               time=k / 10, speeds={"hv_0": 8.0})  # fmt: skip
    m.end_trip("av_0", "arrived")
    m.end_trip("av_1", "collision")
    s = m.summary()
    # velocity: (10 + 20 + 10 + 20) / 4 agent-steps
    assert s["avg_vel_a"] == pytest.approx(15.0)
    # jerk: (|1-0| + |-1-0| + |-2-1| + |-1+1|) / 0.1 / 4
    assert s["avg_jerk_a"] == pytest.approx((1 + 1 + 3 + 0) / 0.1 / 4)
    # offset only while following: av_0 twice at 0.2 m
    assert s["avg_off_a"] == pytest.approx(0.2)
    # TTC < 4 s in 2 of 4 agent-steps
    assert s["pt_rt"] == pytest.approx(50.0)
    # av_0's rear slowed by 0.5 > 0.1 m/s in step 1 only -> 0.1 s; av_1 has no C
    assert s["avg_at_c"] == pytest.approx((0.1 + 0.0) / 2)
    # DEC-C: C at 9 m/s when av_0 braked, minimum 8 m/s within 1 s
    assert s["avg_dec_c"] == pytest.approx(1.0)
    assert s["min_ttc_a"] == pytest.approx(3.0)  # av_0 never had a finite TTC
    assert s["avg_r"] == pytest.approx(0.75)
    assert s["route_completion"] == pytest.approx(50.0)
    assert s["terminal_collision"] == 1.0 and s["av_trips"] == 2.0
    assert m.rear_vehicles() == {"hv_0"}


def test_driving_time_per_km() -> None:
    m = AVMetrics(dt=0.1)
    one = dict(ids=["av_0"], speed=np.array([20.0]), accel=np.zeros(1), prev_accel=np.zeros(1),
               lateral=np.zeros(1), following=np.ones(1, bool), lane_changed=np.zeros(1, bool),
               ttc=np.array([np.inf]), rear_ids=[""], rear_speed=np.zeros(1),
               rear_prev_speed=np.full(1, np.nan), reward=np.zeros(1))  # fmt: skip
    for k in range(500):  # 50 s at 20 m/s = 1 km
        m.step(AVStep(**one), time=k / 10, speeds={})
    assert m.summary()["avg_dt_a"] == pytest.approx(50.0)
