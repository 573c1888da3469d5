"""Reward terms with hand-computed values; each terminal reason in a constructed (real SUMO) situation."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from mixed_traffic.config import RewardConfig
from mixed_traffic.env.control import BicycleController
from mixed_traffic.env.reward import (
    TERM_NAMES,
    centreline_distance,
    lane_change_completed,
    reward_terms,
    total_reward,
)
from mixed_traffic.env.termination import (
    collided_mask,
    off_road_mask,
    overlap_mask,
    red_light_mask,
    route_deviation_mask,
    speed_limit_mask,
    terminal_events,
)
from mixed_traffic.env.traffic_terms import TRAFFIC_TERMS, uniform_flow_reward
from mixed_traffic.world.backend import SumoBackend
from mixed_traffic.world.hdmap import load_hdmap
from mixed_traffic.world.network import build_network

from .test_control import DT, isolate, pick_av, start_straight

CFG = RewardConfig()
PAPER = RewardConfig(lane_change_cap=0.0, lane_term="waypoint")


def base_inputs(n: int = 1) -> dict:
    """A calm situation: no front vehicle, on the centreline, no lane change, no jerk."""
    z = np.zeros(n)
    return dict(
        front_distance=np.full(n, np.nan), closing_speed=z, length=np.full(n, 5.0),
        front_length=np.full(n, 5.0), centre_distance=z, lane_width=np.full(n, 3.5),
        terminal=np.zeros(n, bool), speed=np.full(n, 20.0), speed_limit=np.full(n, 25.0),
        lane_changed=np.zeros(n, bool), gap_new=np.full(n, np.nan), gap_old=np.full(n, np.nan),
        lidar_range=90.0, accel=z, prev_accel=z, rear_speed_prev=np.full(n, 20.0),
        rear_speed_now=np.full(n, 20.0), rear_same=np.ones(n, bool),
    )  # fmt: skip


def terms(cfg: RewardConfig = CFG, **over) -> dict:
    return reward_terms(cfg, DT, **{**base_inputs(), **over})


def test_calm_situation() -> None:
    t = terms()
    assert set(t) == set(TERM_NAMES) - set(TRAFFIC_TERMS)  # the traffic's: traffic_terms
    assert t["r2_speed"][0] == pytest.approx(0.8)
    assert all(t[k][0] == 0 for k in t if k != "r2_speed")
    assert total_reward(t, CFG)[0] == pytest.approx(0.8 * 0.8)


def test_ttc() -> None:
    # centre distance 15 m, lengths 5 + 5 -> bumper gap 10 m; closing 5 m/s -> TTC 2 s
    t = terms(front_distance=np.array([15.0]), closing_speed=np.array([5.0]))
    assert t["r1_ttc"][0] == pytest.approx(math.log(2.0 / 4.0))
    # TTC 0.1 s: ln(0.025) = -3.69 -> clipped at -3
    t = terms(front_distance=np.array([5.5]), closing_speed=np.array([5.0]))
    assert t["r1_ttc"][0] == pytest.approx(-3.0)
    # TTC 5 s > G, or opening gap: 0
    assert terms(front_distance=np.array([35.0]), closing_speed=np.array([5.0]))["r1_ttc"][0] == 0
    assert terms(front_distance=np.array([15.0]), closing_speed=np.array([-1.0]))["r1_ttc"][0] == 0


def test_lane_offset() -> None:
    assert terms(centre_distance=np.array([0.7]))["r1_lane"][0] == pytest.approx(-0.2)


def test_lane_offset_from_waypoints(tmp_path) -> None:
    backend, hd, _, _snap = start_straight(tmp_path)
    backend.close()
    lane = hd.edge_lanes[hd.edge_of("meas"), 1]
    w = hd.wp_offset[lane] + 100  # a waypoint 100 m into the lane
    x, y = hd.wp_xyz[w, 0] + 0.3, hd.wp_xyz[w, 1] + 0.7  # 0.3 m ahead of it, 0.7 m left
    d = centreline_distance(hd, np.array([lane]), np.array([100.3]), np.array([x]), np.array([y]))
    assert d[0] == pytest.approx(math.hypot(0.3, 0.7))


def test_tactical_lane_change() -> None:
    changed = lane_change_completed(
        np.array([4, 4, 4]), np.array([5, 5, 9]), np.array([1, 1, 1]), np.array([1, 2, -1])
    )
    assert changed.tolist() == [True, False, False]  # same edge only
    # old lane: 20 m gap; new lane: 50 m -> (50/20 - 1) * 20 = 30
    t = terms(
        PAPER, lane_changed=np.array([True]), gap_old=np.array([20.0]), gap_new=np.array([50.0])
    )
    assert t["r2_lane_change"][0] == pytest.approx(30.0)
    # new lane empty -> capped at the LiDAR range: (90/30 - 1) * 20 = 40
    t = terms(
        PAPER, lane_changed=np.array([True]), gap_old=np.array([30.0]), gap_new=np.array([np.inf])
    )
    assert t["r2_lane_change"][0] == pytest.approx(40.0)
    # into a tighter gap: (10/40 - 1) * 20 = -15; no completed change: 0
    t = terms(
        PAPER, lane_changed=np.array([True]), gap_old=np.array([40.0]), gap_new=np.array([10.0])
    )
    assert t["r2_lane_change"][0] == pytest.approx(-15.0)
    assert terms(gap_old=np.array([40.0]), gap_new=np.array([10.0]))["r2_lane_change"][0] == 0


def test_lane_change_cap() -> None:
    """The default bounds the gap ratio's change at 0.5: at most 20 x 0.5 = 10 per change."""

    def change(old: float, new: float) -> float:
        t = terms(lane_changed=np.array([True]), gap_old=np.array([old]), gap_new=np.array([new]))
        return float(t["r2_lane_change"][0])

    assert change(0.5, np.inf) == pytest.approx(10.0)  # unbounded: (90/0.5 - 1) * 20 = 3580
    assert change(40.0, 10.0) == pytest.approx(-10.0)  # (10/40 - 1) = -0.75 -> -0.5
    assert change(20.0, 25.0) == pytest.approx(5.0)  # within the bound: unchanged


