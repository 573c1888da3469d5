"""SUMO backend: snapshot contents, the one-libsumo-per-process guard, collisions, errors."""

from __future__ import annotations

import numpy as np
import pytest

from mixed_traffic.world.backend import SumoBackend, SumoError, libsumo_busy
from mixed_traffic.world.scenario import sumo_args
from mixed_traffic.world.snapshot import rad_to_sumo_angle, sumo_angle_to_rad

from .conftest import start_sim


def test_angle_conversion_round_trip() -> None:
    sumo = np.array([0.0, 90.0, 180.0, 270.0, 45.0])
    rad = sumo_angle_to_rad(sumo)
    # SUMO: 0 = north, clockwise; ENU: 0 = east, counter-clockwise
    np.testing.assert_allclose(rad, [np.pi / 2, 0.0, -np.pi / 2, np.pi, np.pi / 4], atol=1e-12)
    np.testing.assert_allclose(rad_to_sumo_angle(rad), sumo, atol=1e-9)


def test_snapshot_fields_are_consistent(sim) -> None:
    snap = sim.step(20)
    n = snap.n
    assert n > 50  # 60 veh/km on 1.6 km
    for name in ("x", "y", "z", "heading", "speed", "accel", "lane", "lane_pos", "lateral", "edge"):
        assert getattr(snap, name).shape == (n,), name
    hd = sim.hdmap
    # straight road along +x: heading east, x grows with lane position, lane rows map to edges
    assert np.all(np.abs(snap.heading) < 0.2)
    assert np.all(snap.lane >= 0)
    np.testing.assert_array_equal(
        hd.lane_edge[snap.lane][snap.edge >= 0], snap.edge[snap.edge >= 0]
    )
    np.testing.assert_array_equal(hd.lane_index[snap.lane], snap.lane_index)
    assert snap.is_av.sum() > 0
    assert all(vid.startswith("av_") == av for vid, av in zip(snap.ids, snap.is_av))
    np.testing.assert_allclose(snap.length, sim.config.vehicle.length)
    assert np.all((snap.route_progress >= 0) & (snap.route_progress <= 1))
    # fuel from SUMO's emission model in ml/s (not mg/s): a car at ~25 m/s burns 4-12 l/100 km
    assert snap.fuel.shape == (n,) and np.all(snap.fuel >= 0)
    per_100km = 100.0 * snap.fuel.sum() / snap.speed.sum()
    assert 2.0 < per_100km < 20.0


def test_route_progress_advances(sim) -> None:
    first = sim.step(1)
    vid = first.ids[int(np.argmin(first.x))]  # the most upstream vehicle
    start = first.route_index[first.ids.index(vid)]
    later = sim.step(400)  # 40 s at ~24 m/s crosses the 400 m warm-up edge
    assert vid in later.ids
    assert later.route_index[later.ids.index(vid)] > start


def test_second_libsumo_falls_back_to_traci_without_touching_the_first(tmp_path) -> None:
    a = start_sim(tmp_path, "libsumo")
    try:
        a.step(30)
        ids_a = set(a.backend.read().ids)
        with pytest.warns(RuntimeWarning, match="falls back to TraCI"):
            b = SumoBackend("libsumo", second_instance="traci")
        assert b.kind == "traci"
        b.set_lane_table(a.hdmap.lane_ids, a.hdmap.lane_edge)
        b.start(sumo_args(a.scenario, a.config, a.route_file, seed=1))
        try:
            snap_b = b.step()
            snap_a = a.step()
            # the first simulation kept its clock and its vehicles
            assert snap_a.time == pytest.approx(3.1)
            assert snap_b.time == pytest.approx(0.1)
            assert len(ids_a & set(snap_a.ids)) > 0.9 * len(ids_a)
            # the TraCI snapshot (subscriptions) carries the same fields
            assert snap_b.n > 0 and np.all(snap_b.lane >= 0)
            assert snap_b.fuel.shape == (snap_b.n,) and snap_b.fuel.sum() > 0
        finally:
            b.close()
    finally:
        a.backend.close()
    assert not libsumo_busy()


def test_second_libsumo_can_be_refused(tmp_path) -> None:
    a = start_sim(tmp_path)
    try:
        with pytest.raises(SumoError, match="libsumo already runs a simulation"):
            SumoBackend("libsumo", second_instance="error")
    finally:
        a.backend.close()
    # once closed, libsumo is free again
    b = SumoBackend("libsumo", second_instance="error")
    assert b.kind == "libsumo"


def test_reload_resets_the_simulation(sim) -> None:
    sim.step(50)
    sim.backend.load(sumo_args(sim.scenario, sim.config, sim.route_file, seed=0))
    snap = sim.step(1)
    assert snap.time == pytest.approx(0.1)


def test_collision_is_reported(sim) -> None:
    snap = sim.step(5)
    av = next(i for i, vid in enumerate(snap.ids) if snap.is_av[i])
    # an AV ignores SUMO's safety checks (speedMode 32): drive it into whatever is ahead
    collided = False
    for _ in range(300):
        vid = snap.ids[av]
        sim.backend.set_speeds([vid], np.array([40.0]))
        snap = sim.step(1)
        if any(vid in (c.collider, c.victim) for c in snap.collisions):
            collided = True
            # SUMO lists collision removals as arrivals too; the snapshot must not
            assert not {vid, *(v for c in snap.collisions for v in (c.collider, c.victim))} & set(
                snap.arrived
            )
            break
        if vid not in snap.ids:
            break
        av = snap.ids.index(vid)
    assert collided, "an AV driven at 40 m/s through 60 veh/km traffic must hit a leader"
    assert vid not in sim.backend.read().ids  # collision.action remove


def test_bad_route_file_gives_sumo_error(tmp_path) -> None:
    a = start_sim(tmp_path)
    a.backend.close()
    bad = tmp_path / "bad.rou.xml"
    bad.write_text(
        '<routes><route id="r" edges="no_such_edge"/><vehicle id="v" route="r" depart="0"/></routes>'
    )
    b = SumoBackend("libsumo")
    with pytest.raises(SumoError, match="no_such_edge"):
        b.start(sumo_args(a.scenario, a.config, bad, seed=0))
    assert not libsumo_busy()
