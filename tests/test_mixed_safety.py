"""Failure modes of ACC-LC in mixed traffic found on SUMO's game configurations (issue 42),
each reproduced in a small setting on real SUMO."""

from __future__ import annotations

import subprocess
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from agents.rules.acc_lc import AccLcPolicy
from mixed_traffic.env import parallel_env
from mixed_traffic.sensing.lane_graph import CURRENT
from mixed_traffic.sensing.merges import merge_leaders
from mixed_traffic.sensing.neighbours import find_neighbours
from mixed_traffic.world.backend import binary
from mixed_traffic.world.hdmap import load_hdmap

from .test_perception import fake_snapshot


def _road_with_a_stopped_truck(tmp_path: Path, length: float) -> str:
    """A 400 m one-lane road; a truck of ``length`` [m] stands at 150 m (routed by its stop, so
    SUMO drives it as written), and a car departs behind it: the one vehicle of the file that
    can be an AV."""
    (tmp_path / "n.nod.xml").write_text(
        '<nodes><node id="A" x="0" y="0"/><node id="B" x="400" y="0"/></nodes>'
    )
    (tmp_path / "e.edg.xml").write_text(
        '<edges><edge id="AB" from="A" to="B" numLanes="1" speed="13.89"/></edges>'
    )
    subprocess.run([binary("netconvert"), "-n", str(tmp_path / "n.nod.xml"), "-e",
                    str(tmp_path / "e.edg.xml"), "-o", str(tmp_path / "road.net.xml")],
                   check=True, capture_output=True)  # fmt: skip
    (tmp_path / "r.rou.xml").write_text(
        f'<routes><vType id="truck" vClass="truck" length="{length}"/>'
        '<trip id="truck" type="truck" depart="0" departPos="100">'
        '<stop lane="AB_0" endPos="150" duration="1000"/></trip>'
        '<vehicle id="car" depart="1"><route edges="AB"/></vehicle></routes>'
    )
    cfg = tmp_path / "run.sumocfg"
    cfg.write_text('<configuration><input><net-file value="road.net.xml"/>'
                   '<route-files value="r.rou.xml"/></input></configuration>')  # fmt: skip
    return str(cfg)


@pytest.mark.parametrize("length", [12.0, 16.5])
def test_stops_behind_a_vehicle_longer_than_the_observation_scale(tmp_path, length) -> None:
    """The observation clips lengths at 10 m. ACC-LC read SUMO's 12 m trucks (ramp.sumocfg) and
    16.25 m trailers (cross.sumocfg) as 10 m long and crept into their rears in queues; it now
    takes a full-scale length as the longest road vehicle and stops behind."""
    e = parallel_env(scenario=_road_with_a_stopped_truck(tmp_path, length), penetration=1.0,
                     episode_length=25.0)  # fmt: skip
    policy, events = AccLcPolicy(), []
    try:
        obs, _ = e.reset(seed=0)
        while e.agents:
            obs, _, _, _, infos = e.step(policy.actions({a: obs[a] for a in e.agents}))
            events += [i["event"] for i in infos.values() if i["event"]]
            snap = e._snap
            if "av_0" in snap.ids and "truck" in snap.ids:
                av, truck = snap.ids.index("av_0"), snap.ids.index("truck")
                gap = snap.lane_pos[truck] - length - snap.lane_pos[av]
                speed = snap.speed[av]
    finally:
        e.close()
    assert "collision" not in events
    assert speed < 0.1 and 0.5 < gap < 10.0, (gap, speed)  # stopped behind, not far back


def test_a_merging_truck_does_not_hide_the_car_queued_in_front() -> None:
    """SUMO's ``cross`` (a snapshot of a collision at 50 % AVs): the agent queues on 1si_0 for
    its right turn, a car stands 1.7 m ahead at the red light, and a 16.25 m truck crossing on
    green is about to merge into the same exit lane. The truck was reported as the leader
    (side by side at the merge point: gap 0, reported 16.25 m ahead), which hid the car; the
    agent drove into it. A merging vehicle enters the path at the merge point, so it comes
    between the agent and its lane leader only once the leader has passed that point."""
    import sumo

    hd = load_hdmap(Path(sumo.SUMO_HOME) / "tools" / "game" / "cross" / "cross.net.xml")
    snap = fake_snapshot(hd, ["1si_0", "1si_0", ":0_10_0"], [118.63, 125.35, 8.16],
                         [1.6, 0.0, 5.44])  # fmt: skip
    snap = replace(snap, length=np.array([5.0, 5.0, 16.25]))
    turn = np.array([hd.edge_row["3o"]])
    nb = find_neighbours(snap, hd, np.array([0]), 90.0, turn)
    assert nb.front[0, CURRENT] == 1 and nb.front_dist[0, CURRENT] == pytest.approx(6.72)
    truck, gap, _ = merge_leaders(snap, hd, np.array([0]), 90.0, turn)  # no lane leader given
    assert truck[0] == 2 and gap[0] == 0.0
    # the car gone through the junction, beyond the merge point: the truck is the leader
    snap = replace(snap, lane=np.array([hd.lane_row[x] for x in ("1si_0", "3o_0", ":0_10_0")],
                                       np.int32), lane_pos=np.array([118.63, 40.0, 8.16]))  # fmt: skip
    nb = find_neighbours(snap, hd, np.array([0]), 90.0, turn)
    assert nb.front[0, CURRENT] == 2 and nb.on_path[0]


def test_leaves_a_lane_shift_in_its_lane(tmp_path) -> None:
    """SUMO's ``cross``: 1fi widens into 1si through junction lanes that jog 7 m sideways within
    10 m. SUMO's heading follows the jog (50-60 deg off the road's heading, which the HD map
    keeps), and ACC-LC steered against it: the yaw it built carried the AV 1.4 m into the next
    lane after the junction, into a car queued there (a collision at 50 % AVs). It now takes
    the course from its measured lateral speed where SUMO's heading disagrees with it."""
    import sumo

    net = Path(sumo.SUMO_HOME) / "tools" / "game" / "cross" / "cross.net.xml"
    (tmp_path / "r.rou.xml").write_text(
        '<routes><vehicle id="car" depart="0" departSpeed="13.89">'
        '<route edges="1fi 1si 3o 3fo"/></vehicle></routes>'
    )
    cfg = tmp_path / "run.sumocfg"
    cfg.write_text(f'<configuration><input><net-file value="{net}"/>'
                   '<route-files value="r.rou.xml"/></input></configuration>')  # fmt: skip
    e = parallel_env(scenario=str(cfg), penetration=1.0, episode_length=12.0)
    policy, lateral = AccLcPolicy(), []
    try:
        obs, _ = e.reset(seed=0)
        while e.agents:
            obs, *_ = e.step(policy.actions({a: obs[a] for a in e.agents}))
            snap = e._snap
            if "av_0" in snap.ids:
                i = snap.ids.index("av_0")
                if e.hdmap.lane_ids[snap.lane[i]] == "1si_0" and snap.lane_pos[i] < 40.0:
                    lateral.append(abs(snap.lateral[i]))
    finally:
        e.close()
    assert len(lateral) > 10 and max(lateral) < 0.5, max(lateral, default=None)
