"""ACC-LC's parameters and index constants (shared by its longitudinal, lateral and planning
parts; see :mod:`agents.rules.acc_lc` for what the driver does)."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from mixed_traffic.config import HumanConfig, SensorConfig, VehicleConfig
from mixed_traffic.env.api import DEAD_END_DISTANCE

#: decisions (rows of ``params``): left change, follow, right change
LEFT, FOLLOW, RIGHT = 0, 1, 2
#: lane columns in the observation (left, current, right)
LANE_L, LANE_C, LANE_R = 0, 1, 2


def check_rule_fields(obj: object, positive: tuple[str, ...]) -> None:
    """``ValueError`` naming the first field of a rule's config that is not a finite number
    >= 0 (> 0 for the ``positive`` ones): every length, time, speed and rate of the rules."""
    for f in fields(obj):
        value = getattr(obj, f.name)
        for v in value if isinstance(value, tuple) else (value,):
            if isinstance(v, bool) or not isinstance(v, int | float):
                continue
            low = "> 0" if f.name in positive else ">= 0"
            if not math.isfinite(v) or v < 0 or (f.name in positive and v == 0):
                raise ValueError(
                    f"{type(obj).__name__}.{f.name}={value!r} must be finite and {low}"
                )


@dataclass(frozen=True)
class AccLcConfig:
    """Parameters of the rule-based driver (SI units). Every field is a finite number >= 0;
    a time, a rate or a factor that divides is > 0."""

    # the env's sensor ranges and vehicle limits (one source: mixed_traffic.config)
    lidar_range: float = SensorConfig.lidar_range
    camera_range: float = SensorConfig.camera_range
    preview_range: float = SensorConfig.preview_range
    wheelbase: float = VehicleConfig.wheelbase
    max_steer_deg: float = VehicleConfig.max_steer_deg
    max_accel: float = VehicleConfig.max_accel
    max_decel: float = VehicleConfig.max_decel
    dt: float = 0.1
    """Time between observation frames, the env's step length [s] (a .sumocfg brings its own:
    SUMO's examples run at 0.05-0.5 s)."""
    # longitudinal: IIDM with a constant time gap T (commercial ACC: 1-2 s, independent of
    # speed); emergency braking only where stopping behind the leader's stopping point needs
    # more than ``emergency_decel`` (blended in over ``emergency_span``)
    a: float = 1.5
    b: float = 2.0
    T: float = 1.4
    s0: float = 2.0
    iidm: bool = True
    emergency_decel: float = 4.0
    emergency_span: float = 2.0
    speed_factor: float = 0.95
    long_length: float = 18.75
    """Length assumed of a vehicle whose observed length fills the observation's scale (10 m;
    buses of 12 m and trailers of 16.5 m are common in SUMO files): the longest road vehicle
    the EU allows [m]. Reading such a vehicle as 10 m long put the gap to its rear up to
    6.5 m further than it was."""
    # lights and junctions
    yellow_stop_decel: float = 3.5
    stop_margin: float = 1.5
    signal_sight_decel: float = 3.0
    """Towards a signal the HD map shows but the camera does not (fog: 30 m of sight), the
    speed stays low enough to stop at its line at this deceleration [m/s²], so a red seen late
    is still stopped for; below ``yellow_stop_decel``, so a late yellow is too."""
    # approach speed at a give-way line [m/s]: SUMO may close the link at any moment (no yellow
    # phase warns), so the AV must be able to stop at the line when it does
    junction_speed: float = 3.3
    curve_accel: float = 2.0
    # a target speed ahead this much below the present one is braked for kinematically [m/s]
    limit_deadband: float = 0.5
    # lane change
    lane_shift: float = 3.4
    lane_width_min: float = 3.2
    lc_threshold: float = 0.4
    keep_right_bias: float = 0.1
    rear_headway: float = 0.6
    rear_decel: float = 2.0
    lc_start_offset: float = 0.3
    # forced merge (mandatory change): the rear vehicle of the target lane, assumed to follow
    # IDM (hv parameters), may need to brake at most ``force_rear_decel`` for the ego
    force_rear_decel: float = 3.0
    force_front_decel: float = 3.0
    hv_a: float = HumanConfig.accel
    hv_b: float = HumanConfig.decel
    hv_T: float = HumanConfig.headway
    hv_s0: float = HumanConfig.min_gap
    # lateral envelope: clearance kept to vehicles alongside (longitudinal overlap)
    side_margin: float = 0.4
    side_long_margin: float = 2.0
    max_body_yaw: float = 0.5
    """Largest angle of its course to the lane [rad] at which the ego's corners are counted in
    its clearance to vehicles alongside."""
    # hidden vehicle: one may sit right ahead of a slower visible neighbour (bumper gap
    # ``hidden_gap``) and pull into our lane; pass slow neighbours only as fast as we could stop
    hidden_gap: float = 1.0
    hidden_decel: float = 4.0
    # cooperation: a waiting mandatory changer signals with a lateral offset towards the target
    # lane; a vehicle ahead in a neighbouring lane offset towards us by ``signal_min`` is yielded
    # to (a leader) when we can stop for it braking at most ``yield_decel``
    signal_offset: float = 0.6
    signal_min: float = 0.4
    yield_decel: float = 2.5
    # a mandatory change waits this far before the end of its lane (room to swing out), and
    # creeps this close to it once the change is under way
    end_wait: float = 6.0
    # (the env ends a trip stuck within DEAD_END_DISTANCE of a dead end as a route deviation)
    end_s0: float = DEAD_END_DISTANCE + 0.5
    # lateral
    lat_accel: float = 2.0
    lat_speed: float = 1.0
    lat_gain: float = 0.8
    heading_gain: float = 1.0
    heading_trust: float = 0.15
    """SUMO's heading counts as the course while it is within this of the course the measured
    lateral velocity gives, and not at all beyond twice it [rad]."""
    # in its lane (follow), the course is never steeper than one that can be turned straight
    # at this curvature [1/m] within the remaining offset: creeping in a queue, a course set
    # from the lateral speed alone reached 21 deg, and when the queue moved on the ego swung
    # past its lane centre into the next lane (a fixed small cap instead left egos straddling
    # two lanes when the queue stopped)
    follow_curvature: float = 0.1

    def __post_init__(self) -> None:
        check_rule_fields(self, _POSITIVE)
        if self.speed_factor > 1.5:
            raise ValueError(f"AccLcConfig.speed_factor={self.speed_factor!r} must be <= 1.5 "
                             "(the desired speed as a share of the limit)")  # fmt: skip


_POSITIVE = ("dt", "a", "b", "T", "speed_factor", "emergency_decel", "emergency_span",
             "yellow_stop_decel", "signal_sight_decel", "junction_speed", "curve_accel",
             "lat_accel", "lat_speed", "max_accel", "max_decel", "hv_a", "hv_b", "hv_T",
             "rear_decel", "force_rear_decel", "force_front_decel", "hidden_decel",
             "yield_decel", "wheelbase", "max_steer_deg")  # fmt: skip


def conservative() -> AccLcConfig:
    """The ACC-LC of the first studies (policy ``acc-lc-conservative``): IDM with T = 1.3 s and
    s0 = 3 m, whose gap widens towards the desired speed, and an emergency term that blends in
    from the comfortable deceleration: in steady following its time gap grew from 1.75 s at
    41 km/h to 3.9 s at 89 km/h."""
    return AccLcConfig(T=1.3, s0=3.0, iidm=False, emergency_decel=2.0, emergency_span=2.0)