def test_jerk() -> None:
    # |1.5 - (-1.5)| / (2 * 3) = 0.5
    t = terms(accel=np.array([1.5]), prev_accel=np.array([-1.5]))
    assert t["r3_comfort"][0] == pytest.approx(-0.5)


def test_own_acceleration_is_penalised_only_with_its_weight() -> None:
    # r7 = -|a| / acc_thr: braking at 1.5 m/s² is -0.5; w7 = 0 keeps the paper's sum
    t = terms(accel=np.array([-1.5]), prev_accel=np.array([-1.5]))
    assert t["r7_accel"][0] == pytest.approx(-0.5)
    flow = RewardConfig(w_accel=2.0)
    assert total_reward(t, flow)[0] - total_reward(t, CFG)[0] == pytest.approx(-1.0)


def test_uniform_flow_pays_one_at_the_reference_and_nothing_at_a_standstill() -> None:
    """r8 = max(0, 1 - RMS(v - v*) / v*) per agent: its traffic at v* (1), at a standstill (0),
    in waves at v*/2 and 3v*/2 (RMS v*/2: 0.5), crawling at 3v*/4 (0.75), none (0)."""
    star = 0.15  # e.g. 4.5 m/s of a 30 m/s limit
    ratio = star * np.array([1.0, 1.0, 0.0, 0.0, 0.5, 1.5, 0.75, 0.75])
    agent = np.array([0, 0, 1, 1, 2, 2, 3, 3])
    r8 = uniform_flow_reward(ratio, star, agent, np.bincount(agent, minlength=5))
    assert r8 == pytest.approx([1.0, 0.0, 0.5, 0.75, 0.0], abs=1e-12)
    faster = uniform_flow_reward(ratio[:2] * 3, star, agent[:2], np.array([2]))
    assert faster[0] == 0.0  # three times v*: as far off as a standstill, floored at 0


