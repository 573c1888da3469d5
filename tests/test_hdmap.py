"""HD map read with sumolib, checked against SUMO's own view of a generated grid network."""

from __future__ import annotations

import gzip
import math
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
import traci

from mixed_traffic.world.backend import binary
from mixed_traffic.world.hdmap import HDMap, build_hdmap
from mixed_traffic.world.user_scenario import _Net

GRID_EDGES = 24  # 3x3 grid: 12 street segments, one edge each way
GRID_LANES = 2


@pytest.fixture(scope="module")
def grid(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3x3 grid with two lanes per edge, 100 m blocks and traffic lights at every junction."""
    net = tmp_path_factory.mktemp("hdmap") / "grid.net.xml"
    args = [binary("netgenerate"), "--grid", "--grid.number", "3", "--grid.length", "100",
            "-L", str(GRID_LANES), "--tls.guess", "--tls.guess.threshold", "0", "-o", str(net)]  # fmt: skip
    subprocess.run(args, check=True, capture_output=True)
    return net


@pytest.fixture(scope="module")
def hd(grid: Path) -> HDMap:
    return build_hdmap(grid)


@pytest.fixture(scope="module")
def sumo(grid: Path) -> dict:
    """Lanes, lengths, links and signal links as SUMO reports them (over TraCI, so a libsumo
    simulation elsewhere in this process is not disturbed)."""
    label = f"hdmap-test-{os.getpid()}"
    traci.start([binary("sumo"), "-n", str(grid), "--no-step-log", "true"], label=label)
    conn = traci.getConnection(label)
    try:
        lanes = conn.lane.getIDList()
        return {
            "lanes": lanes,
            "edges": conn.edge.getIDList(),
            "length": {lane: conn.lane.getLength(lane) for lane in lanes},
            "shape": {lane: conn.lane.getShape(lane) for lane in lanes},
            "links": {lane: conn.lane.getLinks(lane, extended=True) for lane in lanes},
            "tls": {
                t: conn.trafficlight.getControlledLinks(t) for t in conn.trafficlight.getIDList()
            },
        }
    finally:
        conn.close()


def test_tables_match_sumo(hd: HDMap, sumo: dict) -> None:
    assert len(hd.edge_ids) == GRID_EDGES
    assert set(hd.edge_ids) == {e for e in sumo["edges"] if not e.startswith(":")}
    assert set(hd.lane_ids) == set(sumo["lanes"])  # internal lanes included
    assert hd.edge_lanes.shape == (GRID_EDGES, GRID_LANES)
    for e, edge in enumerate(hd.edge_ids):
        assert [hd.lane_ids[r] for r in hd.edge_lanes[e]] == [f"{edge}_{k}" for k in range(2)]
    assert (hd.lane_edge >= 0).sum() == GRID_EDGES * GRID_LANES
    internal = [i for i, lane in enumerate(hd.lane_ids) if lane.startswith(":")]
    assert (hd.lane_edge[internal] == -1).all()
    lengths = np.array([sumo["length"][lane] for lane in hd.lane_ids])
    np.testing.assert_allclose(hd.lane_length, lengths, atol=1e-6)
    np.testing.assert_allclose(hd.edge_length, hd.lane_length[hd.edge_lanes[:, 0]])
    assert np.allclose(hd.lane_speed[hd.lane_edge >= 0], 13.89)  # netgenerate's default speed


def test_waypoints_follow_the_lane(hd: HDMap, sumo: dict) -> None:
    for row, lane in enumerate(hd.lane_ids):
        first = hd.wp_offset[row]
        assert hd.wp_count[row] == max(1, math.ceil(hd.lane_length[row]))  # every 1 m
        assert (hd.wp_lane[first : first + hd.wp_count[row]] == row).all()
        np.testing.assert_allclose(hd.wp_xyz[first, :2], sumo["shape"][lane][0], atol=1e-6)
    assert len(hd.wp_lane) == hd.wp_count.sum()


def test_connections_are_sumo_links(hd: HDMap, sumo: dict) -> None:
    edge_of = {lane: lane.rsplit("_", 1)[0] for lane in hd.lane_ids}
    expected = set()
    for row, lane in enumerate(hd.lane_ids):
        links = sumo["links"][lane]
        if hd.lane_edge[row] >= 0:
            expected |= {(row, hd.edge_row[edge_of[link[0]]]) for link in links}
        # the primary successor: the straight-on link, else the first; through its junction lane
        straight = [link for link in links if link[6] == "s"] or links[:1]
        nxt = (straight[0][4] or straight[0][0]) if straight else None
        assert hd.lane_next[row] == (hd.lane_row[nxt] if nxt else -1), lane
    assert set(hd.conn_to) == expected
    for (src, to), first in hd.conn_to.items():
        firsts = {
            hd.lane_row[link[4] or link[0]]
            for link in sumo["links"][hd.lane_ids[src]]
            if edge_of[link[0]] == hd.edge_ids[to]
        }
        assert first in firsts


def test_signal_links_are_sumo_signal_links(hd: HDMap, sumo: dict) -> None:
    assert hd.tls_links, "every junction of the grid has a traffic light"
    edge_of = {lane: lane.rsplit("_", 1)[0] for lane in hd.lane_ids}
    signalled = {
        (hd.lane_row[frm], hd.edge_row[edge_of[to]])
        for links in sumo["tls"].values()
        for link in links
        for frm, to, _ in link
    }
    assert set(hd.tls_links) == signalled
    for (src, to), (tls, index) in hd.tls_links.items():
        frm, lane_to, _ = sumo["tls"][tls][index][0]
        assert frm == hd.lane_ids[src] and edge_of[lane_to] == hd.edge_ids[to]


def test_gzipped_network_gives_the_same_map(grid: Path, hd: HDMap, tmp_path: Path) -> None:
    gz = tmp_path / "grid.net.xml.gz"
    gz.write_bytes(gzip.compress(grid.read_bytes()))
    other = build_hdmap(gz)
    for name, value in vars(hd).items():
        if name == "net_file" or name.startswith("_") or name not in HDMap.__dataclass_fields__:
            continue
        got = getattr(other, name)
        assert np.array_equal(got, value) if isinstance(value, np.ndarray) else got == value, name


def test_user_network_graph_matches_sumo(grid: Path, hd: HDMap) -> None:
    net = _Net(grid)
    assert net.lanes == dict.fromkeys(hd.edge_ids, GRID_LANES)
    assert net.nodes == {e: (e[:2], e[2:]) for e in hd.edge_ids}  # netgenerate names A0B0 etc.
    succ = {hd.edge_ids[e]: {hd.edge_ids[n] for n in s} for e, s in hd.edge_successors.items()}
    assert net.succ == {e: succ.get(e, set()) for e in hd.edge_ids}


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (b"", "is not valid XML"),
        (b"\x00\x01garbage", "is not valid XML"),
        (b"<routes/>", r"not a SUMO network \(root element <routes>"),
        (b"<net version='1.20'/>", "contains no edges"),
    ],
)
def test_bad_files_raise_value_error_naming_the_file(
    tmp_path: Path, text: bytes, message: str, capsys: pytest.CaptureFixture
) -> None:
    bad = tmp_path / "bad.net.xml"
    bad.write_bytes(text)
    with pytest.raises(ValueError, match=message) as info:
        build_hdmap(bad)
    assert str(bad) in str(info.value)
    assert capsys.readouterr().out == ""


@pytest.mark.parametrize("gz", [False, True])
def test_truncated_network_raises_value_error(
    grid: Path, tmp_path: Path, gz: bool, capsys: pytest.CaptureFixture
) -> None:
    """Cut past the first read block, so that sumolib's parser (not the root check) fails."""
    data = grid.read_bytes()[: len(grid.read_bytes()) * 3 // 4]
    bad = tmp_path / ("cut.net.xml.gz" if gz else "cut.net.xml")
    bad.write_bytes(gzip.compress(data) if gz else data)
    with pytest.raises(ValueError, match="is not valid XML") as info:
        build_hdmap(bad)
    assert str(bad) in str(info.value)
    assert capsys.readouterr().out == ""
    with pytest.raises(FileNotFoundError, match="missing"):
        build_hdmap(tmp_path / "missing.net.xml")
