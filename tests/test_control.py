"""Bicycle-model control on real SUMO: steering, throttle/brake, pose tracking, mechanisms, segfault guard."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from mixed_traffic.config import EnvConfig
from mixed_traffic.env.control import BicycleController, bicycle_frenet_step, measure_mechanisms
from mixed_traffic.world.backend import SumoBackend
from mixed_traffic.world.demand import make_demand, write_demand
from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.registry import load_scenario
from mixed_traffic.world.scenario import sumo_args
from mixed_traffic.world.snapshot import TrafficSnapshot

DT = 0.1


def start_straight(tmp_path: Path, density: float = 30.0, penetration: float = 0.6):
    """Real SUMO on the bundled straight scenario; returns (backend, hdmap, config, snapshot)."""
    cfg = EnvConfig(
        scenario="straight", density=density, penetration=penetration, episode_length=60
    )
    sc = load_scenario(cfg.scenario)
    hd = sc.hdmap
    demand = make_demand(sc, cfg, np.random.default_rng(cfg.seed))
    rf = tmp_path / "demand.rou.xml"
    write_demand(demand, cfg, rf)
    backend = SumoBackend("libsumo", "traci")
    backend.set_lane_table(hd.lane_ids, hd.lane_edge)
    backend.start(sumo_args(sc, cfg, rf, seed=cfg.seed))
    return backend, hd, cfg, backend.step()


def isolate(backend: SumoBackend, snap: TrafficSnapshot, keep: list[str]) -> TrafficSnapshot:
    """Remove every vehicle but ``keep`` and step once."""
    for vid in snap.ids:
        if vid not in keep:
            backend.remove(vid)
    return backend.step()


def pick_av(snap: TrafficSnapshot, hd: HDMap, lane_index: int) -> str:
    """An AV on the measurement edge in the given lane, far from the edge's end."""
    meas = hd.edge_of("meas")
    for k, vid in enumerate(snap.ids):
        if (
            snap.is_av[k]
            and snap.edge[k] == meas
            and snap.lane_index[k] == lane_index
            and snap.lane_pos[k] < 600
        ):
            return vid
    raise AssertionError(f"the test traffic has no AV in lane {lane_index} of 'meas' before 600 m")


@pytest.fixture
def road(tmp_path):
    backend, hd, cfg, snap = start_straight(tmp_path)
    yield backend, hd, cfg, snap
    backend.close()


def drive(backend, hd, cfg, snap, vid, steer_deg, accel, steps):
    """Constant (steer, accel) for ``steps`` steps; returns snapshots and commands per step."""
    ctl = BicycleController(cfg.vehicle, hd, DT)
    ctl.add_from_snapshot(snap, [vid], backend)
    snaps, cmds = [snap], []
    for _ in range(steps):
        cmds.append(
            ctl.step(backend, snap, [vid], np.array([np.deg2rad(steer_deg)]), np.array([accel]))
        )
        snap = backend.step()
        snaps.append(snap)
    return snaps, cmds, ctl


# ---------------------------------------------------------------------- pure model
def test_straight_step_hand_computed() -> None:
    # no steering: v' = 20 + 3*0.1 = 20.3, moves v'*dt = 2.03 m straight ahead
    v, ds, dd, psi, course = bicycle_frenet_step(
        np.array([20.0]),
        np.zeros(1),
        np.zeros(1),
        np.zeros(1),
        np.array([3.0]),
        np.zeros(1),
        2.8,
        0.1,
    )
    np.testing.assert_allclose(
        [v[0], ds[0], dd[0], psi[0], course[0]], [20.3, 2.03, 0, 0, 0], atol=1e-12
    )
    # steering 10 deg left: beta = atan(0.5 tan 10deg); yaw rate = v sin(beta)/1.4
    delta = np.deg2rad(10.0)
    beta = np.arctan(0.5 * np.tan(delta))
    r = 10.0 * np.sin(beta) / 1.4
    v, ds, dd, psi, course = bicycle_frenet_step(
        np.array([10.0]),
        np.zeros(1),
        np.zeros(1),
        np.array([delta]),
        np.zeros(1),
        np.zeros(1),
        2.8,
        0.1,
    )
    np.testing.assert_allclose(psi[0], r * 0.1, rtol=1e-12)
    np.testing.assert_allclose(course[0], 0.5 * r * 0.1 + beta, rtol=1e-12)
    np.testing.assert_allclose(dd[0], 10.0 * np.sin(course[0]) * 0.1, rtol=1e-12)
    assert dd[0] > 0  # positive steering = left


