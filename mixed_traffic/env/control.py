"""Kinematic bicycle model in the lane's Frenet frame, applied to SUMO (paper §IV-D, DESIGN §7).

Model (centre-of-gravity reference). The reference point is the centre of gravity, which sits
``l_r = wheelbase / 2`` in front of the rear axle (``VehicleConfig.wheelbase``: "the rear axle
sits at half of it"). With front steering angle ``δ`` (positive = left) the side-slip angle of
the CoG velocity is ``β = atan(l_r / L · tan δ)`` and the yaw rate ``r = v · sin β / l_r``. In
the Frenet frame of the lane (arc length ``s``, lateral offset ``d`` positive = left, yaw
relative to the lane ``ψ``, lane curvature ``κ`` from the HD map's waypoint headings)::

    v'  = clip(v + a·dt, 0, ∞)                      (no reversing)
    ṡ   = v' · cos(ψ + β) / (1 − κ·d)
    ḋ   = v' · sin(ψ + β)
    ψ̇   = r − κ·ṡ

integrated over one step ``dt`` with the new speed ``v'`` (SUMO's Euler update also moves a
vehicle by its new speed) and the midpoint yaw. The course angle relative to the lane is
clipped to ±``max_course`` (80°) because a SUMO vehicle cannot move backwards along its lane.

Applying it: ``setSpeed(ṡ)`` (the speed along the lane, which is what SUMO advances the lane
position by) plus ``changeSublane(d(t+dt) − d(t))``. The AV's ``lcAccelLat`` is raised
(``SumoBackend.set_lateral_accel``) so SUMO executes the whole lateral move in one step (up to
the vType's ``maxSpeedLat`` = 30 m/s). Measured with libsumo 1.28 (``measure_mechanisms``,
straight, 120 veh/km, all AVs): 0.5-0.6 µs per vehicle for both calls together against 2.6-19 µs for
``moveToXY(keepRoute=2)`` on this 3-edge network (DESIGN §5 quotes ≈35 µs on larger networks,
where keepRoute=2's map search grows); setSpeed+changeSublane wins either way.

What SUMO reports back. ``lane_pos``/``lateral`` follow the model exactly (to float precision).
SUMO's heading is NOT the course angle: SUMO 1.28 draws the body from the front bumper to a
rear point that trails the front's lateral path, so with ``e = d_front − d_rear``
``e ← e·(1 − ds/length) + dd`` each step and heading = lane heading + ``atan2(e, length)``.
The controller tracks ``e`` so the heading SUMO will report is predicted exactly
(``predicted_sumo_heading``); its lag behind the model's course angle ``ψ + β`` is a few
degrees in a lane change at highway speed (measured in ``tests/test_control.py``).
SUMO keeps a vehicle inside the road: a lateral move past the outer lane edge is clamped, so
off-road detection uses ``intended_lateral`` (the model's offset), not SUMO's.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mixed_traffic import compiled
from mixed_traffic.config import VehicleConfig
from mixed_traffic.env import control_kernel
from mixed_traffic.world.backend import SumoBackend
from mixed_traffic.world.hdmap import SPACING, HDMap
from mixed_traffic.world.snapshot import TrafficSnapshot

#: Largest course angle relative to the lane [rad]; SUMO cannot move a vehicle backwards.
MAX_COURSE = np.deg2rad(80.0)
#: Curvature is averaged over this many waypoints ahead (1 m each) to smooth polyline kinks.
CURVATURE_WINDOW = 5


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def waypoint_curvature(hdmap: HDMap, window: int = CURVATURE_WINDOW) -> np.ndarray:
    """(W,) signed centreline curvature at each waypoint [1/m], positive = turning left.

    Heading change to the next waypoint (following the primary successor across junctions),
    averaged over ``window`` waypoints ahead.
    """
    nxt = hdmap.ahead_table(2)[:, 1]
    raw = _wrap(hdmap.wp_heading[nxt] - hdmap.wp_heading) / SPACING
    raw[nxt == np.arange(len(nxt))] = 0.0  # dead end
    return raw[hdmap.ahead_table(window)].mean(axis=1)


def side_slip(steer: np.ndarray, wheelbase: float) -> tuple[float, np.ndarray]:
    """(l_r [m], β (A,) [rad]): the CoG's distance from the rear axle and the side-slip angle
    β = arctan(l_r / L · tan δ) of steering angles ``steer`` (A,) [rad] (numpy's SIMD tan and
    arctan, which the kernels take as given)."""
    lr = 0.5 * wheelbase
    return lr, np.arctan(lr / wheelbase * np.tan(steer))


def bicycle_frenet_step(
    v: np.ndarray,
    psi: np.ndarray,
    d: np.ndarray,
    steer: np.ndarray,
    accel: np.ndarray,
    kappa: np.ndarray,
    wheelbase: float,
    dt: float,
    max_course: float = MAX_COURSE,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One step of the CoG kinematic bicycle model in the Frenet frame (all arrays (A,)).

    Args:
        v: speed of the CoG [m/s]; psi: yaw relative to the lane [rad, + = left];
        d: lateral offset from the centreline [m, + = left]; steer: front-wheel angle [rad,
        + = left]; accel: [m/s²]; kappa: lane curvature [1/m, + = left]; wheelbase [m]; dt [s].

    Returns:
        ``v_new`` [m/s], ``ds`` and ``dd`` displacement along/across the lane [m], ``psi_new``
        [rad] and ``course`` = ψ_mid + β relative to the lane [rad].
    """
    lr, beta = side_slip(steer, wheelbase)
    v_new = np.maximum(v + accel * dt, 0.0)
    yaw_rate = v_new * np.sin(beta) / lr
    scale = 1.0 / np.maximum(1.0 - kappa * d, 0.1)
    s_dot0 = v_new * np.cos(np.clip(psi + beta, -max_course, max_course)) * scale
    psi_new = psi + (yaw_rate - kappa * s_dot0) * dt
    psi_new = np.clip(psi_new + beta, -max_course, max_course) - beta
    course = np.clip(0.5 * (psi + psi_new) + beta, -max_course, max_course)
    ds = v_new * np.cos(course) * scale * dt
    dd = v_new * np.sin(course) * dt
    return v_new, ds, dd, psi_new, course


