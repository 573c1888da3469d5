"""Perception: neighbour search against brute force, sensors, weather noise, traffic lights."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mixed_traffic.config import SensorConfig
from mixed_traffic.sensing.blockers import SWEEP_MARGIN
from mixed_traffic.sensing.camera import GREEN, NO_LIGHT, RED
from mixed_traffic.sensing.geometry import bumper_gap, ttc
from mixed_traffic.sensing.lane_graph import CURRENT, RIGHT, next_route_edge
from mixed_traffic.sensing.lidar import vehicle_features
from mixed_traffic.sensing.neighbours import find_neighbours
from mixed_traffic.sensing.noise import VEHICLE_NOISE_FLOOR, WEATHER_PRESETS
from mixed_traffic.sensing.perception import Perception
from mixed_traffic.world.backend import SumoBackend
from mixed_traffic.world.hdmap import HDMap, load_hdmap
from mixed_traffic.world.network import build_network
from mixed_traffic.world.registry import load_scenario
from mixed_traffic.world.snapshot import TrafficSnapshot

from .conftest import start_sim

# --------------------------------------------------------------------------- helpers
DROP_NODES = """<nodes>
    <node id="a" x="0" y="0"/>
    <node id="b" x="300" y="0" type="traffic_light"/>
    <node id="c" x="600" y="0"/>
</nodes>"""
DROP_EDGES = """<edges>
    <edge id="ab" from="a" to="b" numLanes="2" speed="13.89" width="3.2"/>
    <edge id="bc" from="b" to="c" numLanes="1" speed="13.89" width="3.2"/>
</edges>"""
# only the right lane of ab continues: ab_1 ends at the junction (lane drop)
DROP_CONNECTIONS = """<connections>
    <connection from="ab" to="bc" fromLane="0" toLane="0"/>
</connections>"""


def drop_network(tmp_path: Path) -> HDMap:
    """A 2-lane road whose left lane ends at a signalised junction, then 1 lane (tiny net)."""
    folder = tmp_path / "drop" / "net"
    folder.mkdir(parents=True)
    (folder / "n.nod.xml").write_text(DROP_NODES)
    (folder / "e.edg.xml").write_text(DROP_EDGES)
    (folder / "c.con.xml").write_text(DROP_CONNECTIONS)
    return load_hdmap(build_network(folder))


def start_drop(
    tmp_path: Path, hd: HDMap, vehicles: list[tuple[str, str, int, float]]
) -> SumoBackend:
    """Start SUMO on the drop net with standing vehicles (id, first edge, lane, position)."""
    routes = ['<routes>', '<vType id="av" length="5" width="1.8"/>',
              '<vType id="hv" length="5" width="1.8"/>',
              '<route id="r_ab" edges="ab bc"/>', '<route id="r_bc" edges="bc"/>']  # fmt: skip
    for vid, edge, lane, pos in vehicles:
        vtype = "av" if vid.startswith("av_") else "hv"
        routes.append(
            f'<vehicle id="{vid}" type="{vtype}" route="r_{edge}" depart="0" '
            f'departLane="{lane}" departPos="{pos}" departSpeed="0"/>'
        )
    routes.append("</routes>")
    rf = tmp_path / "drop.rou.xml"
    rf.write_text("\n".join(routes))
    backend = SumoBackend("libsumo", "traci")
    backend.set_lane_table(hd.lane_ids, hd.lane_edge)
    backend.start(["--net-file", hd.net_file, "--route-files", str(rf), "--step-length", "0.1",
                   "--lateral-resolution", "0.8", "--no-step-log", "true", "--no-warnings", "true",
                   "--time-to-teleport", "-1"])  # fmt: skip
    return backend


CROSS_NODES = """<nodes>
    <node id="w" x="-200" y="0"/>
    <node id="e" x="200" y="0"/>
    <node id="s" x="0" y="-200"/>
    <node id="n" x="0" y="200"/>
    <node id="c" x="0" y="0" type="priority"/>
</nodes>"""
# south -> north is the priority road: its traffic crosses the junction without waiting
CROSS_EDGES = """<edges>
    <edge id="wc" from="w" to="c" numLanes="1" speed="13.89" priority="1"/>
    <edge id="ce" from="c" to="e" numLanes="1" speed="13.89" priority="1"/>
    <edge id="sc" from="s" to="c" numLanes="1" speed="13.89" priority="2"/>
    <edge id="cn" from="c" to="n" numLanes="1" speed="13.89" priority="2"/>
