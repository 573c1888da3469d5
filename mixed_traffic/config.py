"""Frozen configuration dataclasses. Units live in each field's docstring; CLIs are built from them.

Every value is checked in ``__post_init__`` so a bad value raises ``ValueError`` naming the field,
the value and the allowed range before SUMO starts.
"""

from __future__ import annotations

import ast
import inspect
import math
from dataclasses import dataclass, field, fields
from functools import cache
from typing import Any

import numpy as np

WEATHERS = ("normal", "rain", "fog", "night")
CAR_FOLLOWING = ("EIDM", "IDM")
BACKENDS = ("libsumo", "traci", "auto")
SECOND_INSTANCE = ("traci", "error")
LANE_TERMS = ("offset", "waypoint")
#: Highest density accepted, veh/km per lane: a 5 m car plus a 2 m standstill gap.
JAM_DENSITY_PER_LANE = 1000.0 / 7.0
#: Episode length where neither the config nor the scenario's spec gives one [s].
DEFAULT_EPISODE_LENGTH = 120.0
#: Most copies of a scenario in one simulation (``EnvConfig.copies``).
MAX_COPIES = 1024
#: Circumferences a ring scenario may be scaled to [m] (``EnvConfig.ring_length``).
RING_LENGTH_RANGE = (150.0, 400.0)


def _check_range(
    obj: Any, name: str, lo: float, hi: float, *, lo_open: bool = False, integer: bool = False
) -> None:
    value = getattr(obj, name)
    kinds = int if integer else (int, float)
    ok = isinstance(value, kinds) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (value > lo if lo_open else value >= lo) and value <= hi
    if not ok:
        left = "(" if lo_open else "["
        what = "integers " if integer else ""
        raise ValueError(
            f"{type(obj).__name__}.{name}={value!r} is out of range; allowed {what}{left}{lo}, {hi}]"
        )


def _check_bool(obj: Any, name: str) -> None:
    value = getattr(obj, name)
    if not isinstance(value, bool):
        raise ValueError(f"{type(obj).__name__}.{name}={value!r} must be True or False")


def _check_choice(obj: Any, name: str, choices: tuple[str, ...]) -> None:
    value = getattr(obj, name)
    if value not in choices:
        raise ValueError(f"{type(obj).__name__}.{name}={value!r} is not one of {choices}")


@cache
def field_docs(cls: type) -> dict[str, str]:
    """Attribute docstrings of a dataclass (the string literal right after each field)."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        try:
            tree = ast.parse(inspect.getsource(klass))
        except (OSError, TypeError):
            continue
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for node, nxt in zip(body, body[1:]):
            if (
                isinstance(node, ast.AnnAssign)
                and isinstance(node.target, ast.Name)
                and isinstance(nxt, ast.Expr)
                and isinstance(nxt.value, ast.Constant)
                and isinstance(nxt.value.value, str)
            ):
                docs[node.target.id] = " ".join(nxt.value.value.split())
    return docs


@dataclass(frozen=True)
class SensorConfig:
    """Perception ranges and history (paper §III-B, §V-J)."""

    lidar_range: float = 90.0
    """LiDAR vehicle detection range [m]; the paper sweeps 50-110 m."""
    camera_range: float = 60.0
    """Camera traffic-light detection range [m]."""
    history: int = 5
    """z: number of history steps in each observation [steps]."""
    waypoints: int = 10
    """m: lane waypoints per lane in each observation [count], spaced 1 m."""
    preview_points: int = 3
    """k: speed-limit drops ahead in the ``limits`` observation [count]."""
    preview_range: float = 150.0
    """How far along the route the speed-limit preview looks [m] (braking from 33 to 14 m/s
    at 3 m/s² takes 149 m). An HD-map lookup: weather and ``range_factor`` leave it alone."""
    noise: bool = True
    """Apply the weather preset's sensor noise and misdetection (False = exact ground truth)."""
    range_factor: float = 1.0
    """Detection ranges as a multiple of ``lidar_range`` and ``camera_range`` [-] (the
    detection-range study, paper §V-J). Distances stay scaled by the nominal ranges a policy
    was trained with, so above 1 they read beyond ±1 (the boxes widen to the factor)."""
    memory: bool = False
    """Add the ``memory`` key: slow summaries of the agent's own and its leader's speed and
    its last command (:mod:`mixed_traffic.sensing.memory`)."""
    memory_taus: tuple[float, ...] = (10.0, 40.0)
    """Time constants of ``memory``'s exponential means and spreads [s]."""

    def __post_init__(self) -> None:
        taus = self.memory_taus
        ok = isinstance(taus, tuple) and 1 <= len(taus) <= 8
        ok = ok and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in taus)
        if not ok or not all(0.0 < x <= 3600.0 for x in taus):
            raise ValueError(f"SensorConfig.memory_taus={taus!r} must be 1-8 time constants "
                             "in (0, 3600] s")  # fmt: skip
        _check_bool(self, "memory")
        _check_range(self, "lidar_range", 0.0, 500.0, lo_open=True)
        _check_range(self, "camera_range", 0.0, 500.0, lo_open=True)
        _check_range(self, "range_factor", 0.0, 2.0, lo_open=True)
        _check_range(self, "history", 1, 50, integer=True)
        _check_range(self, "waypoints", 1, 200, integer=True)
        _check_range(self, "preview_points", 1, 16, integer=True)
        _check_range(self, "preview_range", 0.0, 2000.0, lo_open=True)
        _check_bool(self, "noise")


