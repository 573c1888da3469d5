"""A task's normalised score: 0 = all-human traffic, 1 = the task's reference.

On the ring the reference is the uniform flow of its human drivers: every vehicle at the IDM
equilibrium speed for the ring's spacing (the human model's T and s0, the limit as desired
speed), the speed a perfect smoother could reach. Elsewhere it is the best bundled controller's
measured value, given by the caller.
"""

from __future__ import annotations

from mixed_traffic.config import EnvConfig
from mixed_traffic.world.demand import idm_equilibrium_speed
from mixed_traffic.world.registry import load_scenario


def uniform_flow_speed(config: EnvConfig, ring_length: float) -> float:
    """Equilibrium speed [m/s] of ``config.ring_vehicles`` vehicles on a one-lane ring of
    ``ring_length`` [m] under the human model of ``config`` (``ValueError`` off a ring)."""
    scenario = load_scenario(config.scenario)
    if not scenario.ring or config.ring_vehicles is None:
        raise ValueError(
            f"uniform_flow_speed needs a ring with ring_vehicles, not {config.scenario!r}"
        )
    hd = scenario.hdmap
    limit = float(hd.lane_speed[hd.car_lane_rows(hd.edge_of(scenario.routes[0].entry))].max())
    spacing = ring_length * scenario.lanes / config.ring_vehicles
    return idm_equilibrium_speed(spacing, limit, config.human, config.vehicle.length)


def normalised(value: float, human: float, reference: float) -> float:
    """(value - human) / (reference - human): 0 all human, 1 the reference (``ValueError`` when
    the two coincide)."""
    if abs(reference - human) < 1e-9:
        raise ValueError(f"reference {reference} equals the all-human value: no scale")
    return (value - human) / (reference - human)