</edges>"""


def start_cross(tmp_path: Path, standing: bool) -> tuple[HDMap, SumoBackend]:
    """A priority crossing: ``ego`` drives west -> east, ``hv`` crosses south -> north ahead of
    it at 13 m/s, or (``standing``) creeps into the junction at 3 m/s, ego departing later."""
    folder = tmp_path / "cross" / "net"
    folder.mkdir(parents=True)
    (folder / "n.nod.xml").write_text(CROSS_NODES)
    (folder / "e.edg.xml").write_text(CROSS_EDGES)
    hd = load_hdmap(build_network(folder))
    rf = tmp_path / "cross.rou.xml"
    rf.write_text(
        '<routes><vType id="car" length="5" width="1.8" sigma="0"/>'
        f'<vType id="hv" length="5" width="1.8" sigma="0" maxSpeed="{3 if standing else 13}"/>'
        f'<vehicle id="hv" type="hv" depart="0" departPos="{185 if standing else 150}" '
        'departSpeed="max"><route edges="sc cn"/></vehicle>'
        f'<vehicle id="ego" type="car" depart="{7 if standing else 0}" departPos="120" '
        'departSpeed="8"><route edges="wc ce"/></vehicle></routes>'
    )
    backend = SumoBackend("libsumo", "traci")
    backend.set_lane_table(hd.lane_ids, hd.lane_edge)
    backend.start(["--net-file", hd.net_file, "--route-files", str(rf), "--step-length", "0.1",
                   "--no-step-log", "true", "--no-warnings", "true", "--time-to-teleport", "-1",
                   "--collision.action", "none"])  # fmt: skip
    return hd, backend


def routes_of(backend: SumoBackend, hd: HDMap, ids: list[str]) -> list[list[int]]:
    return [[hd.edge_row[e] for e in backend.vehicle_route(v)] for v in ids]


def fake_snapshot(
    hd: HDMap, lanes: list[str], pos: list[float], speed: list[float]
) -> TrafficSnapshot:
    """A hand-made snapshot (no SUMO) on ``hd``: vehicle i on lane ``lanes[i]`` at ``pos[i]``."""
    n = len(lanes)
    lane = np.array([hd.lane_row[x] for x in lanes], dtype=np.int32)
    z = np.zeros(n)
    return TrafficSnapshot(
        time=0.0, ids=[f"av_{i}" for i in range(n)], is_av=np.ones(n, bool), x=np.array(pos),
        y=z, z=z, heading=z, speed=np.array(speed, float), accel=z, lane=lane,
        lane_index=hd.lane_index[lane], lane_pos=np.array(pos, float), lateral=z,
        length=np.full(n, 5.0), width=np.full(n, 1.8), edge=hd.lane_edge[lane],
        route_index=np.zeros(n, np.int32), route_length=np.full(n, 3, np.int32),
    )  # fmt: skip


def brute_force(
    snap: TrafficSnapshot, ego: int, lane_index: int, rng: float
) -> tuple[float, float]:
    """Nearest front / rear distance on a straight road along +x, by x, in lane ``lane_index``;
    on a neighbour lane, of two cars side by side the one laterally nearer the ego."""
    others = [j for j in range(snap.n) if j != ego and snap.lane_index[j] == lane_index]
    shift = (lane_index - snap.lane_index[ego]) * 3.5  # left is +

    def off(j: int) -> float:  # lateral distance from the ego [m]
        return abs(snap.lateral[j] + shift - snap.lateral[ego])

    def pick(cands: list[int], missing: float) -> float:
        if not cands:
            return missing
        near, *rest = sorted(cands, key=lambda j: abs(snap.x[j] - snap.x[ego]))
        if (
            shift
            and rest
            and abs(snap.x[rest[0]] - snap.x[near])
            < snap.length[max(near, rest[0], key=snap.x.__getitem__)]
            and off(rest[0]) < off(near)
        ):
            near = rest[0]
        return snap.x[near] - snap.x[ego]

    dx = {j: snap.x[j] - snap.x[ego] for j in others}
    return (
        pick([j for j in others if 0 <= dx[j] <= rng], np.inf),
        pick([j for j in others if -rng <= dx[j] < 0], -np.inf),
    )


# --------------------------------------------------------------------------- pure functions
def test_bumper_gap_and_ttc_hand_values() -> None:
    # 30 m front to front, two 5 m cars: 25 m gap; closing at 5 m/s: 5 s
    gap = bumper_gap(np.array([30.0, -30.0, np.inf]), 5.0, 5.0)
    np.testing.assert_allclose(gap, [25.0, 25.0, np.inf])
    np.testing.assert_allclose(ttc(gap, np.array([5.0, 0.0, 3.0])), [5.0, np.inf, np.inf])
    assert ttc(np.array(-1.0), np.array(2.0)) == 0.0  # overlapping and closing
    assert ttc(np.array(10.0), np.array(-2.0)) == np.inf  # opening


def test_weather_presets_are_in_the_documented_ranges() -> None:
    assert set(WEATHER_PRESETS) == {"normal", "rain", "fog", "night"}
    for w in WEATHER_PRESETS.values():
        assert 0.03 <= w.rel_noise <= 0.18
        assert 0.0 < w.light_misdetect < 0.25
        assert 0 < w.lidar_range_factor <= 1 and 0 < w.camera_range_factor <= 1
    assert WEATHER_PRESETS["rain"].light_misdetect == pytest.approx(0.13)
    assert (
        WEATHER_PRESETS["fog"].camera_range_factor < 1
        and WEATHER_PRESETS["night"].camera_range_factor < 1
    )
    with pytest.raises(AttributeError):
        WEATHER_PRESETS["rain"].rel_noise = 0.5  # frozen


def test_next_route_edge() -> None:
    out = next_route_edge([[4, 5, 6], [4, 5, 6], [7]], np.array([0, 2, 0]))
    np.testing.assert_array_equal(out, [5, -1, -1])


def test_leader_across_edge_boundary_synthetic() -> None:
    hd = load_scenario("straight").hdmap
    # ego near the end of warmup lane 1, leader 3 m into meas lane 1, follower on warmup lane 0
    snap = fake_snapshot(hd, ["warmup_1", "meas_1", "meas_0", "warmup_2"],
                         [395.0, 3.0, 1.0, 350.0], [20, 20, 20, 20])  # fmt: skip
    nb = find_neighbours(snap, hd, np.array([0, 1]), 90.0)
    junction = hd.lane_length[hd.lane_row[":m0_0_1"]]
    assert nb.front[0, 1] == 1
    assert nb.front_dist[0, 1] == pytest.approx(5.0 + junction + 3.0)
    assert nb.front[0, 2] == 2  # right lane: meas_0 through the junction
    assert nb.rear[0, 0] == 3 and nb.rear_dist[0, 0] == pytest.approx(-45.0)
    # seen from the leader, the ego is the follower across the boundary
    assert nb.rear[1, 1] == 0 and nb.rear_dist[1, 1] == pytest.approx(-(5.0 + junction + 3.0))
    # out of range
    nb = find_neighbours(snap, hd, np.array([0]), 5.0)
    assert nb.front[0, 1] == -1 and nb.front_dist[0, 1] == np.inf
    assert nb.lane[0, 0] == hd.lane_row["warmup_2"] and nb.lane[0, 2] == hd.lane_row["warmup_0"]


def test_vehicle_straddling_in_behind_a_neighbour_is_the_current_lane_leader() -> None:
    """Sublane model: two cars share the right lane side by side; the farther one straddles
    into the ego's lane and hides behind the nearer one, which keeps to its right edge."""
    hd = load_scenario("straight").hdmap
    snap = fake_snapshot(hd, ["meas_1", "meas_0", "meas_0", "meas_1"],
                         [100.0, 103.0, 108.0, 150.0], [7, 4, 4, 10])  # fmt: skip
    snap = replace(snap, lateral=np.array([0.0, -0.8, 1.65, 0.0]))
    nb = find_neighbours(snap, hd, np.array([0]), 90.0)
    assert nb.front[0, 2] == 1  # the right lane still reports its nearest car
    assert nb.front[0, CURRENT] == 2 and nb.front_dist[0, CURRENT] == pytest.approx(8.0)
    feats = vehicle_features(snap, np.array([0]), nb)[0, CURRENT, 0]
    width = hd.lane_width[hd.lane_row["meas_1"]]
    assert feats[1] == pytest.approx(-3.0)  # its speed minus ours
    assert feats[5] == pytest.approx(1.65 - width)  # its offset from our lane centre
    # keeping to its own lane it is not in our way: the lane leader stays
    snap = replace(snap, lateral=np.array([0.0, -0.8, 0.0, 0.0]))
    assert find_neighbours(snap, hd, np.array([0]), 90.0).front[0, CURRENT] == 3