@dataclass(frozen=True)
class RewardConfig:
    """Hybrid reward weights and thresholds (paper §IV-E, DESIGN §8)."""

    w_safety: float = 0.9
    """w1, weight of the safety term r1 [-]."""
    w_efficiency: float = 0.8
    """w2, weight of the efficiency term r2 [-]."""
    w_comfort: float = 0.6
    """w3, weight of the comfort term r3 [-]."""
    w_impact: float = 0.2
    """w4, weight of the impact term r4 [-]."""
    ttc_threshold: float = 4.0
    """G, TTC below which r1,1 penalises [s]."""
    acc_threshold: float = 3.0
    """acc_thr, acceleration threshold of the comfort and impact terms [m/s^2]."""
    rear_speed_drop: float = 0.1
    """v_thr, speed drop of the rear vehicle within one step that counts as impact [m/s]."""
    terminal_penalty: float = -20.0
    """r1,3 on a terminal event [-]."""
    lane_change_gain: float = 20.0
    """Scale of the tactical lane-change reward r2,2 [-]."""
    lane_change_cap: float = 0.5
    """Bound on the gap ratio's change in r2,2, |gap_new/gap_old - 1| <= cap, so one lane change
    is worth at most lane_change_gain x cap [-]. 0 = the paper's unbounded term, measured from
    -19.9 to +3,580 per change (a change out from behind a car 0.5 m ahead)."""
    w_local_speed: float = 0.0
    """w5, weight of r5_local_speed, the mean speed of the traffic around the agent [-]
    (0 = the paper's reward)."""
    w_follower_comfort: float = 0.0
    """w6, weight of r6_follower_comfort, the accelerations of the agent's followers [-]
    (0 = the paper's reward)."""
    w_accel: float = 0.0
    """w7, weight of r7_accel, the agent's own acceleration magnitude [-] (Flow's ring reward
    penalises it; 0 = the paper's reward)."""
    w_uniform: float = 0.0
    """w8, weight of r8_uniform_flow, how near the traffic around the agent is to the uniform
    flow of a ring or the free flow of a road [-] (Flow's desired-velocity reward; 0 = the
    paper's reward)."""
    local_upstream: float = 200.0
    """How far behind the agent, along its route, r5 counts vehicles and r6 looks for
    followers [m] (on a ring r5 counts the whole ring)."""
    local_downstream: float = 200.0
    """How far ahead of the agent, along its route, r5 counts vehicles [m]."""
    followers: int = 5
    """The nearest vehicles behind the agent in its lane (same lane index) within
    ``local_upstream`` whose accelerations r6 averages [count]."""
    lane_term: str = "offset"
    """How r1,2 measures the distance from the lane centre: offset (SUMO's lateral offset, 0 when
    centred) | waypoint (the paper: distance to the nearest 1 m centreline waypoint, about
    -0.078 when centred because the vehicle sits between waypoints)."""

    def __post_init__(self) -> None:
        for name in ("w_safety", "w_efficiency", "w_comfort", "w_impact", "w_local_speed",
                     "w_follower_comfort", "w_accel", "w_uniform"):  # fmt: skip
            _check_range(self, name, 0.0, 10.0)
        _check_range(self, "local_upstream", 0.0, 10000.0)
        _check_range(self, "local_downstream", 0.0, 10000.0)
        _check_range(self, "followers", 1, 100, integer=True)
        _check_range(self, "ttc_threshold", 0.0, 60.0, lo_open=True)
        _check_range(self, "acc_threshold", 0.0, 20.0, lo_open=True)
        _check_range(self, "rear_speed_drop", 0.0, 10.0)
        _check_range(self, "terminal_penalty", -1000.0, 0.0)
        _check_range(self, "lane_change_gain", 0.0, 1000.0)
        _check_range(self, "lane_change_cap", 0.0, 1000.0)
        _check_choice(self, "lane_term", LANE_TERMS)


