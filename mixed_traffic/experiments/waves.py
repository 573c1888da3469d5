"""Check the wave scenarios of issue 42: rings of other lengths and the open wave road.

    python -m mixed_traffic.experiments.waves [--seeds 0 1 2] [--parts ring road] [--workers 2]

Every episode runs through ``runner.run_episode`` (records appended to ``--out`` if given);
the table gives each figure as the mean over the seeds with its range:

- ``ring_waves``: on rings scaled to each of ``ring_lengths`` at ``ring_density``, all-human
  traffic keeps a speed std of at least 1.5 m/s over ``ring_episode`` (every seed);
- ``ring_damping``: one FollowerStopper on the same ring halves that std (mean over seeds);
- ``road_waves``: on each of ``roads``, all human, the measurement segment upstream of the
  slow zone has a speed std of at least 1.5 m/s and waves travelling upstream at 10 to 25
  km/h (every seed);
- ``road_terminal``: each of ``policies`` at each of ``penetrations`` drives there with AVs
  (in every seed) and without a terminal event.
"""

from __future__ import annotations

import argparse
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from mixed_traffic.config import RING_LENGTH_RANGE, EnvConfig
from mixed_traffic.experiments.cli import add_config_args, check_table, config_from_args
from mixed_traffic.experiments.runner import check_policy, run_episode
from mixed_traffic.experiments.safety_matrix import terminal_events
from mixed_traffic.provenance import check_writable, write_record_atomic
from mixed_traffic.world.demand import av_count
from mixed_traffic.world.registry import load_scenario
from mixed_traffic.world.ring import scaled_ring

MIN_STD = 1.5
"""Speed std [m/s] that counts as waves."""
WAVE_SPEEDS = (-25.0, -10.0)
"""Wave speeds [km/h] that count as stop-and-go waves travelling upstream."""
PARTS = ("ring", "road")


@dataclass(frozen=True)
class WaveCheckConfig:
    """Cells and episodes of the wave checks."""

    seeds: tuple[int, ...] = (0, 1, 2)
    """Root seeds; every cell runs once per seed."""
    parts: tuple[str, ...] = PARTS
    """Which checks to run: ring | road."""
    ring: str = "ring"
    """The bundled ring scenario scaled to each length."""
    ring_lengths: tuple[float, ...] = (200.0, 300.0)
    """Ring circumferences [m]."""
    ring_density: float = 85.0
    """Density on the rings [veh/km]."""
    ring_episode: float = 300.0
    """Simulated time per ring episode [s] (no warm-up: the std is over the whole episode)."""
    roads: tuple[str, ...] = ("wave-highway-eval", "wave-highway-eval-3lane")
    """Open wave roads (inflow scenarios), at their default density."""
    penetrations: tuple[float, ...] = (0.02, 0.1)
    """AV shares on the roads [0-1]."""
    policies: tuple[str, ...] = ("acc-lc", "follower-stopper")
    """Policies driving the AVs on the roads."""
    road_episode: float = 420.0
    """Simulated time per road episode [s]."""
    road_warmup: float = 120.0
    """Time before the roads' flow metrics count [s]: the queue behind the slow zone builds."""
    workers: int = 1
    """Parallel worker processes (one simulation each)."""
    out: Path | None = None
    """Append every episode's record here (JSON lines); default: keep none."""

    def __post_init__(self) -> None:
        if not self.seeds or min(self.seeds) < 0:
            raise ValueError(f"--seeds={list(self.seeds)}: give one or more seeds >= 0")
        if not self.parts or set(self.parts) - set(PARTS):
            raise ValueError(f"--parts={list(self.parts)}: choose from {PARTS}")
        lo, hi = RING_LENGTH_RANGE
        if not self.ring_lengths or not all(lo <= x <= hi for x in self.ring_lengths):
            raise ValueError(f"--ring-lengths={list(self.ring_lengths)}: give lengths in "
                             f"[{lo:g}, {hi:g}] m")  # fmt: skip
        if not load_scenario(self.ring).ring:
            raise ValueError(f"--ring={self.ring!r} is no ring scenario")
        for road in self.roads:
            if not load_scenario(road).inflow:
                raise ValueError(f"--roads: {road!r} is no open road fed by an inflow")
        if not self.penetrations or not all(0 < p <= 1 for p in self.penetrations):
            raise ValueError(f"--penetrations={list(self.penetrations)}: give shares in (0, 1]")
        for policy in self.policies:
            check_policy(policy)
        if not 0 <= self.road_warmup < self.road_episode:
            raise ValueError(f"--road-warmup={self.road_warmup}: must be in [0, --road-episode "
                             f"{self.road_episode}) s")  # fmt: skip
        if self.workers < 1:
            raise ValueError(f"--workers={self.workers}: must be >= 1")
        if self.out is not None:
            check_writable(self.out)


