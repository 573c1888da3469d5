"""Scenario registry, network building, bad inputs and user networks (real SUMO)."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

from mixed_traffic.config import EnvConfig
from mixed_traffic.experiments.scenarios import main
from mixed_traffic.paths import SCENARIOS_DIR
from mixed_traffic.world.backend import SumoBackend, SumoError
from mixed_traffic.world.demand import make_demand
from mixed_traffic.world.network import build_network
from mixed_traffic.world.registry import list_scenarios, load_scenario
from mixed_traffic.world.scenario import sumo_args

from .conftest import start_sim

FAMILIES = ("straight", "highway", "bottleneck", "merge", "urban")


def run_episode(config: EnvConfig, seconds: float) -> tuple[int, int]:
    """Run ``seconds`` of ``config``; returns (vehicles at the end, collisions)."""
    sim = start_sim(Path(tempfile.mkdtemp()), config=config)
    collisions = 0
    try:
        for _ in range(round(seconds / config.step_length)):
            snap = sim.step()
            collisions += len(snap.collisions)
    finally:
        sim.backend.close()
    return len(snap.ids), collisions


# --------------------------------------------------------------------------- registry
def test_every_family_has_train_and_eval_variants() -> None:
    names = list_scenarios()
    for family in FAMILIES:
        assert family in names, f"no default variant for {family}"
        splits = {load_scenario(n).split for n in names if n.startswith(f"{family}-")}
        assert splits == {"train", "eval"}, f"{family}: splits {splits}"


def test_family_geometry() -> None:
    hw = load_scenario("highway").hdmap
    z = hw.wp_xyz[:, 2]
    assert z.max() - z.min() > 5.0, "highway has no gradient"
    heading = np.unwrap(hw.wp_heading[hw.wp_offset[0] : hw.wp_offset[0] + hw.wp_count[0]])
    assert np.ptp(heading) > 0.3 or load_scenario("highway").measurement_length >= 990
    bn = load_scenario("bottleneck")
    lanes = {int(bn.hdmap.edge_num_lanes[bn.hdmap.edge_of(e)]) for e in bn.measurement}
    assert len(lanes) == 2, "bottleneck measurement must span the lane drop"
    urban = load_scenario("urban")
    assert len({link[0] for link in urban.hdmap.tls_links.values()}) >= 9
    assert {13.89, 16.67} <= {round(float(v), 2) for v in urban.hdmap.lane_speed}
    assert all(r.origin and r.destination for r in urban.routes), "urban needs routed trips"
    assert len(load_scenario("merge").routes) >= 2


def test_list_cli_prints_every_scenario(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--list"]) == 0
    out = capsys.readouterr().out
    for name in list_scenarios():
        assert name in out


def test_network_rebuilds_when_a_source_changes(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("MIXED_TRAFFIC_CACHE", str(tmp_path / "cache"))
    folder = tmp_path / "straight" / "copy"
    shutil.copytree(SCENARIOS_DIR / "straight" / "3lane", folder)
    first = build_network(folder)
    assert build_network(folder) == first  # cached
    edg = folder / "road.edg.xml"
    edg.write_text(edg.read_text().replace('speed="27.78"', 'speed="22.22"'))
    second = build_network(folder)
    assert second != first and second.exists()
    assert 'speed="22.22"' in second.read_text()


# --------------------------------------------------------------------------- bad input
def test_unknown_scenario_is_named() -> None:
    with pytest.raises(ValueError, match="unknown scenario 'nowhere'"):
        load_scenario("nowhere")


@pytest.mark.parametrize("density", [0.0, -5.0, 3 * 1000 / 7 + 1])
def test_density_out_of_range(density: float) -> None:
    with pytest.raises(ValueError, match="density"):
        config = EnvConfig(density=density)
        load_scenario(config.scenario).check_density(config.density)


@pytest.mark.parametrize("penetration", [-0.1, 1.5])
def test_penetration_out_of_range(penetration: float) -> None:
    with pytest.raises(ValueError, match="penetration"):
        EnvConfig(penetration=penetration)


def test_missing_and_malformed_networks(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"missing\.net\.xml does not exist"):
        load_scenario(str(tmp_path / "missing.net.xml"))
    bad = tmp_path / "bad.net.xml"
    bad.write_text("<net><edge id='a'")
    with pytest.raises(ValueError, match=r"bad\.net\.xml is malformed"):
        load_scenario(str(bad))
    other = tmp_path / "other.net.xml"
    other.write_text("<routes/>")
    with pytest.raises(ValueError, match="not a SUMO network"):
        load_scenario(str(other))
    empty = tmp_path / "empty.net.xml"
    empty.write_text("<net/>")
    with pytest.raises(ValueError, match="no edges"):
        load_scenario(str(empty))
    cfg = tmp_path / "nonet.sumocfg"
    cfg.write_text("<configuration><input/></configuration>")
    with pytest.raises(ValueError, match=r"nonet\.sumocfg has no net-file"):
        load_scenario(str(cfg))


def test_sumo_start_failure_is_a_sumo_error(tmp_path: Path) -> None:
    config = EnvConfig()
    sc = load_scenario(config.scenario)
    routes = tmp_path / "bad.rou.xml"
    routes.write_text(
        '<routes><vehicle id="v" depart="0"><route edges="no_such_edge"/></vehicle></routes>'
    )
    backend = SumoBackend("libsumo", "error")
    with pytest.raises(SumoError, match="no_such_edge"):
        backend.start(sumo_args(sc, config, routes, seed=0))
    assert not backend.running


# --------------------------------------------------------------------------- user files
def test_user_net_gets_generated_trips(tmp_path: Path) -> None:
    net = tmp_path / "grid.net.xml"
    shutil.copy(load_scenario("urban-eval").net_file, net)
    sc = load_scenario(str(net))
    assert sc.routes and all(r.origin and r.destination for r in sc.routes)
    assert len({r.origin for r in sc.routes}) > 1, "route choice needs several origins"
    assert len(sc.measurement) == len(sc.hdmap.edge_ids)  # the whole network
    assert sc.lanes == 2
    vehicles, _ = run_episode(EnvConfig(scenario=str(net), density=60), 10.0)
    assert vehicles > 50


def test_a_user_net_with_a_long_edge_warns_with_the_fix(tmp_path: Path) -> None:
    """SUMO's sublane model slows with the square of the vehicles on one edge: loading names
    the edge and netconvert's split; the split network loads quietly."""
    import warnings

    for name, args in (
        ("long", ""),
        ("split", "--geometry.max-segment-length 500 --geometry.split"),
    ):
        folder = tmp_path / name
        folder.mkdir()
        (folder / "r.nod.xml").write_text(
            '<nodes><node id="a" x="0" y="0"/><node id="b" x="4000" y="0"/></nodes>'
        )
        (folder / "r.edg.xml").write_text(
            '<edges><edge id="main" from="a" to="b" numLanes="2" speed="30"/></edges>'
        )
        (folder / "netconvert.args").write_text(args)
        net = tmp_path / f"{name}.net.xml"
        shutil.copy(build_network(folder), net)
        if name == "long":
            with pytest.warns(UserWarning, match=r"edge 'main' is 4\.0 km long.*--geometry\.split"):
                load_scenario(str(net))
        else:
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                assert len(load_scenario(str(net)).hdmap.edge_ids) == 8


