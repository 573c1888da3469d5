"""Realistic traffic: the calibrated human drivers, the Sugiyama/Stern ring and its
wave-dampening controllers, through the episode runner on real SUMO."""

from __future__ import annotations

import math

from mixed_traffic.config import EnvConfig, HumanConfig
from mixed_traffic.env.parallel import MixedTrafficEnv
from mixed_traffic.experiments.runner import run_episode

RING = dict(scenario="ring", density=85.0, episode_length=300.0)


def _metrics(policy: str, warmup: float = 0.0, **fields) -> dict:
    return run_episode(EnvConfig(**fields), policy, warmup=warmup)["metrics"]


def test_the_default_ring_holds_22_vehicles_and_one_av_at_5_percent() -> None:
    env = MixedTrafficEnv(config=EnvConfig(penetration=0.05, **RING))
    try:
        env.reset(seed=0)
        assert env._snap.n == 22
        assert env.possible_agents == ["av_0"] and env.agents == ["av_0"]
    finally:
        env.close()


def test_human_drivers_jam_the_ring_and_one_follower_stopper_dampens_it() -> None:
    humans = _metrics("idm", penetration=0.0, **RING)
    assert humans["speed_std"] >= 1.5  # stop-and-go within the first minutes
    assert humans["wave_speed"] < 0  # the jam travels backwards
    stopper = _metrics("follower-stopper", penetration=0.05, **RING)
    assert stopper["speed_std"] <= 0.5 * humans["speed_std"]  # Stern et al. 2018
    assert stopper["collisions"] == 0


def test_deterministic_idm_on_the_ring_stays_uniform() -> None:
    """Without driver errors, reaction and heterogeneity the same ring does not jam: the
    waves come from the human model, not from the ring."""
    human = HumanConfig(car_following="IDM", accel=1.5, headway_dev=0.0, accel_dev=0.0,
                        driver_types=1, action_step=0.0)  # fmt: skip
    m = _metrics("idm", warmup=100.0, penetration=0.0, human=human, **RING)
    assert m["speed_std"] < 0.5


def test_a_free_and_a_congested_point_of_the_fundamental_diagram() -> None:
    """straight-3lane, all human: near capacity (24 veh/km/lane) the flow is in the empirical
    1,800-2,300 veh/h/lane band; at 60 veh/km/lane it is lower, with waves that travel
    upstream at -12 to -25 km/h and a speed spread of at least 1 m/s."""
    common = dict(scenario="straight-3lane", penetration=0.0, episode_length=240.0)
    free = _metrics("idm", warmup=60.0, density=72.0, **common)
    jam = _metrics("idm", warmup=60.0, density=180.0, **common)
    assert 1800 <= free["flow"] <= 2300
    assert jam["flow"] < free["flow"]
    assert jam["speed_std"] >= 1.0
    assert -25.0 <= jam["wave_speed"] <= -12.0
    assert math.isclose(jam["measured_density"] / 3, 60.0, rel_tol=0.1)


def test_a_full_acc_lc_fleet_costs_at_most_ten_percent_of_the_human_travel_time() -> None:
    """straight, 120 veh/km: DT-TF with 100 % ACC-LC against all-human traffic (the
    conservative variant's speed-dependent gap cost about 20 %)."""
    common = dict(scenario="straight", density=120.0, episode_length=120.0)
    human = _metrics("idm", warmup=30.0, penetration=0.0, **common)
    acc = _metrics("acc-lc", warmup=30.0, penetration=1.0, **common)
    assert acc["dt_tf"] <= 1.10 * human["dt_tf"]
    assert acc["collisions"] == 0


def test_urban_traffic_flows_and_has_a_travel_time() -> None:
    """The signalised grid at its default density: vehicles cross the measurement segment (it
    starts after the entry edge) and the humans keep moving (no gridlock)."""
    m = _metrics("idm", warmup=30.0, scenario="urban", penetration=0.0, episode_length=150.0)
    assert m["vehicles_crossed"] > 0 and m["dt_tf"] is not None
    assert m["mean_speed"] >= 4.0
    assert m["collisions"] == 0
