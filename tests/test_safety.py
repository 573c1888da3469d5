"""Safety module (agents.rules.safety) on real SUMO: it stops a reckless driver and leaves ACC-LC alone."""

from __future__ import annotations

import numpy as np
import pytest

from agents.policies import stack_obs, to_actions
from agents.rules.acc_lc import FOLLOW, AccLcPolicy
from agents.rules.rss import RssConfig, rss_accel
from agents.rules.safety import SafetyConfig, SafetyModule
from mixed_traffic.config import EnvConfig
from mixed_traffic.env.action import to_accel_brake, to_physical
from mixed_traffic.schema import TERMINAL_REASONS
from mixed_traffic.sensing.observation import observation_space


def _reckless(obs: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Full throttle whatever the decision; every other agent also steers left."""
    a = len(obs["ego"])
    params = np.zeros((a, 3, 2), np.float32)
    params[::2, :, 0], params[..., 1] = 0.05, 1.0
    return np.full(a, FOLLOW), params


def _drive(act, module: SafetyModule | None, seconds: float = 25.0) -> dict[str, int]:
    """Terminal events of one episode (straight, 120 veh/km, half AVs) driven by ``act``."""
    from mixed_traffic.env import parallel_env

    e = parallel_env(scenario="straight", density=120, penetration=0.5,
                     episode_length=seconds, seed=3, weather="normal")  # fmt: skip
    events: dict[str, int] = {}
    try:
        obs, _ = e.reset(seed=3)
        while e.agents:
            agents = list(e.agents)
            batch = stack_obs(obs, agents)
            decision, params = act(batch)
            if module is not None:
                decision, params, _ = module.filter(batch, decision, params)
            obs, _, term, _, info = e.step(to_actions(agents, decision, params))
            for a, t in term.items():
                ev = info.get(a, {}).get("event", "")
                if t and ev in TERMINAL_REASONS:
                    events[ev] = events.get(ev, 0) + 1
    finally:
        e.close()
    return events


def test_reckless_driver_crashes_alone_and_not_behind_the_module() -> None:
    assert sum(_drive(_reckless, None).values()) > 10
    module = SafetyModule()
    assert _drive(_reckless, module) == {}
    assert module.interventions["lateral"] > 0
    assert module.interventions["longitudinal"] > 0
    assert 0.0 < module.share <= 100.0
    parts = module.shares
    assert parts["sm_lateral"] > 0 and parts["sm_longitudinal"] > 0
    assert parts["sm_lateral"] + parts["sm_longitudinal"] == pytest.approx(module.share)


def test_acc_lc_actions_pass_unchanged() -> None:
    module = SafetyModule()
    assert _drive(AccLcPolicy().act, module) == {}
    assert module.decisions > 1000
    assert module.share < 0.5, module.interventions


def _empty_road(a: int) -> dict[str, np.ndarray]:
    """(a,) egos at 20 m/s on the centre line of a road without waypoints or vehicles."""
    space = observation_space(EnvConfig())
    obs = {k: np.zeros((a, *sp.shape), sp.dtype) for k, sp in space.spaces.items()}
    obs["node_mask"][:] = 1
    obs["action_mask"][:] = 1
    obs["ego"][:, :, 0] = 20.0 / 40.0
    obs["ego"][:, :, 2:4] = [0.45, 0.36]
    return obs


def test_prediction_follows_the_steering() -> None:
    """Pure kinematics: straight ahead keeps the offset, left steering raises it."""
    module = SafetyModule()
    a = 3
    obs = _empty_road(a)
    plan = AccLcPolicy().plan(obs)
    d = module.predicted_offset(plan, np.deg2rad([0.0, 1.2, -1.2]), np.zeros(a))
    assert abs(d[0]) < 1e-6
    assert d[1] > 0.5 and d[2] < -0.5


def test_learned_acceleration_is_clamped_above_acc_lc_braking() -> None:
    """``clamp``: where ACC-LC brakes (15 m/s above the default 13.9 m/s limit), a learned
    acceleration more than ``accel_tolerance`` above ACC-LC's is clamped to that bound; one
    within it, or braking harder than ACC-LC, stands."""
    module = SafetyModule(SafetyConfig(longitudinal="clamp"))
    obs = _empty_road(3)
    obs["ego"][:, :, 0] = 15.0 / 40.0
    plan = module.rule.plan(obs)
    _, rule = to_physical(plan.decision, plan.params, module.vehicle)
    assert ((rule < -0.5) & (rule > -3.0)).all(), rule
    tol = module.config.accel_tolerance
    want = rule + np.array([tol + 2.0, tol - 0.1, -1.0])
    params = plan.params.copy()
    params[np.arange(3), plan.decision, 1] = to_accel_brake(want, module.vehicle)
    decision, params, flags = module.filter(obs, plan.decision, params)
    _, got = to_physical(decision, params, module.vehicle)
    assert flags["longitudinal"].tolist() == [True, False, False]
    assert not flags["lateral"].any()
    np.testing.assert_allclose(got, [rule[0] + tol, want[1], want[2]], atol=1e-5)


def test_rss_bound_stops_the_ego_the_min_gap_behind_the_leader() -> None:
    """Pure: holding ``rss_accel`` for the response time and then braking at the ego's
    deceleration ends exactly ``rss_min_gap`` behind where the leader stops at its hardest
    braking; 0.1 m/s² more ends closer; -inf where even braking now is too late."""
    c = RssConfig()
    rng = np.random.default_rng(0)
    v, v_lead = rng.uniform(0, 35, 200), rng.uniform(0, 35, 200)
    gap = rng.uniform(5, 80, 200)

    def margin(a: np.ndarray) -> np.ndarray:
        x = np.maximum(v + a * c.response, 0.0)
        ego = (v + x) / 2 * c.response + x**2 / (2 * c.ego_decel)
        return gap + v_lead**2 / (2 * c.lead_decel) - ego

    a = rss_accel(v, gap, v_lead, c)
    ok = np.isfinite(a) & (v + a * c.response > 0)
    assert ok.sum() > 100
    np.testing.assert_allclose(margin(a)[ok], c.min_gap, atol=1e-6)
    assert (margin(a + 0.1)[ok] < c.min_gap).all()
    assert rss_accel(np.array([30.0]), np.array([5.0]), np.array([0.0]), c)[0] == -np.inf


def test_rss_mode_caps_speeding_at_acc_lc_speed_cap() -> None:
    """``rss`` on an empty road at 15 m/s (limit 13.9 m/s): no leader bounds the acceleration,
    the speed cap does; accelerating is capped, braking stands; bad config values are named."""
    module = SafetyModule()
    assert module.config.longitudinal == "rss"
    obs = _empty_road(2)
    obs["ego"][:, :, 0] = 15.0 / 40.0
    plan = module.rule.plan(obs)
    params = plan.params.copy()
    params[np.arange(2), plan.decision, 1] = to_accel_brake(np.array([2.0, -2.0]), module.vehicle)
    decision, params, flags = module.filter(obs, plan.decision, params)
    _, got = to_physical(decision, params, module.vehicle)
    assert flags["longitudinal"].tolist() == [True, False]
    assert got[0] < 0.0 and got[1] == pytest.approx(-2.0, abs=1e-5)
    with pytest.raises(ValueError, match="longitudinal"):
        SafetyConfig(longitudinal="loose")
    with pytest.raises(ValueError, match=r"RssConfig\.lead_decel"):
        RssConfig(lead_decel=0.0)


def test_rss_caps_per_lane_and_the_driver_governor() -> None:
    """Pure: a leader 25 m ahead in the left lane (bumper gap 20 m, both at 20 m/s) bounds
    that lane column at ``rss_accel``; the current and right lanes are unbounded (a current
    lane's leader would bound a change too, while the ego still overlaps it). The driver's
    RSS governor lifts no row above its column's cap unless ACC-LC's own is higher."""
    from agents.driver import Driver
    from agents.learners.rbpdqn import LearnerConfig
    from agents.rules.acc_lc_config import AccLcConfig
    from agents.rules.rss import rss_caps

    k = 5
    f = {"v": np.array([20.0]), "d": np.zeros(1), "wid": np.array([1.8]),
         "exists": np.ones((1, 3), bool),
         "h_dist": np.full((1, 3, k), np.inf), "h_len": np.full((1, 3, k), 5.0),
         "h_rel": np.zeros((1, 3, k)), "h_lat": np.zeros((1, 3, k)),
         "h_wid": np.full((1, 3, k), 1.8)}  # fmt: skip
    f["h_dist"][:, 0] = 25.0
    c = RssConfig()
    caps = rss_caps(f, AccLcConfig(), c)
    want = rss_accel(np.array(20.0), np.array(20.0), np.array(20.0), c)
    assert caps[0, 0] == pytest.approx(float(want)) and np.isinf(caps[0, 1:]).all()
    driver = Driver(None, LearnerConfig(residual=True, rss_governor=True), 0.1)
    t_par = np.zeros((1, 3, 2), np.float32)
    t_par[0, :, 1] = [0.1, 0.1, 0.3]
    u = np.ones((1, 3, 2), np.float32)
    out = driver._execute(u, t_par, cap=np.array([[0.2, 0.05, 1.0]]))
    np.testing.assert_allclose(out[0, :, 1], [0.2, 0.1, 0.55])
