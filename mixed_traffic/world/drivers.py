"""The vehicle types of an episode's route file: the human drivers' population (a SUMO
``vTypeDistribution``) and the AV type.

Human drivers differ in their desired time headway T and maximum acceleration a: the
distribution has ``driver_types`` types placed at evenly spaced quantiles of a normal
distribution around the mean (relative spreads ``headway_dev`` and ``accel_dev``), T and a in
opposite quantile order (a driver keeping short gaps accelerates briskly). SUMO draws each
vehicle's type from the distribution with its own seeded generator, and its desired speed
factor from ``normc(1, speed_factor_dev)``. Placement at reset plans with the most cautious
type (``cautious``) so that SUMO accepts every vehicle whichever type it draws.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import replace
from statistics import NormalDist

from mixed_traffic.config import HumanConfig, VehicleConfig
from mixed_traffic.world.hdmap import CAR

SPEED_FACTOR_RANGE = (0.8, 1.2)
"""Truncation of human drivers' speed factor (desired speed / speed limit) [-]."""
HUMAN_TYPE = "hv"
"""Type (distribution) id of the human drivers."""
AV_TYPE = "av"
"""Type id of the AVs."""


def driver_types(human: HumanConfig) -> list[tuple[float, float]]:
    """(T [s], a [m/s^2]) of each driver type, at the quantiles (k + 0.5) / K."""
    k = human.driver_types
    z = [NormalDist().inv_cdf((i + 0.5) / k) for i in range(k)]
    headway = [max(0.3, human.headway * (1.0 + human.headway_dev * q)) for q in z]
    accel = [max(0.3, human.accel * (1.0 - human.accel_dev * q)) for q in z]
    return list(zip(headway, accel))


def cautious(human: HumanConfig) -> HumanConfig:
    """The mean driver with the longest headway and the weakest acceleration of the types."""
    types = driver_types(human)
    return replace(human, headway=max(t for t, _ in types), accel=min(a for _, a in types))


def _human_attrs(human: HumanConfig, vehicle: VehicleConfig) -> dict[str, str]:
    lo, hi = SPEED_FACTOR_RANGE
    attrs = {
        "vClass": CAR, "carFollowModel": human.car_following,
        "decel": f"{human.decel}", "emergencyDecel": "9.0", "minGap": f"{human.min_gap}",
        "delta": f"{human.delta}", "length": f"{vehicle.length}", "width": f"{vehicle.width}",
        "speedFactor": f"normc(1,{human.speed_factor_dev},{lo},{hi})",
        "laneChangeModel": "SL2015", "latAlignment": "center", "color": "0.6,0.6,0.6",
    }  # fmt: skip
    if human.action_step > 0:
        attrs["actionStepLength"] = f"{human.action_step}"
    if human.car_following == "EIDM":
        attrs.update(sigmaerror=f"{human.sigma_error}", sigmagap=f"{human.sigma_gap}",
                     sigmaleader=f"{human.sigma_leader}", treaction=f"{human.reaction_time}",
                     ccoolness=f"{human.coolness}")  # fmt: skip
    return attrs


def add_vehicle_types(root: ET.Element, human: HumanConfig, vehicle: VehicleConfig,
                      avs_as_humans: bool = False, av_class: str = CAR) -> None:  # fmt: skip
    """Add the human ``vTypeDistribution`` and the AV ``vType`` (of SUMO class ``av_class``)
    to a route file's root.

    ``avs_as_humans``: the AV type is a copy of the human population (the all-human reference,
    where SUMO drives the AV-labelled vehicles too)."""
    attrs = _human_attrs(human, vehicle)
    types = driver_types(human)
    for type_id in (HUMAN_TYPE, AV_TYPE) if avs_as_humans else (HUMAN_TYPE,):
        dist = ET.SubElement(root, "vTypeDistribution", id=type_id)
        for k, (headway, accel) in enumerate(types):
            ET.SubElement(dist, "vType", id=f"{type_id}{k}", probability=f"{1 / len(types)}",
                          tau=f"{headway:.3f}", accel=f"{accel:.3f}", **attrs)  # fmt: skip
    if not avs_as_humans:
        ET.SubElement(
            root, "vType", id=AV_TYPE, vClass=av_class, carFollowModel="IDM",
            accel=f"{vehicle.max_accel}", decel=f"{vehicle.max_decel}", emergencyDecel="9.0",
            tau=f"{human.headway}", minGap=f"{human.min_gap}", length=f"{vehicle.length}",
            width=f"{vehicle.width}", speedFactor="1", laneChangeModel="SL2015",
            latAlignment="arbitrary", maxSpeedLat="30", lcSublane="0", color="0.85,0.1,0.1",
        )  # fmt: skip