@dataclass(frozen=True)
class V2XConfig:
    """The downstream feed of ``EnvConfig.v2x`` (observation key ``downstream``): the mean speed
    of the traffic in segments ahead on the AV's route, as a roadside or probe-vehicle feed
    reports it: measured every ``update_period``, received ``latency`` later, with noise."""

    segments: tuple[float, ...] = (0.0, 100.0, 300.0, 1000.0)
    """Edges of the segments along the route, from the AV's front bumper [m], increasing:
    S = len - 1 segments (0-100, 100-300 and 300-1000 m)."""
    update_period: float = 1.0
    """Time between two measurements of the feed [s] (a value shorter than the step length
    measures every step)."""
    latency: float = 1.0
    """Delay from a measurement to its arrival at the AV [s]."""
    speed_noise: float = 0.5
    """Standard deviation of the Gaussian error added to each segment's mean speed [m/s]."""
    probe_share: float = 1.0
    """Chance that a vehicle's report reaches a measurement, drawn per vehicle and
    measurement [0-1] (1 = a roadside feed that sees every vehicle; below 1 a probe-vehicle
    feed, whose density estimate divides the count by it)."""

    def __post_init__(self) -> None:
        seg = self.segments
        ok = isinstance(seg, tuple) and 2 <= len(seg) <= 17
        ok = ok and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in seg)
        ok = ok and all(math.isfinite(x) for x in seg) and seg[0] >= 0.0 and seg[-1] <= 10000.0
        if not ok or any(b <= a for a, b in zip(seg, seg[1:])):
            raise ValueError(f"V2XConfig.segments={seg!r} must be 2-17 increasing distances "
                             "in [0, 10000] m")  # fmt: skip
        _check_range(self, "update_period", 0.0, 3600.0, lo_open=True)
        _check_range(self, "latency", 0.0, 3600.0)
        _check_range(self, "speed_noise", 0.0, 50.0)
        _check_range(self, "probe_share", 0.0, 1.0, lo_open=True)


@dataclass(frozen=True)
class VehicleConfig:
    """Vehicle dimensions (every vehicle) and the AVs' limits."""

    length: float = 5.0
    """Vehicle length [m]."""
    width: float = 1.8
    """Vehicle width [m]."""
    wheelbase: float = 2.8
    """AV wheelbase of the kinematic bicycle model [m]; the rear axle sits at half of it."""
    max_accel: float = 3.0
    """AV acceleration at accel_brake = +1 [m/s^2]."""
    max_decel: float = 6.0
    """AV deceleration at accel_brake = -1 [m/s^2]."""
    max_steer_deg: float = 60.0
    """Steering angle at steering = +-1 [deg] (paper: -60..60)."""

    def __post_init__(self) -> None:
        for name in ("length", "width", "wheelbase", "max_accel", "max_decel"):
            _check_range(self, name, 0.0, 30.0, lo_open=True)
        _check_range(self, "max_steer_deg", 0.0, 89.0, lo_open=True)