def test_rear_deceleration() -> None:
    # C2 20 -> 19.4 m/s in 0.1 s: -0.6 / (2 * 3 * 0.1) = -1
    t = terms(rear_speed_prev=np.array([20.0]), rear_speed_now=np.array([19.4]))
    assert t["r4_impact"][0] == pytest.approx(-1.0)
    # a drop of 0.05 <= v_thr = 0.1: 0; a different rear vehicle: 0
    assert terms(rear_speed_now=np.array([19.95]))["r4_impact"][0] == 0
    assert terms(rear_speed_now=np.array([19.4]), rear_same=np.array([False]))["r4_impact"][0] == 0


def test_total_weights_and_terminal() -> None:
    t = terms(terminal=np.array([True]), accel=np.array([3.0]))
    assert t["r1_terminal"][0] == -20.0
    expected = 0.9 * -20.0 + 0.8 * 0.8 + 0.6 * -0.5
    assert total_reward(t, CFG)[0] == pytest.approx(expected)


def test_vectorised_over_agents() -> None:
    inp = base_inputs(3)
    inp["speed"] = np.array([0.0, 12.5, 25.0])
    t = reward_terms(CFG, DT, **inp)
    np.testing.assert_allclose(t["r2_speed"], [0.0, 0.5, 1.0])


def test_terminal_priority_and_masks() -> None:
    no, tr = np.zeros(3, bool), np.ones(3, bool)
    off, dev, fast = np.array([1, 0, 0], bool), np.array([0, 0, 1], bool), np.array([1, 0, 1], bool)
    out = terminal_events(no, off, dev, no, fast)
    assert out.tolist() == ["off_road", "", "route_deviation"]
    assert terminal_events(tr, tr, tr, tr, tr).tolist() == ["collision"] * 3
    assert overlap_mask(
        np.array([-0.5, -0.5, 2.0]), np.array([0.2, 2.5, 0.0]), np.full(3, 1.8), np.full(3, 1.8)
    ).tolist() == [True, False, False]
    assert speed_limit_mask(np.array([30.0, 31.0]), np.array([27.78, 27.78]), 0.1).tolist() == [
        False,
        True,
    ]


# ---------------------------------------------------------------------- real SUMO
def test_speeding_fires(tmp_path) -> None:
    backend, hd, cfg, snap = start_straight(tmp_path)
    try:
        vid = pick_av(snap, hd, 1)
        snap = isolate(backend, snap, [vid])
        ctl = BicycleController(cfg.vehicle, hd, DT)
        ctl.add_from_snapshot(snap, [vid], backend)
        fired_at = None
        for step in range(60):
            ctl.step(backend, snap, [vid], np.zeros(1), np.array([3.0]))
            snap = backend.step()
            k = snap.index_of()[vid]
            limit = hd.lane_speed[snap.lane[k : k + 1]]
            if speed_limit_mask(snap.speed[k : k + 1], limit, cfg.speed_tolerance)[0]:
                fired_at = step
                break
        assert fired_at is not None
        assert snap.speed[k] > 27.78 * 1.1
    finally:
        backend.close()


def test_off_road_fires_when_steering_right_on_the_rightmost_lane(tmp_path) -> None:
    backend, hd, cfg, snap = start_straight(tmp_path)
    try:
        vid = pick_av(snap, hd, 0)
        snap = isolate(backend, snap, [vid])
        ctl = BicycleController(cfg.vehicle, hd, DT)
        ctl.add_from_snapshot(snap, [vid], backend)
        reasons = []
        for _ in range(20):
            k = snap.index_of()[vid]
            lane = snap.lane[k : k + 1]
            cmd = ctl.step(backend, snap, [vid], np.array([-np.deg2rad(10.0)]), np.zeros(1))
            off = off_road_mask(hd, lane, cmd.intended_lateral)
            snap = backend.step()
            z = np.zeros(1, bool)
            reasons.append(terminal_events(z, off, z, z, z)[0])
            if reasons[-1]:
                break
        assert reasons[-1] == "off_road"
        assert 2 <= len(reasons) <= 10  # not on the first step, but soon
        k = snap.index_of()[vid]
        # SUMO itself keeps the vehicle on the road, hence the model's offset is checked
        assert abs(snap.lateral[k]) < hd.lane_width[snap.lane[k]] / 2
    finally:
        backend.close()