def test_of_two_cars_side_by_side_on_a_neighbour_lane_the_nearer_one_is_reported() -> None:
    """Sublane model: two cars share the right lane side by side, the one at its left edge
    straddling towards the ego. It is the right lane's rear (front) vehicle even when the
    other is a few cm nearer along the lane (a LiDAR sees it first, and it is in the way)."""
    hd = load_scenario("straight").hdmap
    lanes = ["meas_2", "meas_1", "meas_1", "meas_1", "meas_1"]
    snap = fake_snapshot(hd, lanes, [100.0, 95.71, 95.70, 120.0, 120.5], [13.0] * 5)
    snap = replace(snap, lateral=np.array([0.5, -0.85, 1.55, -0.85, 1.4]))
    nb = find_neighbours(snap, hd, np.array([0]), 90.0)
    assert nb.rear[0, RIGHT] == 2 and nb.rear_dist[0, RIGHT] == pytest.approx(-4.3)
    assert nb.front[0, RIGHT] == 4 and nb.front_dist[0, RIGHT] == pytest.approx(20.5)
    # a car length apart they are not side by side: the nearest along the lane stays
    snap = replace(snap, lane_pos=np.array([100.0, 95.71, 90.0, 120.0, 125.5]))
    nb = find_neighbours(snap, hd, np.array([0]), 90.0)
    assert nb.rear[0, RIGHT] == 1 and nb.front[0, RIGHT] == 3
    # nor when the farther one is not laterally nearer the ego
    snap = replace(snap, lane_pos=np.array([100.0, 95.71, 95.70, 120.0, 120.5]),
                   lateral=np.array([0.5, 1.55, -0.85, 1.4, -0.85]))  # fmt: skip
    nb = find_neighbours(snap, hd, np.array([0]), 90.0)
    assert nb.rear[0, RIGHT] == 1 and nb.front[0, RIGHT] == 3