@dataclass(frozen=True)
class HumanConfig:
    """Conventional (human) drivers: SUMO's Extended IDM with estimation and driving errors,
    and a population of driver types (a SUMO vTypeDistribution) spread around the mean
    parameters. Calibrated against the empirical fundamental diagram and stop-and-go waves in
    docs/traffic.md; ``car_following="IDM"`` gives SUMO's deterministic IDM (no errors)."""

    car_following: str = "EIDM"
    """SUMO car-following model: EIDM (with the errors below) | IDM (deterministic)."""
    accel: float = 0.9
    """Mean maximum acceleration a [m/s^2]."""
    decel: float = 2.0
    """Comfortable deceleration b [m/s^2]."""
    headway: float = 1.2
    """Mean desired time headway T (SUMO tau) [s]."""
    min_gap: float = 2.0
    """Standstill gap s0 (SUMO minGap) [m]."""
    delta: float = 4.0
    """Acceleration exponent delta [-]."""
    speed_factor_dev: float = 0.08
    """Standard deviation of the desired-speed factor around the speed limit [-]."""
    headway_dev: float = 0.15
    """Relative standard deviation of T across driver types [-]."""
    accel_dev: float = 0.2
    """Relative standard deviation of a across driver types [-]."""
    driver_types: int = 10
    """Driver types in the distribution, at evenly spaced quantiles of T and a [count]."""
    sigma_error: float = 0.05
    """EIDM driving error: intensity of the random acceleration error [-] (sigmaerror)."""
    sigma_gap: float = 0.05
    """EIDM relative error of the estimated gap [-] (sigmagap)."""
    sigma_leader: float = 0.05
    """EIDM error of the estimated leader speed [-] (sigmaleader)."""
    reaction_time: float = 0.5
    """EIDM reaction time [s] (treaction; 0 = none)."""
    coolness: float = 0.5
    """EIDM coolness: weight of the constant-acceleration heuristic, which brakes less for a
    leader that is braking but far enough [0-1] (ccoolness; 0 = plain IDM braking)."""
    action_step: float = 0.3
    """SUMO actionStepLength: how often a driver decides [s] (0 = every simulation step)."""

    def __post_init__(self) -> None:
        _check_choice(self, "car_following", CAR_FOLLOWING)
        for name in ("accel", "decel", "headway"):
            _check_range(self, name, 0.0, 30.0, lo_open=True)
        _check_range(self, "min_gap", 0.0, 20.0)
        _check_range(self, "delta", 0.5, 10.0)
        _check_range(self, "speed_factor_dev", 0.0, 0.5)
        _check_range(self, "headway_dev", 0.0, 0.5)
        _check_range(self, "accel_dev", 0.0, 0.5)
        _check_range(self, "driver_types", 1, 100, integer=True)
        for name in ("sigma_error", "sigma_gap", "sigma_leader"):
            _check_range(self, name, 0.0, 2.0)
        _check_range(self, "reaction_time", 0.0, 3.0)
        _check_range(self, "coolness", 0.0, 1.0)
        _check_range(self, "action_step", 0.0, 2.0)

    def idm_accel(self, v: Any, v_lead: Any, gap: Any, v0: Any) -> Any:
        """IDM acceleration [m/s²] of the mean driver (no errors) at speed ``v`` [m/s] behind a
        leader at ``v_lead`` [m/s] with bumper ``gap`` [m] (inf: no leader), desired speed
        ``v0`` [m/s]; scalars or arrays of one shape."""
        s_star = self.min_gap + np.maximum(
            0.0, v * self.headway + v * (v - v_lead) / (2 * np.sqrt(self.accel * self.decel))
        )
        return self.accel * (1 - (v / v0) ** self.delta - (s_star / np.maximum(gap, 0.1)) ** 2)


