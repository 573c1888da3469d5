"""A scenario: network, routes, measurement segment, and the SUMO command line of an episode.

A scenario is a bundled folder (``registry``) or a user's own ``.net.xml`` / ``.sumocfg``
(``user_scenario``); both become a ``Scenario``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

from mixed_traffic.config import DEFAULT_EPISODE_LENGTH, JAM_DENSITY_PER_LANE, EnvConfig
from mixed_traffic.world.hdmap import CAR, HDMap, load_hdmap


@dataclass(frozen=True)
class Route:
    """A path through the network: explicit ``edges``, or ``from``/``to`` routed by SUMO."""

    edges: tuple[str, ...] = ()
    origin: str = ""
    destination: str = ""
    weight: float = 1.0
    """Share of the inflow entering on this route (relative)."""

    @property
    def entry(self) -> str:
        return self.edges[0] if self.edges else self.origin


@dataclass(frozen=True)
class OwnVehicle:
    """A vehicle given by the user's own route files (``Scenario.own_vehicles``)."""

    vid: str
    depart: float
    """Departure time [s]."""
    route: int
    """Index into ``Scenario.routes``."""
    vtype: str = ""
    """The user's vType (or vTypeDistribution) id; "" = SUMO's default type."""


@dataclass(frozen=True)
class Scenario:
    """A loadable scenario: network, routes, measurement segment."""

    name: str
    family: str
    split: str
    description: str
    net_file: Path
    routes: tuple[Route, ...]
    measurement: tuple[str, ...]
    """Consecutive edges of the measurement segment (DT-TF, measured density)."""
    lanes: int
    """Lanes of the main road: the reference for density (veh/km summed over lanes)."""
    sumocfg: Path | None = None
    source: Path | None = None
    """Folder of a bundled scenario's plain SUMO XML sources (None: a user's network)."""
    extra_args: tuple[str, ...] = ()
    placement_edges: tuple[str, ...] = field(default=())
    """Edges on which vehicles are placed at reset (default: all edges of the routes)."""
    periodic: bool = False
    """Close the main road into a ring with a virtual leader (see ``boundary``)."""
    density: float = 120.0
    """Default density [veh/km summed over ``lanes``], used when a config gives none."""
    episode_length: float | None = None
    """Default episode length [s], used when a config gives none (None: 120 s). A road whose
    queue takes minutes to reach the measured segment sets a longer one."""
    warmup: float | None = None
    """Default warm-up before flow metrics count [s], used when a command gives none (None:
    the command's own default)."""
    inflow: bool = False
    """An open road: vehicles enter at the density's inflow rate on a timetable, whether or not
    others left (``demand``), so a bottleneck downstream builds a queue; else each vehicle that
    leaves is replaced at the entry (``boundary``)."""
    ring: bool = False
    """The network is a closed loop (the first route's edges, in order): vehicles circle it for
    the whole episode, nobody enters or leaves."""
    own_vehicles: tuple[OwnVehicle, ...] = ()
    """A user's .sumocfg vehicles: used instead of generated demand (see ``user_scenario``)."""
    vclass: str = CAR
    """SUMO vehicle class of the AVs: the lanes they may use (``HDMap.lane_car``)."""
    av_size: tuple[float, float] | None = None
    """(length, width) [m] of a .sumocfg's AVs, from the type they derive from."""
    vtypes: tuple[str, ...] = ()
    """A user's vType / vTypeDistribution elements from its route files, as XML text (they go
    into the episode's route file; those of additional files SUMO loads itself)."""
    verbatim: tuple[tuple[float, str], ...] = ()
    """(departure [s], XML text) of what a .sumocfg's route files define that SUMO runs as
    written, in departure order: persons, containers, vehicles routed by their stops or on roads
    the AVs may not use, and the named routes these use."""
    begin: float = 0.0
    """A .sumocfg's begin [s of SUMO time]: the episode's clock starts there."""
    step_length: float | None = None
    """A .sumocfg's step length [s]: the episode adopts it."""
    end: float | None = None
    """A .sumocfg's end, in seconds after its begin [s]: episodes end there at the latest."""

    def own_in_episode(self, episode_length: float) -> list[OwnVehicle]:
        """The own vehicles that depart within an episode of ``episode_length`` [s], in
        departure order: flows are instantiated over the episode only, so ``possible_agents``
        holds the AVs an episode can have, not those of the whole file."""
        last = self.begin + episode_length
        return sorted((v for v in self.own_vehicles if v.depart <= last), key=lambda v: v.depart)

    @property
    def hdmap(self) -> HDMap:
        return load_hdmap(self.net_file, self.vclass)

    @property
    def measurement_length(self) -> float:
        """Length of the measurement segment [m]."""
        hd = self.hdmap
        return float(sum(hd.edge_length[hd.edge_of(e)] for e in self.measurement))

    @property
    def max_density(self) -> float:
        """Jam density of the main road [veh/km summed over lanes]."""
        return self.lanes * JAM_DENSITY_PER_LANE

    def configure(self, config: EnvConfig) -> EnvConfig:
        """``config`` with this scenario's default density where it gives none, checked
        against the jam density and ring length (``ValueError``)."""
        self._check_ring_length(config)
        if self.own_vehicles:
            return self._configure_own(config)
        if config.ring_vehicles is not None:
            config = replace(config, density=self._ring_density(config))
        if config.density is None:
            config = replace(config, density=self.density)
        if config.episode_length is None:
            config = replace(config, episode_length=self.episode_length or DEFAULT_EPISODE_LENGTH)
        self.check_density(config.density)
        return config

    def default_warmup(self, warmup: float | None, fallback: float, episode: float) -> float:
        """``warmup`` [s] if given, else this scenario's where it is shorter than the
        ``episode`` [s] (a shortened episode, e.g. for training, keeps no warm-up that would
        fill it), else the caller's ``fallback``."""
        if warmup is not None:
            return warmup
        return self.warmup if self.warmup is not None and self.warmup < episode else fallback

    def _configure_own(self, config: EnvConfig) -> EnvConfig:
        """A .sumocfg's own vehicles set the traffic: no density; its step length and end."""
        if config.density is not None:
            raise ValueError(
                f"density={config.density} veh/km does not apply to {self.name}: a .sumocfg "
                "drives its own vehicles (scale their flows in its route files instead)"
            )
        length = config.episode_length or DEFAULT_EPISODE_LENGTH
        length = length if self.end is None else min(length, self.end)
        vehicle = config.vehicle
        if self.av_size is not None:  # AVs the size of the file's type they derive from
            vehicle = replace(vehicle, length=self.av_size[0], width=self.av_size[1])
        return replace(config, step_length=self.step_length or config.step_length,
                       episode_length=length, vehicle=vehicle)  # fmt: skip

    def _check_ring_length(self, config: EnvConfig) -> None:
        """Raise ``ValueError`` if ``config.ring_length`` is given for a scenario that is no
        bundled ring."""
        if config.ring_length and not (self.ring and self.source is not None):
            raise ValueError(f"ring_length={list(config.ring_length)} applies to the bundled ring "
                             f"scenarios only, and {self.name!r} is none")  # fmt: skip

    def _ring_density(self, config: EnvConfig) -> float:
        """The density [veh/km] of ``config.ring_vehicles`` on the longest ring of the config
        (``ValueError`` off a ring, or against another density given with it)."""
        if not self.ring:
            raise ValueError(f"ring_vehicles={config.ring_vehicles} applies to ring scenarios "
                             f"only, and {self.name!r} is none")  # fmt: skip
        hd = self.hdmap
        loop = sum(
            float(hd.edge_length[hd.edge_of(e)]) for e in dict.fromkeys(self.routes[0].edges)
        )
        density = (
            1000.0 * config.ring_vehicles / (config.ring_length[-1] if config.ring_length else loop)
        )
        if config.density is not None and abs(config.density - density) > 1e-6:
            raise ValueError(f"ring_vehicles={config.ring_vehicles} sets the ring's density "
                             f"({density:.2f} veh/km): give it or density={config.density:g}, "
                             "not both")  # fmt: skip
        return density

    def feasible_densities(self, densities: tuple[float, ...]) -> tuple[float | None, ...]:
        """The ``densities`` [veh/km] this scenario can hold (up to its jam density), 0 as None
        (its default); ValueError naming the scenario when none fits."""
        out = tuple(d or None for d in densities if d <= self.max_density)
        if not out:
            raise ValueError(f"no density of {list(densities)} veh/km fits scenario {self.name!r}")
        return out

    def check_density(self, density: float) -> None:
        """Raise ``ValueError`` unless 0 < ``density`` [veh/km] <= the jam density."""
        if not 0 < density <= self.max_density:
            raise ValueError(
                f"density={density} veh/km is outside (0, {self.max_density:.0f}] for scenario "
                f"{self.name!r} ({self.lanes} lanes; jam density {JAM_DENSITY_PER_LANE:.0f} "
                "veh/km per lane)"
            )


