"""A task's normalised score: 0 = all-human traffic, 1 = the task's reference.

On the ring the reference is the uniform flow of its human drivers: every vehicle at the IDM
equilibrium speed for the ring's spacing (the human model's T and s0, the limit as desired
speed), the speed a perfect smoother could reach. On an open road it is the free flow of the
measurement segment: every vehicle at its desired speed, the limit (the human drivers' speed
factor has mean 1), length-weighted over the segment's edges. Both come from the scenario and
the human model alone, never from a measured controller: a "best controller" reference
collapses where no controller beats all-human traffic (then the scale is noise, or has the
wrong sign).
"""

from __future__ import annotations

from mixed_traffic.config import EnvConfig
from mixed_traffic.world.demand import fastest_limit
from mixed_traffic.world.demand import uniform_flow_speed as ring_uniform_flow
from mixed_traffic.world.registry import load_scenario


def uniform_flow_speed(config: EnvConfig, ring_length: float) -> float:
    """Equilibrium speed [m/s] of ``config.ring_vehicles`` vehicles on a one-lane ring of
    ``ring_length`` [m] under the human model of ``config`` (``ValueError`` off a ring)."""
    scenario = load_scenario(config.scenario)
    if not scenario.ring or config.ring_vehicles is None:
        raise ValueError(
            f"uniform_flow_speed needs a ring with ring_vehicles, not {config.scenario!r}"
        )
    return ring_uniform_flow(scenario, config, ring_length)


def free_flow_speed(config: EnvConfig) -> float:
    """Length-weighted mean [m/s] over the measurement segment's edges of their fastest car
    lane's limit: the segment's mean speed without any congestion."""
    scenario = load_scenario(config.scenario)
    hd = scenario.hdmap
    limits = [fastest_limit(hd, e) for e in scenario.measurement]
    lengths = [float(hd.edge_length[hd.edge_of(e)]) for e in scenario.measurement]
    return sum(v * n for v, n in zip(limits, lengths)) / sum(lengths)


def normalised(value: float, human: float, reference: float) -> float:
    """(value - human) / (reference - human): 0 all human, 1 the reference (``ValueError`` when
    the two coincide)."""
    if abs(reference - human) < 1e-9:
        raise ValueError(f"reference {reference} equals the all-human value: no scale")
    return (value - human) / (reference - human)