@dataclass(frozen=True)
class EnvConfig:
    """Everything that defines one environment. ``parallel_env(**kwargs)`` maps onto it."""

    scenario: str = "straight"
    """Scenario name from ``list_scenarios()``, or a path to a .net.xml or .sumocfg file."""
    density: float | None = None
    """Traffic density k summed over all lanes of the road [veh/km] (paper: 60/120/180); None =
    the scenario's default (120 veh/km unless its spec gives one: urban grids use less)."""
    ring_length: tuple[float, ...] = ()
    """Circumference of a ring scenario [m], 150-400: one value scales the ring to it; a (low,
    high) pair draws a length at every reset from the episode's seed. The vehicle count
    follows density x length, or is ``ring_vehicles``. () = the ring as bundled."""
    ring_vehicles: int | None = None
    """Vehicles on a ring whatever its length [count] (Flow's ring: 22 on 220-270 m). Each
    episode's density is then this count / its ring's length, and ``density`` is set to that of
    the longest ring ``ring_length`` names (a different density is refused). None = density x
    length."""
    penetration: float = 0.2
    """AV penetration rate p, the fraction of vehicles that are AVs [0-1]."""
    weather: str = "normal"
    """Weather preset: normal | rain | fog | night (sensor noise and misdetection)."""
    seed: int = 0
    """Root seed for SUMO, demand, sensor noise, numpy and torch."""
    copies: int = 1
    """Independent copies of the scenario in one simulation [count], each with its own demand
    draw, agents, reference speeds and metrics (batched worlds: one step serves them all).
    Ring, straight, highway, wave-highway, merge and bottleneck scenarios only."""
    episode_length: float | None = None
    """Simulated time per episode [s]; reaching it truncates. None = the scenario's (120 s
    unless its spec gives one: wave-highway's queue needs 420 s)."""
    step_length: float = 0.1
    """Simulation and decision step dt [s] (paper: 0.1 s)."""
    lateral_resolution: float = 0.8
    """Sublane width of SUMO's sublane model [m]."""
    backend: str = "libsumo"
    """SUMO binding: libsumo (fast, one simulation per process) | traci | auto."""
    second_instance: str = "traci"
    """What a second libsumo simulation in one process does: traci (fall back) | error."""
    fixed_fleet: bool = False
    """All AVs exist from reset and re-enter upstream when they finish (for SuperSuit/SB3)."""
    speed_tolerance: float = 0.1
    """Speed above the limit, as a fraction of it, that counts as a violation [-]."""
    reset_wait: float = 3600.0
    """How long reset() lets the simulation run, with nobody acting, until the first AV enters
    when none is in the network yet [s]; never past the episode's last step (PettingZoo needs an
    agent after reset). If none enters, reset() raises NoAgentError (docs/env.md)."""
    v2x: bool = False
    """Add the observation key ``downstream``: the traffic's mean speed in segments ahead on
    the route, from a roadside or probe-vehicle feed (``v2x_feed``); off = the paper's
    observation."""
    av_window: float = 200.0
    """Reach ahead of and behind each AV along its lane whose vehicles' speeds make the
    metrics speed_std_ahead / speed_std_behind [m]; on a closed loop at most half the loop."""
    sensors: SensorConfig = field(default_factory=SensorConfig)
    """Sensor ranges, history length and noise switch."""
    v2x_feed: V2XConfig = field(default_factory=V2XConfig)
    """Segments, update period, latency and noise of the ``downstream`` feed (with ``v2x``)."""
    reward: RewardConfig = field(default_factory=RewardConfig)
    """Hybrid reward weights and thresholds."""
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    """Vehicle dimensions and AV limits."""
    human: HumanConfig = field(default_factory=HumanConfig)
    """The conventional (human) drivers' model and population."""

    def __post_init__(self) -> None:
        if not isinstance(self.scenario, str) or not self.scenario:
            raise ValueError(f"EnvConfig.scenario={self.scenario!r} must be a non-empty string")
        # the per-scenario jam density (lanes x JAM_DENSITY_PER_LANE) is checked by the demand builder
        if self.density is not None:
            _check_range(self, "density", 0.0, 1000.0, lo_open=True)
        self._check_ring_length()
        _check_range(self, "penetration", 0.0, 1.0)
        _check_choice(self, "weather", WEATHERS)
        _check_choice(self, "backend", BACKENDS)
        _check_choice(self, "second_instance", SECOND_INSTANCE)
        if not isinstance(self.seed, int) or isinstance(self.seed, bool) or self.seed < 0:
            raise ValueError(f"EnvConfig.seed={self.seed!r} must be an integer >= 0")
        _check_range(self, "copies", 1, MAX_COPIES, integer=True)
        _check_range(self, "step_length", 0.01, 1.0)
        if self.episode_length is not None:
            self._check_episode_length()
        _check_bool(self, "fixed_fleet")
        _check_bool(self, "v2x")
        if self.ring_vehicles is not None:
            _check_range(self, "ring_vehicles", 2, 2000, integer=True)
        if self.fixed_fleet and len(self.ring_length) == 2 and self.ring_vehicles is None:
            raise ValueError(f"EnvConfig.ring_length={self.ring_length!r} draws a length per reset, "
                             "which changes the size of a fixed_fleet: give one length or "
                             "ring_vehicles")  # fmt: skip
        _check_range(self, "lateral_resolution", 0.1, 3.2)
        _check_range(self, "speed_tolerance", 0.0, 1.0)
        _check_range(self, "reset_wait", 0.0, 86400.0)
        _check_range(self, "av_window", 0.0, 1000.0, lo_open=True)
        for name, cls in _nested().items():
            if not isinstance(getattr(self, name), cls):
                raise ValueError(f"EnvConfig.{name}={getattr(self, name)!r} must be a "
                                 f"{cls.__name__}(...) (a dict goes through EnvConfig.from_dict)")  # fmt: skip

    def _check_episode_length(self) -> None:
        _check_range(self, "episode_length", 0.0, 86400.0, lo_open=True)
        if self.episode_length < self.step_length:
            raise ValueError(f"EnvConfig.episode_length={self.episode_length!r} is shorter than one "
                             f"step (step_length={self.step_length!r})")  # fmt: skip

    def _check_ring_length(self) -> None:
        """Accept one length, a (low, high) pair or (); a bare number (or a JSON list) becomes
        a tuple."""
        value = self.ring_length
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            value = (value,)
        if isinstance(value, list):
            value = tuple(value)
        lo, hi = RING_LENGTH_RANGE
        ok = isinstance(value, tuple) and len(value) <= 2
        ok = ok and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
        ok = ok and all(lo <= v <= hi for v in value) and list(value) == sorted(value)
        if not ok:
            raise ValueError(f"EnvConfig.ring_length={self.ring_length!r}: give one length or a "
                             f"(low, high) pair within [{lo:g}, {hi:g}] m")  # fmt: skip
        object.__setattr__(self, "ring_length", tuple(float(v) for v in value))

    @property
    def steps_per_episode(self) -> int:
        return int(round(self.episode_length / self.step_length))

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (JSON-safe) of every field."""
        return _to_dict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> EnvConfig:
        nested = _nested()
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown EnvConfig fields {sorted(unknown)}; known: {sorted(known)}")
        kwargs = {
            k: nested[k](**_tuples(v)) if k in nested and isinstance(v, dict) else v
            for k, v in data.items()
        }
        return cls(**kwargs)


def _nested() -> dict[str, type]:
    """The dataclass-valued fields of ``EnvConfig`` and their types."""
    return {"sensors": SensorConfig, "reward": RewardConfig, "vehicle": VehicleConfig,
            "human": HumanConfig, "v2x_feed": V2XConfig}  # fmt: skip


def _tuples(data: dict[str, Any]) -> dict[str, Any]:
    """``data`` with lists (JSON's tuples) as tuples."""
    return {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}


def _to_dict(obj: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for f in fields(obj):
        value = getattr(obj, f.name)
        out[f.name] = _to_dict(value) if hasattr(value, "__dataclass_fields__") else value
    return out
