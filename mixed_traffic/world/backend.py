"""The only place that talks to SUMO (libsumo or TraCI).

libsumo runs one simulation per process, and a second ``libsumo.start()`` silently replaces the
first. ``SumoBackend`` therefore records which instance owns libsumo; a second one either falls
back to a labelled TraCI connection or raises ``SumoError`` saying why. After a ``moveToXY``
that no ``simulationStep`` followed, the next simulation's first step segfaults (libsumo 1.28),
so ``load``/``close`` always flush a pending move with one step first.
"""

from __future__ import annotations

import contextlib
import itertools
import operator
import os
import shutil
import subprocess
import warnings
from collections.abc import Collection, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mixed_traffic.world.snapshot import Collision, TrafficSnapshot, sumo_angle_to_rad

#: speedMode 32: no safe-speed, acceleration, deceleration or right-of-way checks, so the
#: policy (not SUMO) drives the AV; bit 5 set disregards right of way inside junctions too.
AV_SPEED_MODE = 32
#: laneChangeMode 0: no autonomous lane changes and TraCI changes ignore other drivers.
AV_LANE_CHANGE_MODE = 0

_labels = itertools.count()
_libsumo_owner: SumoBackend | None = None


_ITEM = tuple(operator.itemgetter(i) for i in range(5))


def _libsumo() -> Any:
    """The libsumo module, loaded when a simulation starts (it is large, and importing the
    project, e.g. for analysis, should not load it)."""
    import libsumo

    return libsumo


def _traci() -> Any:
    """The TraCI module, loaded when a simulation starts (as :func:`_libsumo`)."""
    import traci

    return traci


def _traci_vars() -> tuple[int, ...]:
    """The subscribed variables, in :meth:`SumoBackend.read`'s order."""
    import traci.constants as tc

    return (tc.VAR_POSITION3D, tc.VAR_ANGLE, tc.VAR_SPEED, tc.VAR_ACCELERATION, tc.VAR_LANE_ID,
            tc.VAR_LANEPOSITION, tc.VAR_LANEPOSITION_LAT, tc.VAR_FUELCONSUMPTION)  # fmt: skip


def _libsumo_getters() -> tuple:
    """libsumo's C-level vehicle getters in snapshot order (bypassing the Python wrappers)."""
    libsumo = _libsumo()
    ls = getattr(libsumo, "_libsumo", None)
    names = ("getPosition3D", "getAngle", "getSpeed", "getAcceleration", "getLaneID",
             "getLanePosition", "getLateralLanePosition", "getFuelConsumption")  # fmt: skip
    if ls is None:
        return tuple(getattr(libsumo.vehicle, m) for m in names)
    return tuple(getattr(ls, f"vehicle_{m}") for m in names)


class SumoError(RuntimeError):
    """SUMO could not be started or used; the message says what and why."""


def sumo_version() -> str:
    """Version of the SUMO binaries, e.g. ``1.28.0``."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("eclipse-sumo")
    except PackageNotFoundError:
        return _version_from_binary()


def _version_from_binary() -> str:
    out = subprocess.run([binary("sumo"), "--version"], capture_output=True, text=True).stdout
    first = out.splitlines()[0] if out else ""
    return first.split()[-1] if first else "unknown"


def binary(name: str) -> str:
    """Path of a SUMO executable (``sumo``, ``netconvert``, ``sumo-gui``) from the eclipse-sumo wheel."""
    try:
        import sumo

        path = Path(sumo.SUMO_HOME) / "bin" / name
        if path.exists():
            return str(path)
    except ImportError:
        pass
    found = shutil.which(name)
    if found is None:
        raise SumoError(f"SUMO executable {name!r} not found; install the eclipse-sumo package")
    return found


def libsumo_busy() -> bool:
    """True when a simulation owned by some backend is running in this process's libsumo."""
    return _libsumo_owner is not None