def bicycle_rollout(
    v: np.ndarray,
    psi: np.ndarray,
    d: np.ndarray,
    steer: np.ndarray,
    accel: np.ndarray,
    kappa: np.ndarray,
    wheelbase: float,
    dt: float,
    steps: int,
) -> np.ndarray:
    """(A,) lateral offset [m] after ``steps`` steps of :func:`bicycle_frenet_step` holding
    ``steer`` [rad] and ``accel`` [m/s²] from ``v``, ``psi`` and ``d`` (arrays (A,), units as
    there). One kernel (``control_kernel.frenet_rollout``) unless ``compiled.enabled()`` is off;
    the step loop is the reference."""
    if compiled.enabled() and len(v):
        lr, beta = side_slip(steer, wheelbase)
        args = (np.ascontiguousarray(x, np.float64) for x in (v, psi, d, accel, kappa, beta))
        return control_kernel.frenet_rollout(*args, lr, dt, steps, MAX_COURSE)
    for _ in range(steps):
        v, _, dd, psi, _ = bicycle_frenet_step(v, psi, d, steer, accel, kappa, wheelbase, dt)
        d = d + dd
    return d


@dataclass
class ControlCommand:
    """What one control step sends to SUMO and predicts, per agent (rows follow ``ids``)."""

    ids: list[str]
    speed: np.ndarray
    """(A,) speed along the lane sent with setSpeed [m/s]."""
    lateral_move: np.ndarray
    """(A,) lateral displacement sent with changeSublane [m, + = left]."""
    intended_lateral: np.ndarray
    """(A,) lateral offset the model reaches, relative to the lane at t [m]."""
    course: np.ndarray
    """(A,) model course angle relative to the lane, ψ_mid + β [rad]."""
    predicted_sumo_heading: np.ndarray
    """(A,) heading SUMO will report after the step, relative to the lane [rad]."""


