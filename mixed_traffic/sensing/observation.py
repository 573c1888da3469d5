"""Per-agent multi-modal observation with history (DESIGN §6, paper §III-B), vectorised.

Public API::

    observation_space(config: EnvConfig) -> gymnasium.spaces.Dict
    builder = ObservationBuilder(config, hdmap)
    builder.reset()                                   # at every env reset
    obs = builder.build(snap, agent_ids, rows, sensed, routes)   # once per step
    builder.drop(agent_ids)                           # forget agents (e.g. re-entry in fixed_fleet)

``sensed`` is the ``PerceptionFrame`` from ``Perception.sense``; ``routes[i]`` are the edge rows
of agent i's route (its current index is ``snap.route_index[rows[i]]``).

Observation of one agent (z = ``sensors.history``, m = ``sensors.waypoints``; lanes in the order
left, current, right; history oldest first, newest last):

========== =========== ====== ========================================================
key        shape       dtype  features / normalisation (value / constant, then clip to [-1, 1])
========== =========== ====== ========================================================
ego        (z, 5)      f32    speed / 40 m/s, heading rel. lane / pi, length / 10 m,
                              width / 5 m, lateral offset (+ left) / 2 m
lanes      (3, z, 4m)  f32    per waypoint (interleaved wp0 f0..f3, wp1 f0..f3, ...):
                              altitude rel. ego / 10 m, lane index rel. ego / 4,
                              orientation rel. ego heading / pi, speed limit / 40 m/s
vehicles   (3, z, 12)  f32    front then rear vehicle, each: along-lane distance (+ ahead) /
                              lidar_range, relative velocity / 40 m/s, relative heading / pi,
                              length / 10 m, width / 5 m, lateral offset / 2 m
lights     (3, z, 4)   f32    one-hot red, yellow, green; distance to stop line / camera_range
limits     (3, k, 2)   f32    latest frame only (k = ``sensors.preview_points``): the next k
                              points along the route within ``sensors.preview_range`` where
                              the speed limit drops below every limit before it, each:
                              distance / preview_range, limit / 40 m/s; zeros = none
signals    (3,)        f32    latest frame only, from the HD map: distance to the stop line of
                              the next signal along each lane's route (at its end or the next
                              lane's) / preview_range, where within ``sensors.preview_range``;
                              zeros = none (its state is the camera's, in ``lights``)
give_way   (3,)        int8   latest frame only: 1 where the line in ``lights`` is a give-way
                              line (SUMO's right of way: a minor link, a turn waiting for
                              the oncoming stream, a permissive green), not a signal
node_mask  (3, 3)      int8   per lane: lane exists, vehicle(s) detected, light detected
action_mask (3,)       int8   allowed decisions: left change, follow, right change
downstream (S, 2)      f32    only with ``EnvConfig.v2x``: the V2X feed's mean speed / 40 m/s
                              and density / jam density in S segments ahead on the route
                              (:mod:`~mixed_traffic.sensing.v2x`); Box [0, 1]
memory     (M,)        f32    only with ``SensorConfig.memory``: slow means and spreads of the
                              own and the leader's speed and the last command
                              (:mod:`~mixed_traffic.sensing.memory`); Box [-1, 1]
========== =========== ====== ========================================================

Boxes are ``[-1, 1]`` float32 and every value is clipped into them; the masks are int8 0/1 for
the current step only: ``node_mask`` a ``Box(0, 1, (3, 3), int8)`` (TorchRL cannot convert a
2-D ``MultiBinary``), ``action_mask`` a ``MultiBinary(3)``.

Validity convention for the history: a frame that was not observed (episode start, or an
agent that appeared later) is all zeros. ``ego[t, 2]`` (length) > 0 marks an observed frame,
``vehicles`` width (columns 4 and 10) > 0 a present front/rear vehicle, and the light one-hot
sum = 1 a detected light. A missing lane is all zeros in ``lanes`` / ``vehicles`` / ``lights``.

Action mask: a lane change is allowed iff the adjacent lane exists and some lane on that side
(the adjacent one or beyond) continues the route (``hdmap.conn_to[(lane, next_route_edge)]``;
on the route's last edge every lane continues). Within ``MANDATORY_DISTANCE`` of the end of a
lane from which the route cannot continue, ``follow`` is masked (mandatory lane change) and a
virtual stopped vehicle (zero length, width of the lane) sits at the lane's end line as the
front vehicle of the current lane, unless a real vehicle is closer. The mask always allows at
least one decision: with no continuing lane on either side, follow stays allowed. Past a
next route edge shorter than ``SHORT_EDGE`` a lane continues only if the lane it lands on
there continues too.
Waypoints follow the route beyond a lane's end (first hop ``hdmap.conn_to[(lane,
next_route_edge)]`` when that lane continues the route, else the lane's primary successor; later
hops primary successors); so does the speed-limit preview (``limits``). Both come from
the HD map and are not perturbed by weather.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import repeat

import gymnasium as gym
import numpy as np

from mixed_traffic import compiled
from mixed_traffic.config import EnvConfig
from mixed_traffic.sensing import observation_kernel
from mixed_traffic.sensing.camera import NO_LIGHT, lane_signals
from mixed_traffic.sensing.frame import PerceptionFrame
from mixed_traffic.sensing.geometry import wrap_angle
from mixed_traffic.sensing.lane_graph import CURRENT, lane_graph, next_route_edge
from mixed_traffic.sensing.memory import memory_space
from mixed_traffic.sensing.merges import exit_table
from mixed_traffic.sensing.preview import drop_table, limit_preview
from mixed_traffic.world.hdmap import SPACING, HDMap
from mixed_traffic.world.snapshot import TrafficSnapshot

#: Speed scale for velocities, relative velocities and speed limits [m/s].
SPEED_SCALE = 40.0
#: Ego feature scales: speed [m/s], heading rel. lane [rad], length [m], width [m], lateral [m].
EGO_SCALE = np.array([SPEED_SCALE, np.pi, 10.0, 5.0, 2.0])
#: Waypoint feature scales: altitude [m], lane index [-], orientation [rad], speed limit [m/s].
WAYPOINT_SCALE = np.array([10.0, 4.0, np.pi, SPEED_SCALE])
#: Vehicle feature scales after the distance (divided by lidar_range): rel. velocity [m/s],
#: rel. heading [rad], length [m], width [m], lateral [m].
VEHICLE_SCALE_TAIL = np.array([SPEED_SCALE, np.pi, 10.0, 5.0, 2.0])
#: A next route edge shorter than this leaves no room for a lane change [m]: a lane counts as
#: continuing the route only if the lane it lands on there continues too.
SHORT_EDGE = 20.0
#: Distance to the end of a non-continuing lane below which a lane change is mandatory [m].
MANDATORY_DISTANCE = 100.0
#: Decisions in ``action_mask`` order.
LEFT_CHANGE, FOLLOW, RIGHT_CHANGE = 0, 1, 2


VEHICLE_DISTANCES = (0, 6)
"""Columns of ``vehicles`` holding the front and rear distances."""


def reach_of(config: EnvConfig) -> float:
    """Largest normalised distance an observation holds: 1, or the detection-range factor
    where it exceeds 1 (``SensorConfig.range_factor``)."""
    return max(1.0, config.sensors.range_factor)


def clip_far(x: np.ndarray, far: tuple[int, ...], reach: float) -> np.ndarray:
    """``x`` clipped to [-1, 1], and to [-reach, reach] in the last-axis columns ``far``."""
    out = np.clip(x, -1.0, 1.0)
    if reach > 1.0:
        out[..., list(far)] = np.clip(x[..., list(far)], -reach, reach)
    return out


def observation_space(config: EnvConfig) -> gym.spaces.Dict:
    """The per-agent observation space of DESIGN §6 for ``config``."""
    z, m = config.sensors.history, config.sensors.waypoints
    reach = reach_of(config)

    def box(*shape: int, far: tuple[int, ...] = ()) -> gym.spaces.Box:
        """[-1, 1], [-reach, reach] in the last-axis columns ``far`` (distances)."""
        high = np.ones(shape, np.float32)
        high[..., list(far)] = reach
        return gym.spaces.Box(-high, high, dtype=np.float32)

    return gym.spaces.Dict(
        {
            "ego": box(z, 5),
            "lanes": box(3, z, 4 * m),
            "vehicles": box(3, z, 12, far=VEHICLE_DISTANCES),
            "lights": box(3, z, 4, far=(3,)),
            "limits": gym.spaces.Box(0.0, 1.0, (3, config.sensors.preview_points, 2), np.float32),
            "signals": gym.spaces.Box(0.0, 1.0, (3,), np.float32),
            "give_way": gym.spaces.Box(0, 1, (3,), np.int8),
            "node_mask": gym.spaces.Box(0, 1, (3, 3), np.int8),
            "action_mask": gym.spaces.MultiBinary(3),
            **({"downstream": downstream_space(config)} if config.v2x else {}),
            **({"memory": memory_space(config)} if config.sensors.memory else {}),
        }
    )


def downstream_space(config: EnvConfig) -> gym.spaces.Box:
    """``Box(0, 1, (S, 2), float32)`` of the V2X key ``downstream`` (``sensing.v2x``)."""
    return gym.spaces.Box(0.0, 1.0, (len(config.v2x_feed.segments) - 1, 2), np.float32)


class ObservationBuilder:
    """Builds the observations of all agents in one vectorised pass and keeps their history.

    Args:
        config: the env config (sensor ranges, z, m).
        hdmap: the network.
    """

    def __init__(self, config: EnvConfig, hdmap: HDMap) -> None:
        self.config = config
        self.hdmap = hdmap
        self.graph = lane_graph(hdmap)
        self.last_batch: dict[str, np.ndarray] = {}
        self.z = config.sensors.history
        self.m = config.sensors.waypoints
        s = config.sensors
        self._veh_scale = np.concatenate([[s.lidar_range], VEHICLE_SCALE_TAIL])
        self._reach = reach_of(config)
        self._wp_scale = np.tile(WAYPOINT_SCALE, self.m)
        self._map_args: tuple | None = None  # the kernel's map arrays, built at first use
        self.reset()

    # ------------------------------------------------------------------ history slots
    def reset(self) -> None:
        """Forget every agent's history (call at env reset)."""
        self._slot: dict[str, int] = {}
        self._ego = np.zeros((0, self.z, 5), np.float32)
        self._lanes = np.zeros((0, 3, self.z, 4 * self.m), np.float32)
        self._veh = np.zeros((0, 3, self.z, 12), np.float32)
        self._lights = np.zeros((0, 3, self.z, 4), np.float32)
        self._free: list[int] = []
        self._grow(64)

    def drop(self, agent_ids: Sequence[str]) -> None:
        """Forget the history of ``agent_ids``; they start with zeros if built again."""
        for a in agent_ids:
            slot = self._slot.pop(a, None)
            if slot is not None:
                self._free.append(slot)

    def _grow(self, capacity: int) -> None:
        """Enlarge the history buffers to ``capacity`` slots, keeping existing histories."""
        n = len(self._ego)
        for name in ("_ego", "_lanes", "_veh", "_lights"):
            old = getattr(self, name)
            new = np.zeros((capacity, *old.shape[1:]), np.float32)
            new[:n] = old
            setattr(self, name, new)
        self._free.extend(range(capacity - 1, n - 1, -1))  # pop() takes the lowest first

    def _slots(self, agent_ids: Sequence[str]) -> np.ndarray:
        # usual step: every agent has a slot, looked up without a Python-level loop
        known = np.fromiter(map(self._slot.get, agent_ids, repeat(-1)), np.int64, len(agent_ids))
        if (known >= 0).all():
            return known
        out = np.empty(len(agent_ids), dtype=np.int64)
        for i, a in enumerate(agent_ids):
            s = self._slot.get(a)
            if s is None:
                if not self._free:
                    self._grow(2 * len(self._ego))
                s = self._free.pop()
                self._slot[a] = s
                self._ego[s] = 0.0
                self._lanes[s] = 0.0
                self._veh[s] = 0.0
                self._lights[s] = 0.0
            out[i] = s
        return out

    # ------------------------------------------------------------------ build
    def build(
        self,
        snap: TrafficSnapshot,
        agent_ids: Sequence[str],
        rows: np.ndarray,
        sensed: PerceptionFrame,
        routes: Sequence[Sequence[int]] | np.ndarray,
        extra: dict[str, np.ndarray] | None = None,
        dicts: bool = True,
    ) -> dict[str, dict[str, np.ndarray]]:
        """Observations of all agents; shifts each built agent's history by one frame.

        Args:
            snap: the current snapshot.
            agent_ids: (A,) agent ids, aligned with ``rows`` and ``sensed``.
            rows: (A,) snapshot rows of the agents.
            sensed: the sensed ``PerceptionFrame`` for the same rows.
            routes: per agent, the edge rows of its route (or (A, W) of them padded with -1).
            extra: further keys built elsewhere, ``{key: (A, ...)}`` in the order of
                ``agent_ids`` (the V2X ``downstream``).
            dicts: False builds only ``last_batch`` and returns ``{}``.
        Returns:
            ``{agent_id: {key: array}}`` per the module table; arrays are fresh copies. The
            per-agent arrays are views of ``last_batch`` (``{key: (A, ...)}``, rows in the
            order of ``agent_ids``).
        """
        rows = np.asarray(rows, dtype=np.int64)
        A = len(rows)
        if A == 0:
            return {}
        nxt = next_route_edge(routes, snap.route_index[rows])
        after = next_route_edge(routes, snap.route_index[rows] + 1)
        frame = self._frame_compiled if compiled.enabled() else self._frame
        ego, wp, veh, lights, limits, signals, gw, node, act = frame(snap, rows, sensed, nxt, after)

        slots = self._slots(agent_ids)
        h_ego = _push(self._ego, slots, ego, axis=1)
        h_lanes = _push(self._lanes, slots, wp, axis=2)
        h_veh = _push(self._veh, slots, veh, axis=2)
        h_lights = _push(self._lights, slots, lights, axis=2)
        self.last_batch = {"ego": h_ego, "lanes": h_lanes, "vehicles": h_veh, "lights": h_lights,
                           "limits": limits, "signals": signals, "give_way": gw,
                           "node_mask": node, "action_mask": act, **(extra or {})}  # fmt: skip
        if not dicts:
            return {}
        # list(array) makes the per-agent views in C; a dict literal per agent is the cheapest
        out = {
            a: {"ego": e, "lanes": ln, "vehicles": v, "lights": li, "limits": lm,
                "signals": sg, "give_way": g, "node_mask": nm, "action_mask": am}
            for a, e, ln, v, li, lm, sg, g, nm, am in zip(
                agent_ids, list(h_ego), list(h_lanes), list(h_veh), list(h_lights),
                list(limits), list(signals), list(gw), list(node), list(act))
        }  # fmt: skip
        for key, arr in (extra or {}).items():
            for o, x in zip(out.values(), list(arr)):
                o[key] = x
        return out

    # ------------------------------------------------------------------ features
    def _frame(
        self, snap: TrafficSnapshot, rows: np.ndarray, sensed: PerceptionFrame, nxt: np.ndarray,
        after: np.ndarray,
    ) -> tuple[np.ndarray, ...]:  # fmt: skip
        """The current frame of the agents at ``rows`` (A,), whose next two route edges are
        ``nxt`` and ``after`` (A,): ego (A, 5), waypoints (A, 3, 4m), vehicles (A, 3, 12) and
        lights (A, 3, 4) float64, before the history; limits (A, 3, k, 2) and signals (A, 3)
        float32; give_way (A, 3), node_mask (A, 3, 3) and action_mask (A, 3) int8. The numpy
        reference of ``observation_kernel.features``."""
        A = len(rows)
        lanes = sensed.neighbours.lane  # (A, 3)
        exists = lanes >= 0
        act, mandatory, end_dist = self.action_mask(snap, rows, lanes, nxt, after)
        ego = np.clip(sensed.ego / EGO_SCALE, -1.0, 1.0)  # (A, 5)
        pos, via = self._route_hops(snap, rows, lanes, nxt)
        wp = self._waypoints(snap, rows, lanes, pos, via)  # (A, 3, 4m)
        limits = self._limits(lanes, pos, via)  # (A, 3, k, 2)
        signals = self._signals(lanes, pos, nxt, via, after)  # (A, 3)
        veh, present = self._vehicles(sensed, lanes, mandatory, end_dist, snap.speed[rows])
        light_on = sensed.light_state != NO_LIGHT
        lights = np.zeros((A, 3, 4))
        lights[..., :3] = (sensed.light_state[..., None] == np.arange(3)) & light_on[..., None]
        lights[..., 3] = np.where(
            light_on, sensed.light_dist / self.config.sensors.camera_range, 0.0
        )
        lights = clip_far(lights, (3,), self._reach)
        node = np.stack([exists, present, light_on & exists], axis=-1).astype(np.int8)
        gw = np.zeros((A, 3), np.int8)
        gw[:, CURRENT] = sensed.give_way & light_on[:, CURRENT]
        return ego, wp, veh, lights, limits, signals, gw, node, act.astype(np.int8)

    def _frame_compiled(
        self, snap: TrafficSnapshot, rows: np.ndarray, sensed: PerceptionFrame, nxt: np.ndarray,
        after: np.ndarray,
    ) -> tuple[np.ndarray, ...]:  # fmt: skip
        """:meth:`_frame` in one compiled kernel (equal bit for bit)."""
        if self._map_args is None:
            hd, s = self.hdmap, self.config.sensors
            self._map_args = observation_kernel.map_arrays(
                hd, self.graph, hd.ahead_table(self.m), exit_table(hd),
                drop_table(hd, s.preview_points, s.preview_range),
            )  # fmt: skip
        nb, s = sensed.neighbours, self.config.sensors
        return observation_kernel.features(
            rows, nb.lane, nxt, after, snap.lane_pos, snap.z, snap.heading, snap.speed,
            sensed.ego, sensed.vehicles, nb.vehicle >= 0, sensed.light_state, sensed.light_dist,
            sensed.give_way, *self._map_args, EGO_SCALE, self._wp_scale, self._veh_scale,
            self._reach, s.camera_range, s.preview_range, SPEED_SCALE, SPACING, SHORT_EDGE,
            MANDATORY_DISTANCE,
        )  # fmt: skip

    def _route_hops(
        self, snap: TrafficSnapshot, rows: np.ndarray, lanes: np.ndarray, next_edge: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(A, 3) the ego's position projected onto each lane column [m] (scaled by the lane
        lengths), and the lane each column's route hop enters at its end: its connection to
        the route's next edge (``hdmap.conn_to``), -1 where it has none. Where a lane fans out
        this stays the map's first connection even when SUMO takes another: SUMO moves the
        vehicle along the junction lane it takes, and steering along that lane's shift too
        moved AVs a lane further (A10KW: 27 off-road events in 300 s)."""
        hd = self.hdmap
        cur = np.maximum(lanes[:, CURRENT], 0)
        lsafe = np.maximum(lanes, 0)
        ratio = hd.lane_length[lsafe] / np.maximum(hd.lane_length[cur], 1e-9)[:, None]
        pos = snap.lane_pos[rows][:, None] * ratio
        nxt = np.broadcast_to(np.asarray(next_edge, np.int64)[:, None], lanes.shape)
        via = np.where(lanes >= 0, self.graph.connection(lsafe, nxt), -1)
        return pos, via

    def _limits(self, lanes: np.ndarray, pos: np.ndarray, via: np.ndarray) -> np.ndarray:
        """(A, 3, k, 2) the speed-limit preview (:mod:`~mixed_traffic.sensing.preview`) as
        (distance / preview_range, limit / SPEED_SCALE), zeros where no drop is seen."""
        hd, s = self.hdmap, self.config.sensors
        lsafe = np.maximum(lanes, 0)
        hop = np.where(via >= 0, via, np.where(lanes >= 0, hd.lane_next[lsafe], -1))
        dist, speed = limit_preview(hd, lanes, pos, hop, s.preview_points, s.preview_range)
        seen = np.isfinite(dist)
        out = np.zeros((*dist.shape, 2), np.float32)
        out[..., 0] = np.where(seen, dist / s.preview_range, 0.0)
        out[..., 1] = np.where(seen, speed / SPEED_SCALE, 0.0)
        return out

    def _signals(self, lanes: np.ndarray, pos: np.ndarray, next_edge: np.ndarray,
                 via: np.ndarray, after: np.ndarray) -> np.ndarray:  # fmt: skip
        """(A, 3) distance from ``pos`` (A, 3) [m] to the next signal's stop line along each lane
        column's route: at the lane's end into ``next_edge`` (A,), else at the end of the lane
        its route hop ``via`` (A, 3) leads into, towards ``after`` (A,); / preview_range where
        within it, 0 elsewhere (so a signal behind a short edge is known in time)."""
        hd, rng = self.hdmap, self.config.sensors.preview_range
        if len(self.graph.tls_ids) == 0:  # a network without signals
            return np.zeros(lanes.shape, np.float32)
        tl, _ = lane_signals(self.graph, lanes, np.asarray(next_edge, np.int64))
        dist = hd.lane_length[np.maximum(lanes, 0)] - pos
        exit_lane, exit_dist = exit_table(hd)
        vs = np.maximum(via, 0)
        beyond = np.where(via < 0, -1, np.where(exit_lane[vs] >= 0, exit_lane[vs], via))
        tl2, _ = lane_signals(self.graph, beyond, np.asarray(after, np.int64))
        far = (
            dist
            + np.where(exit_lane[vs] >= 0, exit_dist[vs], 0.0)
            + hd.lane_length[np.maximum(beyond, 0)]
        )
        dist = np.where(tl >= 0, dist, np.where((tl2 >= 0) & (beyond >= 0), far, np.inf))
        on = (lanes >= 0) & (dist <= rng)
        return np.where(on, np.clip(dist / rng, 1e-4, 1.0), 0.0).astype(np.float32)

    def _waypoints(
        self,
        snap: TrafficSnapshot,
        rows: np.ndarray,
        lanes: np.ndarray,
        pos: np.ndarray,
        via: np.ndarray,
    ) -> np.ndarray:
        """(A, 3, 4m) normalised waypoint features of the m waypoints ahead on each lane.

        Beyond a lane's end the first hop follows the agent's route (``via``, see
        :meth:`_route_hops`) where the lane continues it, else the lane's primary successor;
        later hops follow primary successors."""
        hd, m = self.hdmap, self.m
        A = len(rows)
        cur = lanes[:, CURRENT]
        lsafe = np.maximum(lanes, 0)
        w0 = hd.waypoint_at(lsafe.ravel(), pos.ravel()).reshape(A, 3)
        wp = hd.ahead_table(m)[w0]  # (A, 3, m) along primary successors
        use = via >= 0
        if use.any():
            left = hd.wp_offset[lsafe] + hd.wp_count[lsafe] - 1 - w0  # wps left on lane
            j = np.arange(m)
            k = j[None, None, :] - left[..., None] - 1  # index into the successor's table
            succ = hd.ahead_table(m)[hd.wp_offset[np.maximum(via, 0)]]  # (A, 3, m)
            on_succ = np.take_along_axis(succ, np.clip(k, 0, m - 1), axis=2)
            wp = np.where(use[..., None] & (k >= 0), on_succ, wp)
        ego_lane_idx = hd.lane_index[np.maximum(cur, 0)].astype(np.float64)
        feats = np.empty((A, 3, m, 4))
        feats[..., 0] = hd.wp_xyz[wp, 2] - snap.z[rows][:, None, None]
        feats[..., 1] = hd.wp_lane_index[wp] - ego_lane_idx[:, None, None]
        feats[..., 2] = wrap_angle(hd.wp_heading[wp] - snap.heading[rows][:, None, None])
        feats[..., 3] = hd.wp_speed[wp]
        out = np.clip(feats.reshape(A, 3, 4 * m) / self._wp_scale, -1.0, 1.0)
        return np.where((lanes >= 0)[..., None], out, 0.0)

    def _vehicles(
        self,
        sensed: PerceptionFrame,
        lanes: np.ndarray,
        mandatory: np.ndarray,
        end_dist: np.ndarray,
        ego_speed: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(A, 3, 12) normalised front/rear features, with the virtual end-of-lane vehicle;
        and (A, 3) bool "vehicle(s) detected"."""
        veh = sensed.vehicles.copy()  # (A, 3, 2, 6)
        found = sensed.neighbours.vehicle >= 0  # (A, 3, 2)
        cur_front = veh[:, CURRENT, 0]
        virt = mandatory & (~found[:, CURRENT, 0] | (end_dist < cur_front[:, 0]))
        width = self.hdmap.lane_width[np.maximum(lanes[:, CURRENT], 0)]
        virtual = np.stack(
            [end_dist, -ego_speed, np.zeros_like(end_dist), np.zeros_like(end_dist), width,
             np.zeros_like(end_dist)], axis=1
        )  # fmt: skip
        veh[:, CURRENT, 0] = np.where(virt[:, None], virtual, cur_front)
        found[:, CURRENT, 0] |= virt
        out = clip_far(veh / self._veh_scale, (0,), self._reach)
        out = np.where(found[..., None], out, 0.0).reshape(len(veh), 3, 12)
        return out, found.any(axis=2)

    def action_mask(
        self, snap: TrafficSnapshot, rows: np.ndarray, lanes: np.ndarray, next_edge: np.ndarray,
        after: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
        """(A, 3) bool allowed (left, follow, right); (A,) bool mandatory-change zone; (A,)
        distance from the front bumper to the current lane's end [m]. ``after``: (A,) the
        route edge after ``next_edge`` (-1 none); a lane whose connection lands on a lane of a
        next edge shorter than ``SHORT_EDGE`` that cannot reach it does not continue."""
        hd, g = self.hdmap, self.graph
        cur = lanes[:, CURRENT]
        csafe = np.maximum(cur, 0)
        edge = np.where(cur >= 0, hd.lane_edge[csafe], -1)
        esafe = np.maximum(edge, 0)
        edge_lanes = hd.edge_lanes[esafe].astype(np.int64)  # (A, K)
        k = np.arange(edge_lanes.shape[1])
        valid = (edge_lanes >= 0) & (edge >= 0)[:, None]
        via = g.connection(edge_lanes, np.broadcast_to(next_edge[:, None], edge_lanes.shape))
        cont = (via >= 0) & self._through_short_edge(via, next_edge, after)
        cont = valid & (cont | (next_edge < 0)[:, None])
        idx = hd.lane_index[csafe].astype(np.int64)[:, None]
        left_ok = lanes[:, 0] >= 0
        right_ok = lanes[:, 2] >= 0
        left_ok &= (cont & (k > idx)).any(axis=1)
        right_ok &= (cont & (k < idx)).any(axis=1)
        cur_cont = (cont & (k == idx)).any(axis=1) | (edge < 0)
        end_dist = hd.lane_length[csafe] - snap.lane_pos[rows]
        mandatory = ~cur_cont & (end_dist <= MANDATORY_DISTANCE) & (edge >= 0)
        follow = ~mandatory | ~(left_ok | right_ok)
        return np.stack([left_ok, follow, right_ok], axis=1), mandatory, end_dist

    def _through_short_edge(
        self, via: np.ndarray, next_edge: np.ndarray, after: np.ndarray
    ) -> np.ndarray:
        """(A, K) bool: through the connections ``via`` (A, K) of a lane into ``next_edge``
        (A,), the route goes on past it: True unless it is shorter than ``SHORT_EDGE`` and the
        lane the connection lands on has no connection into ``after`` (imported networks split
        roads into edges of centimetres, on which no lane change fits)."""
        hd, g = self.hdmap, self.graph
        short = (next_edge >= 0) & (after >= 0)
        short &= hd.edge_length[np.maximum(next_edge, 0)] < SHORT_EDGE
        if not short.any():
            return np.ones(via.shape, bool)
        exit_lane, _ = exit_table(hd)
        vsafe = np.maximum(via, 0)
        land = np.where(hd.lane_edge[vsafe] >= 0, via, exit_lane[vsafe])
        on = g.connection(land, np.broadcast_to(after[:, None], via.shape)) >= 0
        return ~short[:, None] | (via < 0) | on


def _push(buf: np.ndarray, slots: np.ndarray, frame: np.ndarray, axis: int) -> np.ndarray:
    """Shift the history of ``slots`` one frame back along ``axis`` (of the per-slot array,
    +1 for the slot axis), append ``frame``, store, and return the (copied) histories."""
    n = len(slots)
    contiguous = n and slots[-1] - slots[0] == n - 1 and (np.diff(slots) == 1).all()
    # usual case: shift in place in a view, then one copy out; else gather a copy
    hist = buf[slots[0] : slots[0] + n] if contiguous else buf[slots]
    if axis == 1:
        hist[:, :-1] = hist[:, 1:]
        hist[:, -1] = frame
    else:
        hist[:, :, :-1] = hist[:, :, 1:]
        hist[:, :, -1] = frame
    if contiguous:
        return hist.copy()
    buf[slots] = hist
    return hist
