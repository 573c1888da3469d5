"""Scenario registry: the bundled scenarios by name, and loading any scenario.

A bundled scenario is a folder ``scenarios/<family>/<variant>/`` with plain SUMO XML sources
(``*.nod.xml``, ``*.edg.xml``, optionally ``*.con.xml``/``*.tll.xml``) and a ``spec.toml``; its
network is built by ``network.build_network``. How traffic enters is one of the spec's flags:
``periodic`` (leavers re-enter behind a virtual leader), ``ring`` (a closed loop), ``inflow``
(an open road fed on a timetable), or none (leavers re-enter at the entry). A user's own ``.net.xml`` or ``.sumocfg`` loads
through ``user_scenario``.
"""

from __future__ import annotations

import tomllib
from functools import cache
from pathlib import Path

from mixed_traffic.config import DEFAULT_EPISODE_LENGTH
from mixed_traffic.paths import SCENARIOS_DIR
from mixed_traffic.world.network import build_network
from mixed_traffic.world.scenario import Route, Scenario

SPLITS = ("train", "eval")


def _spec_files() -> list[Path]:
    return sorted(SCENARIOS_DIR.glob("*/*/spec.toml"))


@cache
def _registry() -> dict[str, Path]:
    reg: dict[str, Path] = {}
    for spec in _spec_files():
        family, variant = spec.parent.parent.name, spec.parent.name
        reg[f"{family}-{variant}"] = spec.parent
        data = tomllib.loads(spec.read_text())
        if data.get("default"):
            reg[family] = spec.parent
    return reg


def list_scenarios() -> list[str]:
    """Names of all bundled scenarios (``family-variant``; a bare family name is its default)."""
    return sorted(_registry())


def train_scenarios() -> list[str]:
    """Every bundled train-split scenario, one name per variant folder (aliases dropped)."""
    return sorted(
        name
        for name, folder in _registry().items()
        if name == f"{folder.parent.name}-{folder.name}" and load_scenario(name).split == "train"
    )


def train_split_scenario(name: str) -> Scenario:
    """``load_scenario(name)``, refused (ValueError) unless it is on the train split: training
    and checkpoint selection must leave the held-out variants unseen."""
    scenario = load_scenario(name)
    if scenario.split != "train":
        raise ValueError(f"{name!r} is a held-out {scenario.split!r} scenario; use train-split "
                         f"ones: {', '.join(train_scenarios())}")  # fmt: skip
    return scenario


def load_scenario(name: str) -> Scenario:
    """A bundled scenario by name, or a user's ``.net.xml(.gz)`` / ``.sumocfg`` by path."""
    if name.endswith((".net.xml", ".net.xml.gz", ".sumocfg")):
        from mixed_traffic.world.user_scenario import load_user_scenario

        return load_user_scenario(Path(name))
    reg = _registry()
    if name not in reg:
        raise ValueError(
            f"unknown scenario {name!r}; known: {', '.join(sorted(reg))} "
            "(or a path to a .net.xml, .net.xml.gz or .sumocfg file)"
        )
    return _load_folder(name, reg[name])


def _load_folder(name: str, folder: Path) -> Scenario:
    spec_path = folder / "spec.toml"
    try:
        spec = tomllib.loads(spec_path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"scenario spec {spec_path} is malformed: {e}") from e
    for key in ("family", "split", "lanes", "routes", "measurement"):
        if key not in spec:
            raise ValueError(f"scenario spec {spec_path} lacks the required key {key!r}")
    if spec["split"] not in SPLITS:
        raise ValueError(f"{spec_path}: split={spec['split']!r} is not one of {SPLITS}")
    boundaries = [k for k in ("periodic", "ring", "inflow") if spec.get(k)]
    if len(boundaries) > 1:
        raise ValueError(f"{spec_path}: {' and '.join(boundaries)} exclude each other")
    routes = tuple(
        Route(
            edges=tuple(r.get("edges", ())),
            origin=r.get("from", ""),
            destination=r.get("to", ""),
            weight=float(r.get("weight", 1.0)),
        )
        for r in spec["routes"]
    )
    scenario = Scenario(
        name=name,
        family=spec["family"],
        split=spec["split"],
        description=spec.get("description", ""),
        net_file=build_network(folder),
        source=folder,
        routes=routes,
        measurement=tuple(spec["measurement"]),
        lanes=int(spec["lanes"]),
        extra_args=tuple(spec.get("sumo_args", ())),
        placement_edges=tuple(spec.get("placement_edges", ())),
        periodic=bool(spec.get("periodic", False)),
        ring=bool(spec.get("ring", False)),
        inflow=bool(spec.get("inflow", False)),
        density=float(spec.get("density", 120.0)),
        episode_length=_seconds(spec, "episode_length", spec_path, zero=False),
        warmup=_seconds(spec, "warmup", spec_path, zero=True),
    )
    length = scenario.episode_length or DEFAULT_EPISODE_LENGTH
    if scenario.warmup is not None and scenario.warmup >= length:
        raise ValueError(f"{spec_path}: warmup={scenario.warmup} s must be shorter than the "
                         f"episode ({length} s)")  # fmt: skip
    _validate(scenario, spec_path)
    return scenario


def _seconds(spec: dict, key: str, spec_path: Path, zero: bool) -> float | None:
    """The spec's ``key`` [s], None when absent; ValueError unless it is in (0, 86400] s, or
    [0, 86400] s where ``zero`` is allowed."""
    if key not in spec:
        return None
    value = spec[key]
    ok = not isinstance(value, bool) and isinstance(value, (int, float))
    if not (ok and (value >= 0 if zero else value > 0) and value <= 86400):
        bounds = "[0, 86400]" if zero else "(0, 86400]"
        raise ValueError(f"{spec_path}: {key}={value!r} must be a time in {bounds} s")
    return float(value)


def _validate(scenario: Scenario, source: Path) -> None:
    hd = scenario.hdmap
    for e in scenario.measurement:
        if e not in hd.edge_row:
            raise ValueError(f"{source}: measurement edge {e!r} is not in the network")
    for r in scenario.routes:
        for e in (*r.edges, r.origin, r.destination):
            if e and e not in hd.edge_row:
                raise ValueError(f"{source}: route edge {e!r} is not in the network")