class BicycleController:
    """Per-agent bicycle-model state (speed, yaw relative to the lane) and its application.

    Args:
        vehicle: wheelbase and AV limits.
        hdmap: lane geometry (curvature from the waypoint headings).
        dt: step length [s].
    """

    def __init__(self, vehicle: VehicleConfig, hdmap: HDMap, dt: float) -> None:
        self.vehicle = vehicle
        self.hdmap = hdmap
        self.dt = float(dt)
        self.kappa_wp = waypoint_curvature(hdmap)
        self.reset()

    # ------------------------------------------------------------------ agent set
    def reset(self) -> None:
        """Forget every agent."""
        self.ids: list[str] = []
        self._row: dict[str, int] = {}
        self.v = np.zeros(0)
        self.psi = np.zeros(0)
        self.body_offset = np.zeros(0)
        self.length = np.zeros(0)

    def add(
        self,
        ids: Sequence[str],
        speed: np.ndarray,
        length: np.ndarray | None = None,
        psi: np.ndarray | None = None,
        backend: SumoBackend | None = None,
    ) -> None:
        """Start tracking agents (e.g. when they enter), with their current speed [m/s].

        ``psi`` defaults to 0 (aligned with the lane); ``length`` [m] defaults to the vehicle
        config. With ``backend`` given, the agents' lateral acceleration limit is raised so
        each lateral move is executed within one step.
        """
        new = [i for i in ids if i not in self._row]
        if len(new) != len(ids):
            raise ValueError(f"agents already tracked: {sorted(set(ids) - set(new))}")
        n = len(ids)
        speed = np.broadcast_to(np.asarray(speed, np.float64), (n,))
        length = np.full(n, self.vehicle.length) if length is None else np.asarray(length, float)
        psi = np.zeros(n) if psi is None else np.asarray(psi, np.float64)
        self.ids = [*self.ids, *ids]
        self._row = {vid: i for i, vid in enumerate(self.ids)}
        self.v = np.concatenate([self.v, speed])
        self.psi = np.concatenate([self.psi, psi])
        self.body_offset = np.concatenate([self.body_offset, np.zeros(n)])
        self.length = np.concatenate([self.length, length])
        if backend is not None and n:
            backend.set_lateral_accel(list(ids))

    def add_from_snapshot(
        self, snap: TrafficSnapshot, ids: Sequence[str], backend: SumoBackend | None = None
    ) -> None:
        """``add`` with speeds and lengths read from ``snap``."""
        rows = self._rows_in(snap, ids)
        self.add(ids, snap.speed[rows], snap.length[rows], backend=backend)

    def remove(self, ids: Sequence[str]) -> None:
        """Stop tracking agents (unknown ids are ignored)."""
        drop = {self._row[i] for i in ids if i in self._row}
        if not drop:
            return
        keep = np.array([k for k in range(len(self.ids)) if k not in drop], dtype=np.int64)
        self.ids = [self.ids[k] for k in keep]
        self._row = {vid: i for i, vid in enumerate(self.ids)}
        self.v, self.psi = self.v[keep], self.psi[keep]
        self.body_offset, self.length = self.body_offset[keep], self.length[keep]

    @property
    def tracked(self) -> set[str]:
        """Ids of the agents whose model state is kept."""
        return set(self._row)

    def rows(self, ids: Sequence[str]) -> np.ndarray:
        """(A,) state rows of ``ids``; KeyError names an untracked agent."""
        try:
            return np.fromiter((self._row[i] for i in ids), np.int64, len(ids))
        except KeyError as e:
            raise KeyError(f"agent {e.args[0]!r} is not tracked by the controller") from None

    @staticmethod
    def _rows_in(snap: TrafficSnapshot, ids: Sequence[str]) -> np.ndarray:
        index = snap.index_of()
        missing = [i for i in ids if i not in index]
        if missing:
            raise KeyError(f"agents {missing} are not in the snapshot")
        return np.fromiter((index[i] for i in ids), np.int64, len(ids))

    # ------------------------------------------------------------------ stepping
    def curvature(self, lane: np.ndarray, lane_pos: np.ndarray) -> np.ndarray:
        """(A,) lane curvature [1/m] at the given lane rows and positions [m]."""
        return self.kappa_wp[self.hdmap.waypoint_at(lane, np.maximum(lane_pos, 0.0))]

    def compute(
        self,
        ids: Sequence[str],
        steer: np.ndarray,
        accel: np.ndarray,
        lane: np.ndarray,
        lane_pos: np.ndarray,
        lateral: np.ndarray,
    ) -> ControlCommand:
        """Advance the model of agents ``ids`` by one step (updates the internal state).

        Args:
            steer: (A,) [rad, + = left]; accel: (A,) [m/s²]; lane, lane_pos, lateral: (A,) the
                agents' lane rows, lane positions [m] and lateral offsets [m] now (snapshot).
        """
        r = self.rows(ids)
        kappa = self.curvature(lane, lane_pos)
        if compiled.enabled():
            return self._compute_kernel(ids, r, steer, accel, kappa, lateral)
        v_new, ds, dd, psi_new, course = bicycle_frenet_step(
            self.v[r], self.psi[r], lateral, steer, accel, kappa, self.vehicle.wheelbase, self.dt
        )
        body = self.body_offset[r] * (1.0 - np.minimum(ds / self.length[r], 1.0)) + dd
        self.v[r], self.psi[r], self.body_offset[r] = v_new, psi_new, body
        return ControlCommand(
            ids=list(ids),
            speed=ds / self.dt,
            lateral_move=dd,
            intended_lateral=lateral + dd,
            course=course,
            predicted_sumo_heading=np.arctan2(body, self.length[r]),
        )

    def _compute_kernel(
        self,
        ids: Sequence[str],
        r: np.ndarray,
        steer: np.ndarray,
        accel: np.ndarray,
        kappa: np.ndarray,
        lateral: np.ndarray,
    ) -> ControlCommand:
        """``compute``'s arithmetic in ``control_kernel.frenet_compute``; β and the heading's
        arctan2 stay numpy's (its SIMD tan/arctan/arctan2 differ from libm's in the last bit)."""
        lr, beta = side_slip(steer, self.vehicle.wheelbase)
        f64 = np.float64
        speed, move, intended, course, body = control_kernel.frenet_compute(
            self.v, self.psi, self.body_offset, self.length, r, np.ascontiguousarray(lateral, f64),
            np.ascontiguousarray(accel, f64), np.ascontiguousarray(kappa, f64),
            np.ascontiguousarray(beta, f64), float(lr), self.dt, float(MAX_COURSE),
        )  # fmt: skip
        return ControlCommand(
            ids=list(ids), speed=speed, lateral_move=move, intended_lateral=intended,
            course=course, predicted_sumo_heading=np.arctan2(body, self.length[r]),
        )  # fmt: skip

    def step(
        self,
        backend: SumoBackend,
        snap: TrafficSnapshot,
        ids: Sequence[str],
        steer: np.ndarray,
        accel: np.ndarray,
    ) -> ControlCommand:
        """``compute`` from the snapshot rows of ``ids`` and send the command to SUMO."""
        rows = self._rows_in(snap, ids)
        cmd = self.compute(
            ids, steer, accel, snap.lane[rows], snap.lane_pos[rows], snap.lateral[rows]
        )
        apply_command(backend, cmd)
        return cmd