def test_collision_fires_when_accelerating_into_a_leader(tmp_path) -> None:
    backend, hd, cfg, snap = start_straight(tmp_path)
    try:
        vid = pick_av(snap, hd, 1)
        k = snap.index_of()[vid]
        same = np.flatnonzero((snap.lane == snap.lane[k]) & (snap.lane_pos > snap.lane_pos[k]))
        assert len(same), "the test traffic must have a leader ahead of the AV"
        leader = snap.ids[same[np.argmin(snap.lane_pos[same])]]
        snap = isolate(backend, snap, [vid, leader])
        ctl = BicycleController(cfg.vehicle, hd, DT)
        ctl.add_from_snapshot(snap, [vid], backend)
        event = ""
        for _ in range(300):
            backend.set_speeds([leader], np.array([5.0]))
            ctl.step(backend, snap, [vid], np.zeros(1), np.array([3.0]))
            snap = backend.step()
            coll = collided_mask([vid], snap.collisions)
            z = np.zeros(1, bool)
            event = terminal_events(coll, z, z, z, z)[0]
            if event:
                break
        assert event == "collision"
        assert vid not in snap.ids  # SUMO removed the colliding vehicles
    finally:
        backend.close()


def _sim(net_folder: Path, routes_xml: str, tmp_path: Path):
    net = build_network(net_folder)
    hd = load_hdmap(net)
    rf = tmp_path / "r.rou.xml"
    rf.write_text(routes_xml)
    backend = SumoBackend("libsumo", "traci")
    backend.set_lane_table(hd.lane_ids, hd.lane_edge)
    backend.start(
        ["--net-file", str(net), "--route-files", str(rf), "--step-length", f"{DT}",
         "--lateral-resolution", "0.8", "--no-step-log", "true", "--time-to-teleport", "-1",
         "--collision.action", "remove", "--no-warnings", "true"]
    )  # fmt: skip
    return backend, hd


_AV_TYPE = (
    '<vType id="av" length="5" width="1.8" laneChangeModel="SL2015" latAlignment="arbitrary" '
    'maxSpeedLat="30" lcSublane="0"/>'
)


def test_red_light_fires_on_a_signalised_network(tmp_path) -> None:
    folder = tmp_path / "tls" / "net"
    folder.mkdir(parents=True)
    (folder / "a.nod.xml").write_text(
        '<nodes><node id="w" x="0" y="0"/><node id="c" x="200" y="0" type="traffic_light"/>'
        '<node id="e" x="400" y="0"/></nodes>'
    )
    (folder / "a.edg.xml").write_text(
        '<edges><edge id="in" from="w" to="c" numLanes="1" speed="13.89"/>'
        '<edge id="out" from="c" to="e" numLanes="1" speed="13.89"/></edges>'
    )
    (folder / "a.con.xml").write_text(
        '<connections><connection from="in" to="out" fromLane="0" toLane="0"/></connections>'
    )
    (folder / "a.tll.xml").write_text(
        '<tlLogics><tlLogic id="c" type="static" programID="0" offset="0">'
        '<phase duration="1000" state="r"/></tlLogic>'
        '<connection from="in" to="out" fromLane="0" toLane="0" tl="c" linkIndex="0"/></tlLogics>'
    )
    routes = (
        f'<routes>{_AV_TYPE}<route id="r" edges="in out"/>'
        '<vehicle id="av_0" type="av" route="r" depart="0" departPos="150" departSpeed="10"/></routes>'
    )
    backend, hd = _sim(folder, routes, tmp_path)
    try:
        out_edge = hd.edge_of("out")
        snap = backend.step()
        fired = []
        for _ in range(100):
            states = dict(zip(["c"], backend.tls_states(["c"])))
            k = snap.index_of()["av_0"]
            lane_prev = snap.lane[k : k + 1].copy()
            backend.set_speeds(["av_0"], np.array([10.0]))  # speedMode 32: drives through red
            snap = backend.step()
            k = snap.index_of()["av_0"]
            red = red_light_mask(hd, lane_prev, snap.lane[k : k + 1], np.array([out_edge]), states)
            z = np.zeros(1, bool)
            fired.append(terminal_events(z, z, z, red, z)[0])
            if fired[-1]:
                break
        assert fired[-1] == "red_light"
        assert fired.count("red_light") == 1 and len(fired) > 3  # only at the stop line
        # the same crossing on green does not fire
        green = red_light_mask(
            hd, lane_prev, snap.lane[k : k + 1], np.array([out_edge]), {"c": "G"}
        )
        assert not green[0]
    finally:
        backend.close()