@dataclass(frozen=True)
class Cell:
    """One episode: which check it belongs to, where, its config, policy and warm-up."""

    check: str
    where: str
    config: EnvConfig
    policy: str
    warmup: float


def ring_cells(cfg: WaveCheckConfig) -> list[Cell]:
    """All human and one FollowerStopper on each ring length, every seed."""
    cells = []
    for length in cfg.ring_lengths:
        base = EnvConfig(scenario=cfg.ring, density=cfg.ring_density, ring_length=(length,),
                         episode_length=cfg.ring_episode)  # fmt: skip
        n = av_count(scaled_ring(load_scenario(cfg.ring), length), replace(base, penetration=1.0))
        where = f"{cfg.ring} {length:g} m, {cfg.ring_density:g} veh/km ({n} veh)"
        for seed in cfg.seeds:
            human = replace(base, penetration=0.0, seed=seed)
            one = replace(base, penetration=1.0 / n, seed=seed)  # one AV
            cells += [Cell("ring", where, human, "idm", 0.0),
                      Cell("ring", where, one, "follower-stopper", 0.0)]  # fmt: skip
    return cells


def road_cells(cfg: WaveCheckConfig) -> list[Cell]:
    """All human, and every policy at every penetration, on each road, every seed."""
    cells = []
    for road in cfg.roads:
        for seed in cfg.seeds:
            base = EnvConfig(scenario=road, episode_length=cfg.road_episode, seed=seed)
            human = replace(base, penetration=0.0)
            cells.append(Cell("road", road, human, "idm", cfg.road_warmup))
            for policy in cfg.policies:
                for p in cfg.penetrations:
                    mixed = replace(base, penetration=p)
                    cells.append(Cell("road", road, mixed, policy, cfg.road_warmup))
    return cells


def run_cell(cell: Cell) -> dict[str, Any]:
    """The record of one cell's episode."""
    return run_episode(cell.config, cell.policy, cell.warmup)


def run_cells(cells: list[Cell], workers: int, out: Path | None) -> list[dict[str, Any]]:
    """Records of ``cells`` in order, ``workers`` episodes at a time."""
    with ProcessPoolExecutor(max_workers=workers) as pool:
        records = []
        for cell, record in zip(cells, pool.map(run_cell, cells)):
            print(f"  {cell.where}, {cell.policy}, {100 * cell.config.penetration:g} % AVs, "
                  f"seed {cell.config.seed}: done", file=sys.stderr)  # fmt: skip
            if out is not None:
                write_record_atomic(out, record)
            records.append(record)
    return records


def _spread(values: list[float]) -> str:
    """'mean [min, max]' of finite values (n/a if none)."""
    v = np.array([x for x in values if x is not None and np.isfinite(x)], dtype=float)
    return f"{v.mean():.2f} [{v.min():.2f}, {v.max():.2f}]" if len(v) else "n/a"


