"""Perception: ground-truth neighbour search and the AV's sensors with weather noise (paper §III-B).

The stage, one module per part (A = number of queried agents, N = vehicles in the snapshot):

- ``lane_graph``: ``LaneGraph`` lookups, ``tls_ids(hdmap)`` (order of the light state strings),
  ``next_route_edge(routes, route_index)``.
- ``neighbours``: ``find_neighbours(snap, hdmap, rows, max_range, next_edge) -> Neighbours``,
  ground truth; for each agent and each of its lanes (left, current, right) = columns 0, 1, 2,
  the lane row and the front / rear vehicle within ``max_range`` metres along the lane.
- ``blockers``: ``path_blockers(...)``, the nearest vehicle across each agent's path ahead on
  another (junction) lane; ``find_neighbours`` reports it as the lane's front vehicle when nearer.
- ``lidar`` (vehicle features), ``camera`` (traffic lights), ``gnss`` (ego features), ``noise``
  (``WEATHER_PRESETS``, ``degrade``), ``geometry`` (``bumper_gap``, ``ttc``, ``wrap_angle``).
- This module: ``Perception(sensors, hdmap, weather).sense(snap, rows, next_edge, tls_states,
  rng) -> (truth, sensed)``, two ``PerceptionFrame``.

The env calls, once per step::

    nxt = next_route_edge(routes, snap.route_index[rows])
    truth, sensed = perception.sense(snap, rows, nxt, backend.tls_states(perception.tls_ids), rng)

and uses ``truth`` for rewards/metrics and ``sensed`` for observations. With
``SensorConfig.noise=False``, ``sensed is truth``.

Conventions
-----------
* Along-lane distance is front bumper to front bumper (SUMO ``lanePosition``), + = ahead.
  A missing vehicle has row -1 and distance +inf (front) / -inf (rear), so gaps and TTCs of
  missing vehicles are +inf without special cases.
* The search follows each lane across its end into its successor (through junction lanes),
  up to ``SEARCH_DEPTH`` lanes deep, and behind into one predecessor per lane (the lane whose
  primary successor it is). For the first hop ahead the route is used when ``next_edge`` is
  given (``hdmap.conn_to[(lane, next_edge)]``), else the primary successor ``hdmap.lane_next``.
* Vehicles across the path: a vehicle on another lane of a junction the ego's path crosses
  (the current lane and its successors within range) whose body comes within half the ego's
  width of the path is the current lane's front vehicle when its bumper gap is smaller
  (``path_blockers``). Its distance is the bumper gap along the path + its body's extent along
  the path, and its features are measured in the path's frame (``PATH_GEOMETRY``): length and
  width are its extents along / across the path, the relative velocity is its speed along the
  path minus the ego's, the lateral offset is its centre's offset from the path.
* Sublane model: a vehicle straddling two lanes is in the lane SUMO reports for it, which is
  the lane holding its centre; its ``lateral`` offset (feature) shows the overlap. A vehicle
  among the first ``STRADDLE_DEPTH`` ahead on a neighbour lane whose body overlaps the ego's
  laterally is also the current lane's front vehicle when nearer (two cars can share a lane
  side by side, and the nearer one would hide it); like a vehicle across the path, its
  features are then in the ego lane's frame (``path_geometry``). Of two cars side by side on
  a neighbour lane (bodies overlapping along it), that lane's front / rear vehicle is the one
  laterally nearer the ego (``_nearer_beside``): the other may be a few cm nearer along the
  lane while this one straddles towards the ego.
* On a neighbour lane the agent's position is projected by the lane-length ratio
  (lanes of one edge have near-equal lengths; curves make them differ slightly).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mixed_traffic.config import SensorConfig
from mixed_traffic.sensing.camera import NO_LIGHT, give_way, traffic_lights
from mixed_traffic.sensing.frame import PerceptionFrame
from mixed_traffic.sensing.gnss import ego_features
from mixed_traffic.sensing.lane_graph import CURRENT, lane_graph
from mixed_traffic.sensing.lidar import vehicle_features
from mixed_traffic.sensing.neighbours import find_neighbours
from mixed_traffic.sensing.noise import (
    WEATHER_PRESETS,
    WeatherPreset,
    degrade,
    noise_draws,
    within_range,
)
from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.snapshot import TrafficSnapshot


class Perception:
    """LiDAR (vehicles), camera (traffic lights) and GNSS/IMU (ego) over ground truth.

    Args:
        sensors: ranges and the noise switch.
        hdmap: the network.
        weather: preset name or ``WeatherPreset``.
    """

    def __init__(self, sensors: SensorConfig, hdmap: HDMap, weather: str | WeatherPreset) -> None:
        if isinstance(weather, str):
            if weather not in WEATHER_PRESETS:
                raise ValueError(f"weather={weather!r} is not one of {tuple(WEATHER_PRESETS)}")
            weather = WEATHER_PRESETS[weather]
        self.sensors = sensors
        self.hdmap = hdmap
        self.weather = weather
        self.graph = lane_graph(hdmap)

    @property
    def tls_ids(self) -> list[str]:
        """Light ids whose ``backend.tls_states`` strings ``sense`` expects, in this order."""
        return self.graph.tls_ids

    def sense(
        self,
        snap: TrafficSnapshot,
        rows: np.ndarray,
        next_edge: np.ndarray,
        tls_states: Sequence[str],
        rng: np.random.Generator,
        gates: np.ndarray | None = None,
        via: np.ndarray | None = None,
    ) -> tuple[PerceptionFrame, PerceptionFrame]:
        """Ground truth and sensed frames for the agents at snapshot ``rows`` (A,).

        Args:
            next_edge: (A,) next route edge row of each agent, -1 on its last edge.
            tls_states: state strings of ``self.tls_ids`` (``backend.tls_states``).
            rng: the env's generator; the only source of randomness.
            gates: (A,) int8 camera code of the stop line where the agent's lane gives way at an
                unsignalised junction: RED while SUMO holds the link closed, GREEN while open,
                NO_LIGHT where the lane has none (``camera.give_way``).
            via: (A,) lane the agent's lane leads into where SUMO chose among several (a lane
                that fans out, ``HDMap.lane_fans``), -1 elsewhere (the map's connection).
        Returns:
            ``(truth, sensed)``; truth uses the nominal ranges and no noise. ``sensed is truth``
            when ``sensors.noise`` is False.
        """
        rows = np.asarray(rows, dtype=np.int64)
        next_edge = np.asarray(next_edge, dtype=np.int64)
        s = self.sensors
        far = max(1.0, s.range_factor)  # the truth keeps at least the nominal ranges
        nb = find_neighbours(snap, self.hdmap, rows, s.lidar_range * far, next_edge, via)
        state, dist = traffic_lights(
            self.graph, self.hdmap, snap, rows, nb.lane, next_edge, tls_states
        )
        yields = np.zeros(len(rows), bool)
        if gates is not None and (gates != NO_LIGHT).any():
            yields = give_way(self.hdmap, snap, rows, nb.lane[:, CURRENT], gates, state, dist)
        cam = s.camera_range * far
        state = np.where(dist <= cam, state, NO_LIGHT).astype(np.int8)
        dist = np.where(state != NO_LIGHT, dist, np.inf)
        truth = PerceptionFrame(nb, vehicle_features(snap, rows, nb), ego_features(snap, self.hdmap, rows),
                                state, dist, yields)  # fmt: skip
        if not s.noise:
            return truth, truth if s.range_factor == 1 else within_range(truth, s, 1.0, 1.0)
        return truth, degrade(truth, self.weather, s, rng)

    def skip_noise(self, n_agents: int, rng: np.random.Generator) -> None:
        """Consume exactly the random numbers ``sense`` would draw for ``n_agents`` agents,
        for a caller that only needs ground truth but must keep the noise stream unchanged."""
        if self.sensors.noise:
            noise_draws(rng, n_agents)