def test_no_reversing() -> None:
    v, ds, *_ = bicycle_frenet_step(
        np.array([0.2]),
        np.zeros(1),
        np.zeros(1),
        np.zeros(1),
        np.array([-6.0]),
        np.zeros(1),
        2.8,
        0.1,
    )
    assert v[0] == 0.0 and ds[0] == 0.0


def test_steady_cornering_follows_a_curve() -> None:
    # on a lane of curvature kappa, sin(beta) = kappa*l_r with yaw psi = -beta keeps d and psi constant
    kappa, lr, L = 0.01, 1.4, 2.8
    beta = np.arcsin(kappa * lr)
    delta = np.arctan(np.tan(beta) * L / lr)
    v, psi, d = np.array([15.0]), np.array([-beta]), np.zeros(1)
    for _ in range(50):
        v, _ds, dd, psi, _ = bicycle_frenet_step(
            v, psi, d, np.array([delta]), np.zeros(1), np.array([kappa]), L, 0.1
        )
        d = d + dd
    assert abs(d[0]) < 1e-9 and abs(psi[0] + beta) < 1e-9


# ---------------------------------------------------------------------- real SUMO
def test_steering_left_moves_into_the_left_lane(road) -> None:
    backend, hd, cfg, snap = road
    vid = pick_av(snap, hd, lane_index=1)
    snap = isolate(backend, snap, [vid])
    k = snap.index_of()[vid]
    y0, lane0 = snap.y[k], int(snap.lane_index[k])
    snaps, cmds, _ = drive(backend, hd, cfg, snap, vid, steer_deg=3.0, accel=0.0, steps=7)
    last = snaps[-1]
    k = last.index_of()[vid]
    assert last.y[k] > y0 + 2.0  # the road runs along +x, so left is +y
    assert int(last.lane_index[k]) == lane0 + 1  # across into the left lane
    # positions follow the model: SUMO executes the lateral move and the lane speed exactly
    for s0, s1, cmd in zip(snaps[:-1], snaps[1:], cmds):
        a, b = s0.index_of()[vid], s1.index_of()[vid]
        moved_lat = s1.y[b] - s0.y[a]  # straight road: lateral = y
        assert abs(moved_lat - cmd.lateral_move[0]) < 1e-6
        assert abs((s1.lane_pos[b] - s0.lane_pos[a]) - cmd.speed[0] * DT) < 1e-6


def test_steering_right_moves_right(road) -> None:
    backend, hd, cfg, snap = road
    vid = pick_av(snap, hd, lane_index=1)
    snap = isolate(backend, snap, [vid])
    snaps, _, _ = drive(backend, hd, cfg, snap, vid, steer_deg=-3.0, accel=0.0, steps=8)
    k = snaps[-1].index_of()[vid]
    assert int(snaps[-1].lane_index[k]) == 0


def test_sumo_pose_follows_the_bicycle_model(road) -> None:
    """Lateral position exact; SUMO's heading = predicted body heading (< 0.3 deg), and within
    3 deg of the model's course angle psi + beta (SUMO's body lags the course)."""
    backend, hd, cfg, snap = road
    vid = pick_av(snap, hd, lane_index=1)
    snap = isolate(backend, snap, [vid])
    lane0 = hd.edge_lanes[hd.edge_of("meas"), 1]
    lat_origin = snap.y[snap.index_of()[vid]] - hd.wp_xyz[hd.wp_offset[lane0], 1]
    snaps, cmds, _ = drive(backend, hd, cfg, snap, vid, steer_deg=2.0, accel=0.0, steps=6)
    lat_model = lat_origin + np.cumsum([c.lateral_move[0] for c in cmds])
    for s, cmd, lat in zip(snaps[1:], cmds, lat_model):
        k = s.index_of()[vid]
        lane_heading = hd.wp_heading[hd.waypoint_at(s.lane[k : k + 1], s.lane_pos[k : k + 1])][0]
        sumo_rel = s.heading[k] - lane_heading
        lat_sumo = s.y[k] - hd.wp_xyz[hd.wp_offset[lane0], 1]
        assert abs(lat_sumo - lat) < 1e-6
        assert abs(np.rad2deg(sumo_rel - cmd.predicted_sumo_heading[0])) < 0.3
        assert abs(np.rad2deg(sumo_rel - cmd.course[0])) < 3.0