class SumoBackend:
    """One SUMO simulation: start/load/step/close, one-batch state reads, and vehicle commands.

    Args:
        kind: ``libsumo`` (default, fastest), ``traci``, or ``auto`` (libsumo unless busy).
        second_instance: when libsumo is already owned by another backend in this process:
            ``traci`` falls back to a TraCI connection, ``error`` raises ``SumoError``.
        gui: run ``sumo-gui`` (over TraCI) instead of ``sumo``.
    """

    def __init__(
        self, kind: str = "libsumo", second_instance: str = "traci", gui: bool = False
    ) -> None:
        if kind not in ("libsumo", "traci", "auto"):
            raise ValueError(f"backend kind {kind!r} is not one of ('libsumo', 'traci', 'auto')")
        self.second_instance = second_instance
        self._warn_fallback = kind == "libsumo"
        self.kind = "traci" if gui else "libsumo" if kind == "auto" else kind
        self.gui = gui  # libsumo has no GUI: sumo-gui is driven over TraCI
        self._check_libsumo_free()
        self._api = None
        self._label: str | None = None
        self._pending_move = False
        self._lane_row: dict[str, int] = {}
        self._lane_edge: dict[str, int] = {}
        self._lane_idx: dict[str, int] = {}
        self._edge_row: dict[str, int] = {}
        self._static: dict[str, tuple[float, float, bool, dict[int, int], int]] = {}
        self._route_pos: dict[str, int] = {}
        # edge row at which ``_route_pos`` was last resolved (-2: never)
        self._edge_last: dict[str, int] = {}
        self._lane_edge_arr = np.full(1, -1, np.int32)
        self._lane_idx_arr = np.zeros(1, np.int16)
        self.time = 0.0
        """Simulated time since the simulation's begin [s] (a .sumocfg may begin at 25200)."""
        self.begin = 0.0
        """SUMO's begin time of the running simulation [s]."""

    def _check_libsumo_free(self) -> None:
        """Fall back to TraCI (or refuse) when another backend owns libsumo in this process."""
        if self.kind != "libsumo" or not libsumo_busy() or _libsumo_owner is self:
            return
        if self.second_instance == "error":
            raise SumoError(
                "libsumo already runs a simulation in this process and allows only one; "
                "a second libsumo.start() would silently replace it. Close the first env, "
                "use backend='traci', or run the second env in another process."
            )
        if self._warn_fallback:
            warnings.warn(
                "libsumo is busy in this process; this simulation falls back to TraCI",
                RuntimeWarning,
                stacklevel=3,
            )
        self.kind = "traci"

    # ------------------------------------------------------------------ lifecycle
    @property
    def running(self) -> bool:
        return self._api is not None

    def set_lane_table(self, lane_ids: Sequence[str], lane_edges: Sequence[int]) -> None:
        """Map SUMO lane ids to rows of the HD map's lane table (and their edge rows)."""
        self._lane_row = {lid: i for i, lid in enumerate(lane_ids)}
        self._lane_edge = {lid: int(e) for lid, e in zip(lane_ids, lane_edges)}
        self._lane_idx = {lid: int(lid.rsplit("_", 1)[1]) for lid in lane_ids}
        self._edge_row.clear()
        # row -1 (unknown lane) indexes the extra last slot
        self._lane_edge_arr = np.append(np.asarray(lane_edges, np.int32), np.int32(-1))
        self._lane_idx_arr = np.fromiter(
            (self._lane_idx[lid] for lid in lane_ids), np.int16, len(lane_ids)
        )
        self._lane_idx_arr = np.append(self._lane_idx_arr, np.int16(0))
        for lid, e in zip(lane_ids, lane_edges):
            if e >= 0:
                self._edge_row[lid.rsplit("_", 1)[0]] = int(e)

    def start(self, args: Sequence[str]) -> None:
        """Start SUMO with command-line ``args`` (without the binary), or reload if running."""
        global _libsumo_owner
        if self.running:
            self.load(args)
            return
        cmd = (
            [binary("sumo-gui"), "--start", "--quit-on-end", *args]
            if self.gui
            else [binary("sumo"), *args]
        )
        self._check_libsumo_free()  # another env may have started since this one was made
        libsumo, traci = _libsumo(), _traci()
        try:
            if self.kind == "libsumo":
                libsumo.start(cmd)
                self._api = libsumo
                _libsumo_owner = self
            else:
                self._label = f"mixed_traffic_{os.getpid()}_{next(_labels)}"
                traci.start(cmd, label=self._label)
                self._api = traci.getConnection(self._label)
        except (
            libsumo.TraCIException,
            traci.exceptions.TraCIException,
            traci.exceptions.FatalTraCIError,
        ) as e:
            self._api = None
            raise SumoError(f"SUMO failed to start ({' '.join(args)}): {e}") from e
        self._after_load()

    def load(self, args: Sequence[str]) -> None:
        """Replace the running simulation (a reset) with a new one made from ``args``."""
        if not self.running:
            self.start(args)
            return
        self._flush_pending_move()
        try:
            self._api.load(list(args))
        except (_libsumo().TraCIException, _traci().exceptions.TraCIException) as e:
            raise SumoError(f"SUMO failed to load ({' '.join(args)}): {e}") from e
        self._after_load()

    def _after_load(self) -> None:
        self._static.clear()
        self._route_pos.clear()
        self._edge_last.clear()
        self._pending_move = False
        self.begin = self._api.simulation.getTime()
        self.time = 0.0

    def close(self) -> None:
        """End the simulation; safe to call twice."""
        global _libsumo_owner
        if not self.running:
            return
        with contextlib.suppress(Exception):
            self._flush_pending_move()
        with contextlib.suppress(Exception):
            self._api.close()
        if _libsumo_owner is self:
            _libsumo_owner = None
        self._api = None

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.close()

    def _flush_pending_move(self) -> None:
        # libsumo 1.28 segfaults on the next simulation's first step if a moveToXY was not stepped.
        if self._pending_move:
            self._api.simulationStep()
            self._pending_move = False

    # ------------------------------------------------------------------ stepping
    def step(self) -> TrafficSnapshot:
        """Advance one step and read every vehicle's state in one batch."""
        self._api.simulationStep()
        self._pending_move = False
        return self.collect()

    def collect(self) -> TrafficSnapshot:
        """Snapshot of the step just made: vehicle states plus the step's events.

        ``step()`` is ``raw_step()`` followed by this; call it once after each ``raw_step()``
        (benchmarks time the two parts separately).
        """
        sim = self._api.simulation
        self.time = sim.getTime() - self.begin
        departed = list(sim.getDepartedIDList())
        for vid in departed:
            self._register(vid)
        collisions = [Collision(c.collider, c.victim, c.type, c.lane) for c in sim.getCollisions()]
        crashed = {v for c in collisions for v in (c.collider, c.victim)}
        # SUMO also lists vehicles removed by a collision as arrived; they did not arrive
        arrived = [v for v in sim.getArrivedIDList() if v not in crashed]
        teleports = list(sim.getStartingTeleportIDList())
        for vid in itertools.chain(arrived, crashed):
            self._static.pop(vid, None)
            self._route_pos.pop(vid, None)
        snap = self.read()
        snap.departed, snap.arrived = departed, arrived
        snap.collisions, snap.teleports = collisions, teleports
        return snap

    def refresh_routes(self, vids: Sequence[str]) -> list[tuple[tuple[str, ...], int]]:
        """SUMO's route and route index now of each of ``vids``, whose routes SUMO changed (a
        rerouter, a rerouting device); later snapshots resolve route indices on them."""
        v, out = self._api.vehicle, []
        for vid in vids:
            route = tuple(v.getRoute(vid))
            length, width, is_av, *_ = self._static[vid]
            self._static[vid] = (length, width, is_av, self._route_positions(route), len(route))
            self._route_pos[vid] = ri = v.getRouteIndex(vid)
            out.append((route, ri))
        return out

    def _route_positions(self, route: Sequence[str]) -> dict[int, int]:
        """Edge row -> its first index in ``route`` (how snapshots resolve route indices)."""
        return {self._edge_row.get(e, -1): i for i, e in reversed(list(enumerate(route)))}

    def _register(self, vid: str) -> None:
        v = self._api.vehicle
        is_av = vid.startswith("av_")
        route = v.getRoute(vid)
        self._static[vid] = (v.getLength(vid), v.getWidth(vid), is_av,
                             self._route_positions(route), len(route))  # fmt: skip
        self._route_pos[vid] = 0
        self._edge_last[vid] = -2
        if is_av:
            v.setSpeedMode(vid, AV_SPEED_MODE)
            v.setLaneChangeMode(vid, AV_LANE_CHANGE_MODE)
        if self.kind == "traci":
            v.subscribe(vid, _traci_vars())

    def read(self) -> TrafficSnapshot:
        """Current state of every vehicle (getters on libsumo, subscriptions on TraCI)."""
        v = self._api.vehicle
        ids = list(v.getIDList())
        # vehicles present at load time never show up as departed
        for vid in set(ids).difference(self._static):
            self._register(vid)
        if self.kind == "libsumo":
            # the C functions behind libsumo's Python wrappers, mapped over all ids: no Python
            # frame per call (about half the cost of the wrapped getters)
            f = _libsumo_getters()
            pos = list(map(f[0], ids))
            angle = list(map(f[1], ids))
            speed = list(map(f[2], ids))
            accel = list(map(f[3], ids))
            lane = list(map(f[4], ids))
            lpos = list(map(f[5], ids))
            lat = list(map(f[6], ids))
            fuel = list(map(f[7], ids))
        else:
            res = v.getAllSubscriptionResults()
            pos, angle, speed, accel, lane, lpos, lat, fuel = (
                [res[i][k] for i in ids] for k in _traci_vars()
            )
        return self._assemble(ids, pos, angle, speed, accel, lane, lpos, lat, fuel)

    def _lane_rows(self, lane: list[str]) -> np.ndarray:
        """(N,) lane-table row of each lane id, -1 for lanes not in the table."""
        n = len(lane)
        try:
            return np.fromiter(map(self._lane_row.__getitem__, lane), np.int32, n)
        except KeyError:
            get = self._lane_row.get
            return np.fromiter((get(lid, -1) for lid in lane), np.int32, n)

    def _assemble(self, ids, pos, angle, speed, accel, lane, lpos, lat, fuel) -> TrafficSnapshot:
        n = len(ids)
        xyz = np.array(pos, dtype=np.float64).reshape(n, 3)
        static = list(map(self._static.__getitem__, ids))
        lane_rows = self._lane_rows(lane)
        edge = self._lane_edge_arr[lane_rows]
        # route index: resolved only for vehicles whose (normal) edge changed since last time
        last = np.fromiter(map(self._edge_last.__getitem__, ids), np.int32, n)
        for k in np.flatnonzero((edge != last) & (edge >= 0)).tolist():
            vid, e = ids[k], int(edge[k])
            self._edge_last[vid] = e
            ri = static[k][3].get(e, -1)
            if ri >= 0:
                self._route_pos[vid] = ri
        route_index = np.fromiter(map(self._route_pos.__getitem__, ids), np.int32, n)
        return TrafficSnapshot(
            time=self.time,
            ids=ids,
            is_av=np.fromiter(map(_ITEM[2], static), bool, n),
            x=xyz[:, 0].copy(),
            y=xyz[:, 1].copy(),
            z=xyz[:, 2].copy(),
            heading=sumo_angle_to_rad(np.array(angle, dtype=np.float64)),
            speed=np.array(speed, dtype=np.float64),
            accel=np.array(accel, dtype=np.float64),
            lane=lane_rows,
            lane_index=self._lane_idx_arr[lane_rows],
            lane_pos=np.array(lpos, dtype=np.float64),
            lateral=np.array(lat, dtype=np.float64),
            length=np.fromiter(map(_ITEM[0], static), np.float64, n),
            width=np.fromiter(map(_ITEM[1], static), np.float64, n),
            edge=edge,
            route_index=route_index,
            route_length=np.fromiter(map(_ITEM[4], static), np.int32, n),
            fuel=np.array(fuel, dtype=np.float64),
        )

    def raw_step(self) -> None:
        """A bare ``simulationStep`` with no reads (for benchmarks)."""
        self._api.simulationStep()
        self._pending_move = False

    # ------------------------------------------------------------------ commands
    def set_speeds(self, ids: Sequence[str], speeds: np.ndarray) -> None:
        """Speed for the next step [m/s] (AVs ignore SUMO's safety checks)."""
        set_speed = self._api.vehicle.setSpeed
        for vid, s in zip(ids, speeds.tolist()):
            set_speed(vid, s)

    def release_control(self, ids: Sequence[str]) -> None:
        """Give AVs back to SUMO: default speed mode (31) and lane-change mode (1621), so they
        drive by their vType's car-following (IDM) and lane-change models like conventional cars
        (the all-human reference)."""
        v = self._api.vehicle
        for vid in ids:
            v.setSpeedMode(vid, 31)
            v.setLaneChangeMode(vid, 1621)

    def release_speed(self, vid: str) -> None:
        """Hand a vehicle's speed back to its car-following model."""
        with contextlib.suppress(Exception):
            self._api.vehicle.setSpeed(vid, -1)

    def change_sublane(self, ids: Sequence[str], lateral_moves: np.ndarray) -> None:
        """Lateral displacement to apply in the next step [m], positive = left."""
        change = self._api.vehicle.changeSublane
        for vid, d in zip(ids, lateral_moves.tolist()):
            change(vid, d)

    def set_lateral_accel(self, ids: Sequence[str], accel_lat: float = 1000.0) -> None:
        """Lateral acceleration limit of the sublane model [m/s^2] (``lcAccelLat``).

        SUMO's default (1 m/s^2) smooths a ``changeSublane`` request over many steps; an
        externally controlled AV sets it high so each request is executed within one step (up to
        the vType's ``maxSpeedLat``·dt).
        """
        set_param = self._api.vehicle.setParameter
        for vid in ids:
            set_param(vid, "laneChangeModel.lcAccelLat", f"{accel_lat}")

    def move_to_xy(
        self,
        vid: str,
        edge: str,
        lane: int,
        x: float,
        y: float,
        angle_deg: float,
        keep_route: int = 2,
    ) -> None:
        """Place a vehicle at a pose (SUMO angle convention); flushed before any reset."""
        self._api.vehicle.moveToXY(vid, edge, lane, x, y, angle_deg, keep_route)
        self._pending_move = True

    def add_vehicle(
        self,
        vid: str,
        route_id: str,
        type_id: str,
        depart_pos: float | str = "base",
        depart_lane: int | str = "best",
        depart_speed: float | str = "max",
        destination: str = "",
    ) -> None:
        """Insert a vehicle now on an existing route (then routed to ``destination`` if given)."""
        self._api.vehicle.add(
            vid,
            route_id,
            typeID=type_id,
            depart="now",
            departLane=str(depart_lane),
            departPos=str(depart_pos),
            departSpeed=str(depart_speed),
        )
        if destination:
            self._api.vehicle.changeTarget(vid, destination)

    def remove(self, vid: str) -> None:
        """Take a vehicle out of the simulation (no-op if it is already gone)."""
        with contextlib.suppress(Exception):
            self._api.vehicle.remove(vid)
        self._static.pop(vid, None)
        self._route_pos.pop(vid, None)

    def pending(self) -> tuple[str, ...]:
        """Vehicles loaded but not inserted yet (SUMO retries them every step)."""
        return tuple(self._api.simulation.getPendingVehicles())

    def drop_pending(self, among: Collection[str]) -> list[str]:
        """Remove the vehicles of ``among`` that SUMO has not inserted yet; returns their ids.

        For vehicles placed mid-road at t = 0: one SUMO refused would otherwise appear there
        whenever a gap opens later (a vehicle waiting at an entry is normal and not dropped).
        """
        dropped = [vid for vid in self.pending() if vid in among]
        for vid in dropped:
            self.remove(vid)
        return dropped

    def vehicle_route(self, vid: str) -> tuple[str, ...]:
        return tuple(self._api.vehicle.getRoute(vid))

    # ------------------------------------------------------------------ traffic lights
    def tls_states(self, tls_ids: Sequence[str]) -> list[str]:
        """Signal strings (``rRgGyYoO...``), one character per controlled link."""
        get = self._api.trafficlight.getRedYellowGreenState
        return [get(t) for t in tls_ids]

    def must_yield(self, vehicle_ids: Sequence[str]) -> np.ndarray:
        """(N,) bool: SUMO holds the vehicle's next link closed for it (a foe has the right of
        way at a minor link, a stop sign not yet served); False without a next link."""
        links = self._api.vehicle.getNextLinks
        out = np.zeros(len(vehicle_ids), dtype=bool)
        for i, vid in enumerate(vehicle_ids):
            nxt = links(vid)
            out[i] = bool(nxt) and not nxt[0][2]  # (lane, has priority, is open, has foe, ...)
        return out

    def next_vias(self, vehicle_ids: Sequence[str]) -> list[str]:
        """The lane each vehicle enters at the end of its current lane, as SUMO chose it (at a
        lane that fans out onto several lanes of the next edge): its next link's junction
        lane, else the link's lane; "" without a next link."""
        links = self._api.vehicle.getNextLinks
        out = []
        for vid in vehicle_ids:
            nxt = links(vid)  # (lane, has priority, is open, has foe, junction lane, ...)
            out.append((nxt[0][4] or nxt[0][0]) if nxt else "")
        return out

    def tls_links(self, tls_id: str) -> list[list[tuple[str, str, str]]]:
        """For each link index: the (incoming lane, outgoing lane, via lane) triples it controls."""
        return [
            list(map(tuple, links)) for links in self._api.trafficlight.getControlledLinks(tls_id)
        ]
