"""The study, scale and throughput sections of ``python -m mixed_traffic.bench`` (issue 45): what they run
and the JSON rows they print. Timings are never asserted."""

from __future__ import annotations

import argparse
import json
from collections import Counter

from mixed_traffic.experiments import bench
from mixed_traffic.experiments.bench_study import floor_cells, study_sweep
from mixed_traffic.experiments.sweep import cells, fd_sweep


def test_the_study_floor_runs_every_study_cell_with_sumo_driving(tmp_path) -> None:
    args = argparse.Namespace(study_workers=2, study_seeds=2, study_episode=40.0)
    sweep = study_sweep(args, tmp_path)
    assert sweep.seeds == (0, 1) and sweep.episode_length == 40.0 and sweep.warmup == 20.0
    study = cells(sweep) + cells(fd_sweep(sweep))
    floor = floor_cells(sweep)
    assert {c.policy for c in floor} == {"idm"} and len(floor) == len(study) > 0
    drop = lambda c: (c.scenario, c.density, c.penetration, c.seed)  # noqa: E731
    assert Counter(map(drop, floor)) == Counter(map(drop, study))  # repeats kept: same work
    assert any(c.penetration == 1.0 for c in floor)  # AVs present, driven by SUMO


def test_the_study_limit_commands_every_av_and_keeps_them_safe() -> None:
    """The limit's cell writes a command for every AV at every step (at least 10 AVs here),
    and SUMO's safety keeps them from colliding."""
    from mixed_traffic.config import EnvConfig
    from mixed_traffic.experiments.bench_study import limit_episode

    config = EnvConfig(scenario="straight", density=120.0, penetration=0.5, episode_length=20.0)
    commands, collisions = limit_episode(config)
    assert commands > 20 / 0.1 * 10 and collisions == 0


def test_the_scale_section_prints_its_row(capsys) -> None:
    argv = ["--section", "scale", "--json", "--scale-avs", "20", "40", "--scale-steps", "3",
            "--city-grid", "3", "--city-episode", "1"]  # fmt: skip
    assert bench.main(argv) == 0
    row = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert row["section"] == "scale" and row["city_completed"] is True
    assert row["city_vehicles"] > 10 and row["city_sumo_s"] > 0
    assert abs(row["ladder"][0]["avs"] - 20) <= 4  # placement rounds per lane
    assert all(r["realtime_factor"] > 0 for r in row["ladder"])
    assert row["max_avs_realtime"] in [0] + [r["avs"] for r in row["ladder"]]


def test_the_long_road_is_split_into_short_edges() -> None:
    """SUMO's sublane model slows with the vehicles on one lane, so the ladder's road is cut
    into edges of at most 500 m by netconvert (``SPLIT_ARGS``), end to end."""
    import sumolib

    from mixed_traffic.experiments.bench_scale import long_road

    edges = sumolib.net.readNet(str(long_road(1.2, 2))).getEdges()
    lengths = [e.getLength() for e in edges]
    assert len(edges) >= 3 and max(lengths) <= 500.0 + 1e-6
    assert abs(sum(lengths) - 1200.0) < 1.0 and {e.getLaneNumber() for e in edges} == {2}


def test_the_throughput_section_prints_a_row_per_task_copies_and_mode(capsys) -> None:
    argv = ["--section", "throughput", "--json", "--throughput-tasks", "ring-v2",
            "--throughput-copies", "2", "--throughput-decisions", "20", "--throughput-steps", "5",
            "--throughput-ppo", "--throughput-rbpdqn", "20"]  # fmt: skip
    assert bench.main(argv) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    rows = [json.loads(x) for x in lines if x.startswith("{")]
    assert [(r["copies"], r["mode"]) for r in rows] == [(1, "env"), (1, "rbpdqn"), (2, "env"),
                                                       (2, "rbpdqn")]  # fmt: skip
    assert all(r["task"] == "ring-v2" and r["decisions_per_s_per_core"] > 0 for r in rows)
    assert [r["ratio_to_single"] for r in rows[:2]] == [1.0, 1.0]
    assert rows[2]["sumo_ratio"] > 0 and rows[3]["sumo_ratio"] is None
