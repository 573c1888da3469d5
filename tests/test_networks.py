"""Networks the project has never seen, generated here with SUMO's own tools (netgenerate,
netconvert): lane permissions (sidewalks, bike lanes, bike-only roads), gzip, a single edge
(issue 24, part 1). Episodes run in real SUMO with ACC-LC AVs."""

from __future__ import annotations

import gzip
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from mixed_traffic.config import EnvConfig
from mixed_traffic.env import parallel_env
from mixed_traffic.experiments.bench_env import bench_actions
from mixed_traffic.experiments.runner import run_episode
from mixed_traffic.schema import TERMINAL_REASONS
from mixed_traffic.world.backend import binary
from mixed_traffic.world.registry import load_scenario

NODES = """<nodes><node id="A" x="0" y="0"/><node id="B" x="600" y="0"/>
<node id="C" x="1200" y="0"/></nodes>"""


def _netgenerate(out: Path, *args: str) -> Path:
    subprocess.run([binary("netgenerate"), "--grid", "--grid.number", "3", "--grid.length",
                    "200", "--default.lanenumber", "2", *args, "-o", str(out)],
                   check=True, capture_output=True, timeout=120)  # fmt: skip
    return out


def _netconvert(folder: Path, edges: str, name: str) -> Path:
    (folder / "n.nod.xml").write_text(NODES)
    (folder / "e.edg.xml").write_text(f"<edges>{edges}</edges>")
    out = folder / name
    subprocess.run([binary("netconvert"), "-n", str(folder / "n.nod.xml"), "-e",
                    str(folder / "e.edg.xml"), "-o", str(out)],
                   check=True, capture_output=True, timeout=120)  # fmt: skip
    return out


def _episode(net: Path, **kw) -> dict:
    cfg = EnvConfig(**{"scenario": str(net), "penetration": 0.5, "episode_length": 25.0,
                       "seed": 0, **kw})  # fmt: skip
    return run_episode(cfg, "acc-lc", warmup=0.0)


def test_sidewalks_and_bike_lanes_carry_no_car(tmp_path: Path) -> None:
    net = _netgenerate(tmp_path / "side.net.xml", "--sidewalks.guess", "--bikelanes.guess")
    sc = load_scenario(str(net))
    hd = sc.hdmap
    assert sc.lanes == 2, "density counts the car lanes, not sidewalks or bike lanes"
    assert (~hd.lane_car).any() and hd.lane_car.any()
    # no connection or neighbour of a car lane leads onto a lane cars may not use
    assert all(hd.lane_car[a] and hd.lane_car[b] for (a, _), b in hd.conn_to.items())
    for side in (-1, 1):
        nb = hd.neighbour_lane(np.flatnonzero(hd.lane_car), side)
        assert hd.lane_car[nb[nb >= 0]].all()
    # random decisions within the mask: no car ever stands on a sidewalk or a bike lane
    env = parallel_env(scenario=str(net), density=30.0, penetration=0.5, episode_length=25.0)
    obs, _ = env.reset(seed=0)
    space, rng, steps, agents = env.action_space(env.agents[0]), np.random.default_rng(0), 0, 0
    while env.agents:
        obs, *_ = env.step(bench_actions(env, obs, space, rng, "random"))
        lanes = env._snap.lane[env._snap.lane >= 0]
        assert hd.lane_car[lanes].all(), "a car on a lane that SUMO's permissions bar"
        steps, agents = steps + 1, agents + len(env.agents)
    env.close()
    assert steps >= 240 and agents > 0


def test_a_gzipped_network_runs(tmp_path: Path) -> None:
    net = _netgenerate(tmp_path / "grid.net.xml.gz")
    assert net.read_bytes()[:2] == b"\x1f\x8b"
    record = _episode(net, density=30.0)
    assert record["metrics"]["av_trips"] > 0


def test_a_single_edge_road_runs(tmp_path: Path) -> None:
    net = _netconvert(tmp_path, '<edge id="AB" from="A" to="B" numLanes="2" speed="25"/>',
                      "one.net.xml")  # fmt: skip
    sc = load_scenario(str(net))
    assert [(r.origin, r.destination) for r in sc.routes] == [("AB", "AB")]
    record = _episode(net, density=40.0)
    assert record["metrics"]["av_trips"] > 0 and record["metrics"]["collisions"] == 0