def _terminal(metrics: dict[str, Any]) -> int:
    return sum(terminal_events(metrics).values())


def ring_rows(cells: list[Cell], records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """ring_waves and ring_damping per ring length."""
    rows = []
    for where in dict.fromkeys(c.where for c in cells):
        std = {p: [r["metrics"]["speed_std"] for c, r in zip(cells, records)
                   if c.where == where and c.policy == p] for p in ("idm", "follower-stopper")}  # fmt: skip
        human, fs = np.mean(std["idm"]), np.mean(std["follower-stopper"])
        rows += [
            _row("ring_waves", where, f"all-human speed std {_spread(std['idm'])} m/s",
                 min(std["idm"]) >= MIN_STD),
            _row("ring_damping", where, f"one FollowerStopper {_spread(std['follower-stopper'])} "
                 f"m/s = {fs / human:.2f} x all human", fs <= 0.5 * human),
        ]  # fmt: skip
    return rows


def road_rows(cells: list[Cell], records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """road_waves per road, road_terminal per road, policy and penetration."""
    rows = []
    for road in dict.fromkeys(c.where for c in cells):
        pairs = [(c, r) for c, r in zip(cells, records) if c.where == road]
        human = [r["metrics"] for c, r in pairs if c.policy == "idm"]
        std, wave = [m["speed_std"] for m in human], [m["wave_speed"] for m in human]
        lo, hi = WAVE_SPEEDS
        waves = all(s >= MIN_STD for s in std) and all(
            w is not None and lo <= w <= hi for w in wave
        )
        rows.append(_row("road_waves", road, f"all-human speed std {_spread(std)} m/s, wave "
                         f"speed {_spread(wave)} km/h", waves))  # fmt: skip
        for policy, p in dict.fromkeys((c.policy, c.config.penetration) for c, _ in pairs):
            if policy == "idm":
                continue
            got = [
                r["metrics"] for c, r in pairs if (c.policy, c.config.penetration) == (policy, p)
            ]
            events = sum(map(_terminal, got))
            trips = [m.get("av_trips") or 0 for m in got]
            drove = all(m.get("avg_vel_a") is not None for m in got)  # AVs on the road each seed
            rows.append(_row("road_terminal", f"{road}, {policy}, {100 * p:g} % AVs",
                             f"{events} terminal events; AV trips ended {_spread(trips)}",
                             events == 0 and drove))  # fmt: skip
    return rows


def _row(check: str, where: str, value: str, passed: bool) -> dict[str, Any]:
    return {"check": check, "where": where, "value": value, "pass": bool(passed)}


def table(rows: list[dict[str, Any]]) -> str:
    """The checks as aligned text, one per line."""
    head = {"check": "check", "where": "where", "value": "value", "pass": "pass"}
    cells = [head, *({**r, "pass": "yes" if r["pass"] else "NO"} for r in rows)]
    widths = {k: max(len(str(c[k])) for c in cells) for k in head}
    return "\n".join("  ".join(str(c[k]).ljust(widths[k]) for k in head) for c in cells)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m mixed_traffic.experiments.waves",
        description="Check that scaled rings and the open wave roads form stop-and-go waves in "
        "all-human traffic, that one FollowerStopper damps a ring, and that ACC-LC and "
        "FollowerStopper drive the roads without terminal events (issue 42).",
    )
    add_config_args(p, WaveCheckConfig)
    args = p.parse_args(argv)
    try:
        cfg = config_from_args(args, WaveCheckConfig)
    except ValueError as e:
        p.error(str(e))
    rows = []
    if "ring" in cfg.parts:
        cells = ring_cells(cfg)
        rows += ring_rows(cells, run_cells(cells, cfg.workers, cfg.out))
    if "road" in cfg.parts:
        cells = road_cells(cfg)
        rows += road_rows(cells, run_cells(cells, cfg.workers, cfg.out))
    print(check_table(rows))
    return 0 if all(r["pass"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