def test_accel_brake_speeds_up_and_slows_down(road) -> None:
    backend, hd, cfg, snap = road
    vid = pick_av(snap, hd, lane_index=1)
    snap = isolate(backend, snap, [vid])
    v0 = snap.speed[snap.index_of()[vid]]
    snaps, _, _ = drive(backend, hd, cfg, snap, vid, steer_deg=0.0, accel=3.0, steps=10)
    v1 = snaps[-1].speed[snaps[-1].index_of()[vid]]
    np.testing.assert_allclose(v1, v0 + 3.0, atol=1e-6)  # +1 -> +3 m/s^2 for 1 s
    snaps, _, _ = drive(backend, hd, cfg, snaps[-1], vid, steer_deg=0.0, accel=-6.0, steps=10)
    v2 = snaps[-1].speed[snaps[-1].index_of()[vid]]
    np.testing.assert_allclose(v2, v1 - 6.0, atol=1e-6)  # -1 -> -6 m/s^2 for 1 s


def test_controller_add_remove_reset(road) -> None:
    backend, hd, cfg, snap = road
    avs = [v for v, av in zip(snap.ids, snap.is_av) if av][:3]
    ctl = BicycleController(cfg.vehicle, hd, DT)
    ctl.add_from_snapshot(snap, avs, backend)
    with pytest.raises(ValueError, match="already tracked"):
        ctl.add([avs[0]], np.array([1.0]))
    ctl.remove([avs[1], "nobody"])
    assert ctl.ids == [avs[0], avs[2]]
    with pytest.raises(KeyError, match="not tracked"):
        ctl.rows([avs[1]])
    ctl.reset()
    assert ctl.ids == [] and ctl.v.shape == (0,)


def test_measure_mechanisms_reports_both(tmp_path, capsys) -> None:
    backend, hd, _cfg, snap = start_straight(tmp_path, density=60.0, penetration=1.0)
    try:
        ids = [v for v, av in zip(snap.ids, snap.is_av) if av]
        out = measure_mechanisms(backend, snap, hd, ids, repeats=3)
    finally:
        backend.close()
    assert out["set_speed_change_sublane_us"] > 0 and out["move_to_xy_us"] > 0
    assert "µs/vehicle" in capsys.readouterr().out


_SEGFAULT_SCRIPT = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    import numpy as np
    from mixed_traffic.world.backend import SumoBackend
    from mixed_traffic.world.snapshot import rad_to_sumo_angle
    from mixed_traffic.config import EnvConfig
    from mixed_traffic.world.registry import load_scenario
    from mixed_traffic.world.demand import make_demand, write_demand
    from mixed_traffic.world.scenario import sumo_args

    mode = sys.argv[1]
    cfg = EnvConfig(density=30.0, penetration=0.5, episode_length=30)
    sc = load_scenario(cfg.scenario); hd = sc.hdmap
    rf = Path(sys.argv[2]); write_demand(make_demand(sc, cfg, np.random.default_rng(0)), cfg, rf)
    args = sumo_args(sc, cfg, rf, seed=0)
    b = SumoBackend("libsumo"); b.set_lane_table(hd.lane_ids, hd.lane_edge); b.start(args)
    snap = b.step()
    for k in np.flatnonzero(snap.is_av):  # moving every AV reproduces the crash without the guard
        lane = int(snap.lane[k])
        b.move_to_xy(snap.ids[k], hd.edge_ids[hd.lane_edge[lane]], int(hd.lane_index[lane]),
                     float(snap.x[k]) + 1.0, float(snap.y[k]),
                     float(rad_to_sumo_angle(snap.heading[k])))
    if mode == "load":
        b.load(args)          # reset right after a moveToXY
    else:
        b.close(); b.start(args)
    for _ in range(3):
        b.step()
    b.close()
    print("ok")
    """
)


@pytest.mark.parametrize("mode", ["load", "restart"])
def test_move_to_xy_then_reset_does_not_segfault(tmp_path, mode) -> None:
    proc = subprocess.run(
        [sys.executable, "-c", _SEGFAULT_SCRIPT, mode, str(tmp_path / "d.rou.xml")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, (
        f"exit {proc.returncode} (negative = signal): {proc.stderr[-2000:]}"
    )
    assert proc.stdout.strip().endswith("ok")