# --------------------------------------------------------------------------- real SUMO
def test_neighbours_match_brute_force_on_straight(tmp_path) -> None:
    sim = start_sim(tmp_path, density=120.0, penetration=0.5)
    try:
        rng = 90.0
        checked = 0
        for _ in range(6):
            snap = sim.step(10)
            rows = np.flatnonzero(snap.is_av)
            nb = find_neighbours(snap, sim.hdmap, rows, rng)
            for a, r in enumerate(rows):
                for col, d in enumerate((+1, 0, -1)):
                    k = snap.lane_index[r] + d
                    if not 0 <= k < 3:
                        assert nb.lane[a, col] == -1 and nb.front[a, col] == -1
                        continue
                    f, b = brute_force(snap, r, k, rng)
                    # x and lane position agree to the junction lanes' 0.1 m rounding
                    assert nb.front_dist[a, col] == pytest.approx(f, abs=0.3), (a, col)
                    assert nb.rear_dist[a, col] == pytest.approx(b, abs=0.3), (a, col)
                    if np.isfinite(f):
                        assert snap.x[nb.front[a, col]] - snap.x[r] == pytest.approx(f, abs=0.3)
                    checked += 1
        assert checked > 500
    finally:
        sim.backend.close()


def test_noise_off_is_ground_truth_and_noise_on_has_preset_magnitude(tmp_path) -> None:
    sim = start_sim(tmp_path, density=120.0, penetration=1.0)
    try:
        snap = sim.step(20)
        rows = np.flatnonzero(snap.is_av)
        nxt = np.full(len(rows), -1)
        exact = Perception(SensorConfig(noise=False), sim.hdmap, "fog")
        truth, sensed = exact.sense(snap, rows, nxt, [], np.random.default_rng(0))
        assert sensed is truth
        np.testing.assert_array_equal(truth.ego[:, 0], snap.speed[rows])
        np.testing.assert_array_equal(truth.ego[:, 4], snap.lateral[rows])
        for name in ("rain", "fog", "night", "normal"):
            w = WEATHER_PRESETS[name]
            p = Perception(SensorConfig(noise=True), sim.hdmap, name)
            t, s = p.sense(snap, rows, nxt, [], np.random.default_rng(1))
            both = (t.neighbours.vehicle >= 0) & (s.neighbours.vehicle >= 0)
            assert both.sum() > 100
            # relative RMS error of every vehicle feature ~ rel_noise
            err = (s.vehicles - t.vehicles)[both] / (np.abs(t.vehicles[both]) + VEHICLE_NOISE_FLOOR)
            rms = np.sqrt(np.mean(err**2))
            assert 0.8 * w.rel_noise < rms < 1.2 * w.rel_noise, (name, rms)
            # the shortened LiDAR range drops far vehicles
            lidar = 90.0 * w.lidar_range_factor
            assert np.all(np.abs(t.neighbours.distance[s.neighbours.vehicle >= 0]) <= lidar + 1e-9)
            if w.lidar_range_factor < 0.9:  # dense traffic: check with a 40 m nominal range
                p40 = Perception(SensorConfig(lidar_range=40.0, noise=True), sim.hdmap, name)
                t, s = p40.sense(snap, rows, nxt, [], np.random.default_rng(1))
                assert (s.neighbours.vehicle >= 0).sum() < (t.neighbours.vehicle >= 0).sum()
            assert not np.array_equal(s.ego[:, 0], t.ego[:, 0])
    finally:
        sim.backend.close()


