"""Signal plans of the bundled urban grids: four stages with protected left turns, the arterial
coordinated as a green wave.

    python -m mixed_traffic.experiments.signal_plans scenarios/urban/grid3x3 \\
        --arterial W1toJ0_1 J0_1toJ1_1 J1_1toJ2_1 J2_1toE1

netconvert's two-stage plan (``--tls.layout opposites``) lets left turns go on a permissive
green against oncoming traffic. This tool splits each stage into a through stage with the lefts
on red and a protected left stage, in a fixed cycle, and writes them as ``signals.tll.xml``
into the scenario folder, where the scenario build (``world.network``) passes it to netconvert.
Junctions along the arterial get offsets for a green wave in its first direction.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import sumolib

from mixed_traffic.world.backend import binary


@dataclass(frozen=True)
class Stages:
    """Durations of one cycle [s]: arterial through, arterial left, cross through, cross left,
    then yellow and all-red after each (cycle = sum of the four + 4 x (yellow + all-red))."""

    arterial: float = 37.0
    arterial_left: float = 7.0
    cross: float = 19.0
    cross_left: float = 5.0
    yellow: float = 3.0
    all_red: float = 2.0
    progression_speed: float = 16.67
    """Speed of the green wave along the arterial [m/s]."""


def _split(state: str, lefts: set[int]) -> tuple[str, str]:
    """A two-stage state -> (through stage with the lefts on red, protected left stage)."""
    through = "".join("r" if i in lefts else ch for i, ch in enumerate(state))
    left = "".join("G" if i in lefts and ch in "Gg" else "r" for i, ch in enumerate(state))
    return through, left


def _direction(from_lane, to_lane) -> str:
    """SUMO's direction code of the connection between two lanes (s, r, l, t, ...)."""
    return next(c.getDirection() for c in from_lane.getOutgoing() if c.getToLane() == to_lane)


def _amber(state: str) -> str:
    return "".join("y" if ch in "Gg" else "r" for ch in state)


def plan(net: sumolib.net.Net, tls, arterial: list[str], stages: Stages) -> list[tuple[float, str]]:
    """(duration [s], state) of each phase of ``tls`` in the four-stage plan."""
    program = next(iter(tls.getPrograms().values()))
    greens = [p.state for p in program.getPhases() if "G" in p.state or "g" in p.state]
    lefts = {c[2] for c in tls.getConnections() if _direction(c[0], c[1]) in "lL"}
    art_links = {c[2] for c in tls.getConnections() if c[0].getEdge().getID() in arterial}
    first = next((g for g in greens if any(g[i] in "Gg" for i in art_links)), greens[0])
    second = next((g for g in greens if g is not first), first)
    phases: list[tuple[float, str]] = []
    for state, main, side in ((first, stages.arterial, stages.arterial_left),
                              (second, stages.cross, stages.cross_left)):  # fmt: skip
        through, left = _split(state, lefts)
        for dur, st in ((main, through), (side, left)):
            if "G" not in st and "g" not in st:
                continue
            phases += [(dur, st), (stages.yellow, _amber(st)), (stages.all_red, "r" * len(st))]
    return phases


def offsets(net: sumolib.net.Net, arterial: list[str], speed: float) -> dict[str, float]:
    """Junction id -> offset [s] for a green wave along ``arterial`` at ``speed``."""
    out, travelled = {}, 0.0
    for eid in arterial:
        edge = net.getEdge(eid)
        travelled += edge.getLength()
        out[edge.getToNode().getID()] = travelled / speed
    return out


def write_plans(folder: Path, arterial: list[str], stages: Stages = Stages()) -> Path:
    """Build ``folder``'s network with the two-stage plans and write ``signals.tll.xml``."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "net.net.xml"
        cmd = [binary("netconvert"), "--node-files", ",".join(map(str, folder.glob("*.nod.xml"))),
               "--edge-files", ",".join(map(str, folder.glob("*.edg.xml"))),
               "--tls.layout", "opposites", "--no-turnarounds", "true", "-o", str(out),
               "--no-warnings"]  # fmt: skip
        subprocess.run(cmd, check=True, capture_output=True)
        net = sumolib.net.readNet(str(out), withPrograms=True)
    shift = offsets(net, arterial, stages.progression_speed)
    root = ET.Element("tlLogics")
    for tls in net.getTrafficLights():
        phases = plan(net, tls, arterial, stages)
        cycle = sum(d for d, _ in phases)
        logic = ET.SubElement(root, "tlLogic", id=tls.getID(), type="static", programID="0",
                              offset=f"{shift.get(tls.getID(), 0.0) % cycle:.1f}")  # fmt: skip
        for dur, state in phases:
            ET.SubElement(logic, "phase", duration=f"{dur:g}", state=state)
    ET.indent(root)
    path = folder / "signals.tll.xml"
    ET.ElementTree(root).write(path, encoding="utf-8", xml_declaration=True)
    return path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m mixed_traffic.experiments.signal_plans",
                                description=__doc__.split("\n\n")[0])  # fmt: skip
    p.add_argument("folder", type=Path, help="scenario folder with *.nod.xml and *.edg.xml")
    p.add_argument("--arterial", nargs="+", required=True, metavar="EDGE",
                   help="edges of the coordinated arterial, in the direction of the green wave")  # fmt: skip
    args = p.parse_args(argv)
    print(write_plans(args.folder, args.arterial))
    return 0


if __name__ == "__main__":
    sys.exit(main())