def apply_command(backend: SumoBackend, cmd: ControlCommand) -> None:
    """setSpeed (speed along the lane) + changeSublane (lateral move) for every agent."""
    backend.set_speeds(cmd.ids, cmd.speed)
    backend.change_sublane(cmd.ids, cmd.lateral_move)


# ---------------------------------------------------------------------- benchmark
def measure_mechanisms(
    backend: SumoBackend,
    snap: TrafficSnapshot,
    hdmap: HDMap,
    ids: Sequence[str],
    repeats: int = 20,
    verbose: bool = True,
) -> dict[str, float]:
    """Cost per vehicle [µs] of the two ways to apply a pose, on a running simulation.

    Times ``setSpeed`` + ``changeSublane`` and ``moveToXY(keepRoute=2)`` (to the vehicle's
    current pose) over ``repeats`` rounds for all ``ids``; a simulation step follows each round
    (not timed), so no ``moveToXY`` is left pending. Measured on this machine (libsumo 1.28,
    straight, 120 veh/km, 187 AVs, two runs): 0.52-0.61 µs vs 2.6-19 µs per vehicle.

    Returns:
        ``{"set_speed_change_sublane_us": ..., "move_to_xy_us": ...}`` per vehicle.
    """
    from mixed_traffic.world.snapshot import rad_to_sumo_angle

    wanted = set(ids)
    t_cs = t_xy = 0.0
    n_cs = n_xy = 0
    for _ in range(repeats):
        index = snap.index_of()
        rows = np.array([index[v] for v in snap.ids if v in wanted], dtype=np.int64)
        now = [snap.ids[k] for k in rows]
        speed = snap.speed[rows].copy()
        zeros = np.zeros(len(now))
        t0 = time.perf_counter()
        backend.set_speeds(now, speed)
        backend.change_sublane(now, zeros)
        t_cs += time.perf_counter() - t0
        n_cs += len(now)
        snap = backend.step()
        args = []
        for k, vid in enumerate(snap.ids):
            lane = int(snap.lane[k])
            if vid not in wanted or lane < 0 or hdmap.lane_edge[lane] < 0:
                continue
            edge = hdmap.edge_ids[hdmap.lane_edge[lane]]
            angle = float(rad_to_sumo_angle(snap.heading[k]))
            args.append((vid, edge, int(hdmap.lane_index[lane]), snap.x[k], snap.y[k], angle))
        t0 = time.perf_counter()
        for a in args:
            backend.move_to_xy(*a, keep_route=2)
        t_xy += time.perf_counter() - t0
        n_xy += len(args)
        snap = backend.step()
    out = {
        "set_speed_change_sublane_us": t_cs / max(n_cs, 1) * 1e6,
        "move_to_xy_us": t_xy / max(n_xy, 1) * 1e6,
    }
    if verbose:
        print(
            f"setSpeed+changeSublane: {out['set_speed_change_sublane_us']:.2f} µs/vehicle; "
            f"moveToXY(keepRoute=2): {out['move_to_xy_us']:.2f} µs/vehicle "
            f"({n_cs / repeats:.0f} vehicles, {repeats} rounds, {backend.kind})"
        )
    return out