def test_camera_sees_the_light_and_rain_misdetects_it(tmp_path) -> None:
    hd = drop_network(tmp_path)
    backend = start_drop(tmp_path, hd, [("av_0", "ab", 0, 250.0), ("av_1", "ab", 0, 100.0)])
    try:
        snap = backend.step()
        ids = ["av_0", "av_1"]
        rows = np.array([snap.ids.index(v) for v in ids])
        nxt = next_route_edge(routes_of(backend, hd, ids), snap.route_index[rows])
        exact = Perception(SensorConfig(noise=False), hd, "normal")
        assert exact.tls_ids == ["b"]
        states = backend.tls_states(["b"])
        truth, _ = exact.sense(snap, rows, nxt, states, np.random.default_rng(0))
        # independent: the link index of lane ab_0 from SUMO's controlled links
        links = backend.tls_links("b")
        k = next(i for i, ls in enumerate(links) if any(lk[0] == "ab_0" for lk in ls))
        expect = {"r": RED, "R": RED, "g": GREEN, "G": GREEN}.get(states[0][k], 1)
        assert truth.light_state[0, 1] == expect
        stop = hd.lane_length[hd.lane_row["ab_0"]] - snap.lane_pos[rows[0]]
        assert truth.light_dist[0, 1] == pytest.approx(stop)
        assert truth.light_state[1, 1] == NO_LIGHT  # ~196 m away: beyond the camera's 60 m
        # ab_1 (left of av_0) has no link to bc: the lane ends, no signal for it
        assert truth.light_state[0, 0] == NO_LIGHT
        # rain: ~13 % wrong states over many draws
        rain = Perception(SensorConfig(noise=True), hd, "rain")
        g = np.random.default_rng(3)
        wrong = [rain.sense(snap, rows[:1], nxt[:1], states, g)[1].light_state[0, 1] != expect
                 for _ in range(2000)]  # fmt: skip
        assert 0.10 < np.mean(wrong) < 0.16
    finally:
        backend.close()


def test_same_seed_same_noise(tmp_path) -> None:
    hd = load_scenario("straight").hdmap
    snap = fake_snapshot(hd, ["meas_1", "meas_1", "meas_0"], [100.0, 130.0, 90.0], [20, 15, 22])
    p = Perception(replace(SensorConfig(), noise=True), hd, "rain")
    a = p.sense(snap, np.array([0]), np.array([-1]), [], np.random.default_rng(7))[1]
    b = p.sense(snap, np.array([0]), np.array([-1]), [], np.random.default_rng(7))[1]
    np.testing.assert_array_equal(a.vehicles, b.vehicles)
    np.testing.assert_array_equal(a.ego, b.ego)