def test_user_sumocfg_uses_its_own_vehicles(tmp_path: Path) -> None:
    shutil.copy(load_scenario("straight").net_file, tmp_path / "road.net.xml")
    (tmp_path / "routes.rou.xml").write_text(
        """<routes>
    <route id="main" edges="warmup meas exit"/>
    <vehicle id="av_7" depart="0" route="main"/>
    <vehicle id="car" depart="1"><route edges="warmup meas exit"/></vehicle>
    <trip id="trip" depart="2" from="warmup" to="exit"/>
    <flow id="f" begin="0" end="20" period="2" route="main"/>
    <flow id="n" begin="0" number="5" from="warmup" to="exit"/>
    <flow id="h" begin="0" end="10" vehsPerHour="720" route="main"/>
    <flow id="p" begin="0" end="100" probability="0.3" route="main"/>
</routes>"""
    )
    cfg = tmp_path / "run.sumocfg"
    cfg.write_text(
        '<configuration><input><net-file value="road.net.xml"/>'
        '<route-files value="routes.rou.xml"/></input></configuration>'
    )
    sc = load_scenario(str(cfg))
    n_prob = len(sc.own_vehicles) - (3 + 10 + 5 + 2)
    assert 10 < n_prob < 50, "probability flow: about 0.3 per second over 100 s"
    config = sc.configure(EnvConfig(scenario=str(cfg), penetration=0.25, seed=3))
    demand = make_demand(sc, config, np.random.default_rng(3))
    n = len(sc.own_in_episode(config.episode_length))  # the 100 s probability flow: 120 s
    assert n < len(sc.own_vehicles) and len(demand.av_ids) == round(0.25 * n)
    assert sorted(demand.av_ids) == sorted(f"av_{i}" for i in range(round(0.25 * n)))
    hv = [v.vid for v in demand.vehicles if not v.is_av]
    assert len(set(hv)) == len(hv) and not any(v.startswith("av_") for v in hv)
    own = {v.vid for v in sc.own_vehicles}
    renamed = {f"hv_{v}" for v in own if v.startswith("av_")}
    assert set(hv) <= (own - {"av_7"}) | renamed, "conventional vehicles keep their ids"
    vehicles, collisions = run_episode(config, 10.0)
    assert vehicles > 0 and collisions == 0