def test_a_network_without_car_lanes_is_named(tmp_path: Path) -> None:
    edges = ('<edge id="AB" from="A" to="B" numLanes="1" allow="bicycle"/>'
             '<edge id="BC" from="B" to="C" numLanes="1" allow="bicycle pedestrian"/>')  # fmt: skip
    net = _netconvert(tmp_path, edges, "bike.net.xml")
    with pytest.raises(ValueError, match="no lane that passenger cars may use"):
        load_scenario(str(net))
    out = subprocess.run(
        ["python", "-m", "mixed_traffic.evaluate", "--policy", "acc-lc", "--scenario", str(net)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert out.stderr.strip().splitlines()[-1].endswith("bicycles or rail)")


def test_a_sumocfg_runs_as_sumo_would_run_it(tmp_path: Path) -> None:
    """Its vTypes, additional files, begin, end and step length hold (issue 24, part 2)."""
    shutil.copy(load_scenario("straight").net_file, tmp_path / "road.net.xml")
    (tmp_path / "routes.rou.xml").write_text("""<routes>
  <vType id="car" vClass="passenger" length="4.5" accel="2.0" decel="4.0" maxSpeed="30"/>
  <vType id="truck" vClass="truck" length="12" accel="1.0" maxSpeed="25"/>
  <route id="main" edges="warmup meas exit"/>
  <flow id="cars" type="car" begin="100" end="400" period="2" route="main"/>
  <flow id="trucks" type="truck" begin="100" end="400" period="10" route="main"/>
  <vehicle id="plain" depart="101" route="main"/>
</routes>""")
    (tmp_path / "det.add.xml").write_text('<additional><inductionLoop id="loop0" lane="meas_0" '
                                          'pos="50" period="10" file="loops.xml"/></additional>')  # fmt: skip
    cfg = tmp_path / "run.sumocfg"
    cfg.write_text('<configuration><input><net-file value="road.net.xml"/><route-files '
                   'value="routes.rou.xml"/><additional-files value="det.add.xml"/></input><time>'
                   '<begin value="100"/><end value="130"/><step-length value="0.2"/></time>'
                   "</configuration>")  # fmt: skip
    sc = load_scenario(str(cfg))
    assert (sc.step_length, sc.end) == (0.2, 30.0)
    with pytest.raises(ValueError, match="does not apply"):
        parallel_env(scenario=str(cfg), density=50.0)
    env = parallel_env(scenario=str(cfg), penetration=0.3, episode_length=60.0)
    assert (env.config.step_length, env.config.episode_length) == (0.2, 30.0)
    # flows become vehicles over the episode only: 21 of the file's 181 depart in its 30 s
    assert len(sc.own_vehicles) == 181 and len(env.possible_agents) == round(0.3 * 21)
    env.reset(seed=0)
    assert env.sim_time < 2.0, "the episode's clock starts at the file's begin"
    types, steps = {}, 0
    api = env._backend._api.vehicle
    while env.agents:
        env.step({a: {"decision": 1, "params": np.zeros((3, 2), np.float32)} for a in env.agents})
        types.update({v: api.getTypeID(v) for v in api.getIDList() if not v.startswith("av_")})
        steps += 1
    env.close()
    assert steps <= 150  # 30 s of 0.2 s steps
    assert {"car", "truck"} <= set(types.values())
    for vid, vtype in types.items():  # each keeps its type; "plain" has none: SUMO's default
        assert vtype == {"cars": "car", "trucks": "truck"}.get(vid.split(".")[0], "DEFAULT_VEHTYPE")
    assert "loop0" in (tmp_path / "loops.xml").read_text()  # the additional file ran


def test_acc_lc_gives_way_at_unsignalised_junctions(tmp_path: Path) -> None:
    """Right of way from SUMO: the camera shows a give-way line, red while SUMO holds the AV's
    link closed (issue 24, part 3). Without it this episode had 4 collisions at junctions."""
    net = _netgenerate(tmp_path / "grid.net.xml")
    hd = load_scenario(str(net)).hdmap
    assert hd.lane_yields.any(), "netgenerate's priority junctions have minor links"
    record = _episode(net, density=30.0, seed=2, episode_length=60.0)
    m = record["metrics"]
    # (the 23 trips before the speed-limit preview were mostly AVs removed for speeding)
    assert m["av_trips"] >= 4 and m["collisions"] == 0
    assert sum(m[f"terminal_{r}"] for r in TERMINAL_REASONS) == 0


def test_a_sumocfg_keeps_what_the_env_does_not_model(tmp_path: Path) -> None:
    """A person on foot, a bus routed only by its stops and bikes on a bike-only road go to
    SUMO as written and are never AVs; the cars are the traffic the AVs come from."""
    net = _netconvert(tmp_path, '<edge id="AB" from="A" to="B" numLanes="2" speed="14" '
                      'sidewalkWidth="2"/><edge id="BC" from="B" to="C" numLanes="2" speed="14" '
                      'sidewalkWidth="2"/><edge id="BK" from="B" to="C" numLanes="1" '
                      'allow="bicycle"/>', "mixed.net.xml")  # fmt: skip
    (tmp_path / "stops.add.xml").write_text('<additional><busStop id="s1" lane="BC_1" '
                                            'startPos="20" endPos="40"/></additional>')  # fmt: skip
    (tmp_path / "r.rou.xml").write_text(
        '<routes><vType id="bus" vClass="bus" length="12"/><route id="bike_way" edges="BK"/>'
        '<flow id="cars" begin="0" end="30" period="2" from="AB" to="BC"/>'
        '<trip id="bus0" type="bus" depart="3"><stop busStop="s1" duration="5"/></trip>'
        '<flow id="bikes" type="DEFAULT_BIKETYPE" begin="1" end="30" period="5" '
        'route="bike_way"/><person id="walker" depart="2"><walk edges="AB BC"/></person>'
        "</routes>"
    )
    cfg = tmp_path / "mixed.sumocfg"
    cfg.write_text(f'<configuration><input><net-file value="{net.name}"/><route-files '
                   'value="r.rou.xml"/><additional-files value="stops.add.xml"/></input>'
                   "</configuration>")  # fmt: skip
    sc = load_scenario(str(cfg))
    assert len(sc.own_vehicles) == 15  # the cars only
    env = parallel_env(scenario=str(cfg), penetration=1.0, episode_length=30.0)
    assert len(env.possible_agents) == 15
    env.reset(seed=0)
    api, seen = env._backend._api, set()
    while env.agents:
        seen |= set(api.vehicle.getIDList()) | {f"person:{p}" for p in api.person.getIDList()}
        env.step({a: {"decision": 1, "params": np.zeros((3, 2), np.float32)} for a in env.agents})
    env.close()
    assert {"bus0", "bikes.0", "person:walker"} <= seen
    assert not any(v.startswith("av_") for v in ("bus0", "bikes.0"))


def test_a_sumocfg_in_sumos_other_forms(tmp_path: Path) -> None:
    """A gzipped route file with a route distribution, vehicles in an additional file, a
    begin in h:m:s; a file of trains only gets a named error (SUMO's game examples)."""
    shutil.copy(load_scenario("straight").net_file, tmp_path / "road.net.xml")
    with gzip.open(tmp_path / "r.rou.xml.gz", "wt") as f:
        f.write('<routes><routeDistribution id="mix"><route id="long" edges="warmup meas exit" '
                'probability="3"/><route id="short" edges="meas exit" probability="1"/>'
                '</routeDistribution><flow id="f" begin="1:0:0" end="1:1:0" period="1" '
                'route="mix"/></routes>')  # fmt: skip
    (tmp_path / "more.add.xml").write_text('<additional><vehicle id="extra" depart="3605" '
                                           'route="long2"/><route id="long2" edges="warmup meas '
                                           'exit"/></additional>')  # fmt: skip
    (tmp_path / "det.add.xml").write_text('<additional><inductionLoop id="l" lane="meas_0" '
                                          'pos="5" period="10" file="loops.xml"/></additional>')  # fmt: skip
    cfg = tmp_path / "run.sumocfg"
    cfg.write_text('<configuration><input><net-file value="road.net.xml"/><route-files '
                   'value="r.rou.xml.gz"/><additional-files value="more.add.xml,det.add.xml"/>'
                   '</input><time><begin value="1:0:0"/></time></configuration>')  # fmt: skip
    sc = load_scenario(str(cfg))
    assert sc.begin == 3600.0 and len(sc.own_vehicles) == 61
    firsts = [sc.routes[v.route].edges[0] for v in sc.own_vehicles if v.vid != "extra"]
    assert 0.6 < firsts.count("warmup") / len(firsts) < 0.9  # drawn 3 : 1
    assert sc.extra_args == ("--additional-files", str((tmp_path / "det.add.xml").resolve()))
    env = parallel_env(scenario=str(cfg), penetration=0.0, episode_length=10.0)
    env.reset(seed=0, options={"allow_no_agents": True})
    while env.sim_time < 9.9:
        env.step({})
    seen = set(env._backend._api.vehicle.getIDList())
    env.close()
    assert "extra" in seen  # once: from the episode's route file only
    rails = tmp_path / "trains.rou.xml"
    rails.write_text('<routes><vType id="t" vClass="rail" length="52"/><flow id="f" type="t" '
                     'begin="0" end="10" period="5" from="warmup" to="exit"/></routes>')  # fmt: skip
    (tmp_path / "t.sumocfg").write_text('<configuration><input><net-file value="road.net.xml"/>'
                                        '<route-files value="trains.rou.xml"/></input>'
                                        "</configuration>")  # fmt: skip
    with pytest.raises(
        ValueError, match=r"no vehicle on roads the AVs may use \(only vClass 'rail'\)"
    ):
        load_scenario(str(tmp_path / "t.sumocfg"))


def test_a_route_that_sumo_changes_is_followed_not_a_deviation(tmp_path: Path) -> None:
    """A rerouter on the destination edge sends every vehicle on (as on SUMO's race track,
    where all 13 AV trips ended as route deviations): the AVs follow SUMO's new route."""
    net = _netgenerate(tmp_path / "grid.net.xml")
    (tmp_path / "r.rou.xml").write_text('<routes><flow id="f" begin="0" end="20" period="4" '
                                        'from="A0A1" to="A1A2"/></routes>')  # fmt: skip
    (tmp_path / "rr.add.xml").write_text('<additional><rerouter id="on" edges="A1A2"><interval '
                                         'begin="0" end="1000"><destProbReroute id="B2C2"/>'
                                         "</interval></rerouter></additional>")  # fmt: skip
    cfg = tmp_path / "run.sumocfg"
    cfg.write_text(f'<configuration><input><net-file value="{net.name}"/><route-files '
                   'value="r.rou.xml"/><additional-files value="rr.add.xml"/></input>'
                   "</configuration>")  # fmt: skip
    config = EnvConfig(scenario=str(cfg), penetration=1.0, episode_length=120.0, seed=0)
    m = run_episode(config, "acc-lc", warmup=0.0)["metrics"]
    # (before, all 5 trips that ended in 90 s were route deviations at the old route's end)
    assert m["av_trips"] >= 3 and m["terminal_route_deviation"] == 0


def test_avs_derive_from_a_sumocfg_type_of_another_class(tmp_path: Path) -> None:
    """A file with only racing cars of class vip on vip-only lanes: the AVs are vip cars the
    size of the racing type, and the lanes are theirs (issue 24, part 2)."""
    net = _netconvert(tmp_path, '<edge id="AB" from="A" to="B" numLanes="2" speed="40" '
                      'allow="vip"/><edge id="BC" from="B" to="C" numLanes="2" speed="40" '
                      'allow="vip"/>', "track.net.xml")  # fmt: skip
    (tmp_path / "race.rou.xml").write_text(
        '<routes><vType id="racecar" vClass="vip" length="4.2" width="2.0" minGap="1"/>'
        '<flow id="cars" type="racecar" begin="0" end="20" period="1" from="AB" to="BC"/>'
        "</routes>"
    )
    cfg = tmp_path / "race.sumocfg"
    cfg.write_text(f'<configuration><input><net-file value="{net.name}"/><route-files '
                   'value="race.rou.xml"/></input></configuration>')  # fmt: skip
    with pytest.raises(ValueError, match="no lane that passenger cars may use"):
        load_scenario(str(net))  # a bare network gets passenger cars
    sc = load_scenario(str(cfg))
    assert (sc.vclass, sc.av_size) == ("vip", (4.2, 2.0)) and sc.hdmap.lane_car.any()
    env = parallel_env(scenario=str(cfg), penetration=0.5, episode_length=20.0)
    assert (env.config.vehicle.length, env.config.vehicle.width) == (4.2, 2.0)
    env.reset(seed=0)
    assert env._backend._api.vehicletype.getVehicleClass("av") == "vip"
    seen = set()
    while env.agents:
        seen |= set(env.agents)
        env.step({a: {"decision": 1, "params": np.zeros((3, 2), np.float32)} for a in env.agents})
    env.close()
    assert len(seen) >= 5