@pytest.mark.parametrize("standing", [False, True], ids=["crossing", "standing"])
def test_vehicle_across_the_junction_is_the_current_lane_leader(tmp_path, standing) -> None:
    """hv crosses the junction ahead of ego on the crossing internal lane, at speed or standing
    in the middle: while its body covers ego's path ahead (brute force: its rectangle
    within ego's half width + SWEEP_MARGIN of the straight path y = y_ego), it is ego's current-lane front
    vehicle, at the bumper gap along the path, with its speed along the path (~0), its
    extents along / across the path and its offset from the path as features."""
    hd, backend = start_cross(tmp_path, standing)
    try:
        p = Perception(SensorConfig(noise=False), hd, "normal")
        path_y = hd.wp_xyz[hd.wp_offset[hd.lane_row["wc_0"]], 1]
        seen = 0
        for _ in range(150):
            snap = backend.step()
            ix = snap.index_of()
            h = ix.get("hv", -1)
            if standing and h >= 0 and snap.y[h] - 2.5 > path_y - 0.3:
                backend.set_speeds(["hv"], np.zeros(1))  # stop across ego's path
            if "ego" not in ix or h < 0:
                continue
            a = ix["ego"]
            rows = np.array([a])
            nxt = next_route_edge(routes_of(backend, hd, ["ego"]), snap.route_index[rows])
            truth, _ = p.sense(snap, rows, nxt, [], np.random.default_rng(0))
            nb, f = truth.neighbours, truth.vehicles[0, CURRENT, 0]
            # brute force: hv's body (a rectangle behind its front bumper) vs the path band
            c, s = np.cos(snap.heading[h]), np.sin(snap.heading[h])
            corners = np.array([[snap.x[h] - u * c - w * s, snap.y[h] - u * s + w * c]
                                for u in (0.0, 5.0) for w in (-0.9, 0.9)])  # fmt: skip
            dy = corners[:, 1] - snap.y[a]
            ahead = corners[:, 0].min() - snap.x[a]
            if ahead < 0.5:
                break  # passed (or reached) it
            band = 0.9 + SWEEP_MARGIN  # ego's half width and the margin for a body's sweep
            if not (dy.min() < band and dy.max() > -band and ahead < 90):
                assert nb.front[0, CURRENT] != h
                continue
            seen += 1
            assert nb.front[0, CURRENT] == h and nb.on_path[0]
            assert abs(np.cos(snap.heading[h])) < 0.1  # at right angles to the path
            # in the junction, or leaving it with its rear still inside
            assert hd.lane_edge[snap.lane[h]] < 0 or snap.lane_pos[h] < snap.length[h]
            assert (snap.speed[h] < 0.1) if standing else (snap.speed[h] > 5.0)
            gap = f[0] - f[3]  # distance - extent along the path
            assert gap == pytest.approx(ahead, abs=0.3)
            # no speed along the path (its full speed would give rel. velocity ~13 - v_ego)
            assert f[1] == pytest.approx(-snap.speed[a], abs=0.5)
            assert f[3] == pytest.approx(1.8, abs=0.3) and f[4] == pytest.approx(5.0, abs=0.3)
            assert f[5] == pytest.approx(snap.y[h] - 2.5 * s - snap.y[a], abs=0.3)
        assert seen >= 3
    finally:
        backend.close()


@pytest.mark.parametrize("noise", [False, True])
def test_detection_range_factor_cuts_and_extends_the_sensed_range(tmp_path, noise) -> None:
    """range_factor scales the ranges the sensed frame keeps; the truth keeps at least the
    nominal ones, and the observation still scales distances by the nominal range."""
    sim = start_sim(tmp_path, density=15.0, penetration=1.0)  # ~67 m apart per lane
    try:
        snap = sim.step(30)
        rows = np.flatnonzero(snap.is_av)
        nxt = np.full(len(rows), -1)
        seen = {}
        for f in (0.3, 1.0, 1.5):
            p = Perception(SensorConfig(noise=noise, range_factor=f), sim.hdmap, "normal")
            t, s = p.sense(snap, rows, nxt, [], np.random.default_rng(0))
            found = s.neighbours.vehicle >= 0
            far = np.abs(t.neighbours.distance[found])
            assert np.all(far <= 90.0 * f + 1e-9), f
            assert (t.neighbours.vehicle >= 0).sum() >= found.sum()
            seen[f] = (found.sum(), far.max(initial=0.0))
        assert seen[0.3][0] < seen[1.0][0] < seen[1.5][0], seen
        assert seen[1.5][1] > 90.0  # beyond the nominal LiDAR range
    finally:
        sim.backend.close()