def test_route_deviation_fires_at_a_dead_end_lane(tmp_path) -> None:
    folder = tmp_path / "dev" / "net"
    folder.mkdir(parents=True)
    (folder / "a.nod.xml").write_text(
        '<nodes><node id="w" x="0" y="0"/><node id="c" x="200" y="0"/><node id="e" x="400" y="0"/></nodes>'
    )
    (folder / "a.edg.xml").write_text(
        '<edges><edge id="a" from="w" to="c" numLanes="2" speed="13.89"/>'
        '<edge id="b" from="c" to="e" numLanes="1" speed="13.89"/></edges>'
    )
    (folder / "a.con.xml").write_text(  # only the left lane of "a" continues to "b"
        '<connections><connection from="a" to="b" fromLane="1" toLane="0"/>'
        '<delete from="a" to="b" fromLane="0" toLane="0"/></connections>'
    )
    routes = (
        f'<routes>{_AV_TYPE}<route id="r" edges="a b"/>'
        '<vehicle id="av_0" type="av" route="r" depart="0" departPos="150" departLane="0" '
        'departSpeed="10"/></routes>'
    )
    backend, hd = _sim(folder, routes, tmp_path)
    try:
        routes_rows = np.array([[hd.edge_of("a"), hd.edge_of("b")]])
        snap = backend.step()
        fired = []
        for _ in range(100):
            backend.set_speeds(["av_0"], np.array([10.0]))
            snap = backend.step()
            if "av_0" not in snap.ids:
                break
            k = snap.index_of()["av_0"]
            s = slice(k, k + 1)
            dev = route_deviation_mask(
                hd, snap.edge[s], snap.lane[s], snap.lane_pos[s], routes_rows, snap.route_index[s]
            )
            z = np.zeros(1, bool)
            fired.append(terminal_events(z, z, dev, z, z)[0])
            if fired[-1]:
                break
        assert fired and fired[-1] == "route_deviation"
        assert len(fired) > 3  # not while the lane still has room
        # the left lane (which connects) does not fire at the same position
        left = np.array([hd.edge_lanes[hd.edge_of("a"), 1]])
        assert not route_deviation_mask(
            hd, snap.edge[s], left, snap.lane_pos[s], routes_rows, snap.route_index[s]
        )[0]
        # an edge that is not on the route fires at once
        assert route_deviation_mask(
            hd,
            np.array([hd.edge_of("b")]),
            np.array([hd.edge_lanes[hd.edge_of("b"), 0]]),
            np.array([5.0]),
            np.array([[hd.edge_of("a"), -1]]),
            np.array([0]),
        )[0]
    finally:
        backend.close()


def test_lane_term_from_the_offset_vanishes_at_the_centre() -> None:
    """ACC-LC keeps the lane centre: r1_lane from SUMO's lateral offset is about 0 there, the
    paper's distance to the nearest 1 m waypoint is not (the car sits between waypoints)."""
    from agents.policies import make_policy, stack_obs, to_actions
    from mixed_traffic.env import parallel_env

    means = {}
    for term in ("offset", "waypoint"):
        env = parallel_env(scenario="straight-3lane", penetration=0.5, episode_length=8.0,
                           seed=0, reward=RewardConfig(lane_term=term))  # fmt: skip
        pol, values = make_policy("acc-lc"), []
        obs, _ = env.reset(seed=0)
        for _ in range(79):
            agents = list(env.agents)
            obs, _, _, _, infos = env.step(to_actions(agents, *pol.act(stack_obs(obs, agents))))
            values += [
                infos[a]["reward_terms"]["r1_lane"] for a in agents if infos[a]["reward_terms"]
            ]
        env.close()
        means[term] = float(np.mean(values))
    assert -0.02 < means["offset"] <= 0.0
    assert means["waypoint"] < -0.04