def sumo_args(scenario: Scenario, config: EnvConfig, route_file: Path, seed: int) -> list[str]:
    """SUMO command line (without the binary) for one episode. A .sumocfg is SUMO's own
    configuration (additional files, begin, TLS programs, ...); these options override it."""
    return [
        *(("-c", str(scenario.sumocfg)) if scenario.sumocfg else ()),
        "--net-file", str(scenario.net_file),
        "--route-files", str(route_file),
        "--step-length", f"{config.step_length}",
        "--lateral-resolution", f"{config.lateral_resolution}",
        "--time-to-teleport", "-1",
        "--collision.action", "remove",
        "--collision.check-junctions", "true",
        "--collision.mingap-factor", "0",
        "--seed", str(seed),
        "--no-step-log", "true",
        "--no-warnings", "true",
        "--duration-log.disable", "true",
        "--eager-insert", "true",
        "--default.speeddev", "0",
        # an actionStepLength (human drivers) would switch SUMO to the ballistic update; the
        # AVs' commands are integrated with Euler steps (env/control.py), so keep Euler
        "--step-method.ballistic", "false",
        # fuel in ml (SUMO converts at each fuel's density) instead of mg, for l/100 km
        "--emissions.volumetric-fuel", "true",
        *scenario.extra_args,
    ]  # fmt: skip
