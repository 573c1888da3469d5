"""Fleet-return search: the ES math (pure) and one resumable run on real SUMO."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.checkpoint import load_checkpoint, save_checkpoint
from agents.learners.rbpdqn import RBPDQN, LearnerConfig
from agents.nets.lca import LCAConfig
from agents.training.fleet_search import (
    Adam,
    SearchConfig,
    accel_rows,
    episode_score,
    es_gradient,
    get_theta,
    set_theta,
    unsafe_events,
)
from mixed_traffic.config import EnvConfig
from mixed_traffic.experiments.fleet import FleetConfig, FleetSearch, main, scenario_pool


def _learner() -> RBPDQN:
    sensors = EnvConfig().sensors
    torch.manual_seed(0)
    return RBPDQN(LCAConfig(z=sensors.history, m=sensors.waypoints), LearnerConfig(residual=True))


def test_theta_is_the_accel_rows_of_the_last_layer() -> None:
    actor = _learner().actor
    layer = actor.head[-1]
    assert accel_rows(actor) == [1, 3, 5]
    before = layer.weight.detach().clone(), layer.bias.detach().clone()
    theta = get_theta(actor)
    assert theta.shape == (3 * (layer.in_features + 1),)
    new = np.arange(len(theta), dtype=float) / 100
    set_theta(actor, new)
    np.testing.assert_allclose(get_theta(actor), new, atol=1e-6)
    steer = [0, 2, 4]
    assert torch.equal(layer.weight[steer], before[0][steer])  # steering rows untouched
    assert torch.equal(layer.bias[steer], before[1][steer])
    with pytest.raises(ValueError, match="theta must be"):
        set_theta(actor, new[:-1])
    with pytest.raises(ValueError, match="theta must be"):
        set_theta(actor, np.full_like(new, np.nan))
    with pytest.raises(ValueError, match="target='steer'"):
        get_theta(actor, "steer")


def test_antithetic_gradient_points_up_a_linear_score() -> None:
    rng = np.random.default_rng(0)
    w = rng.standard_normal(20)
    eps = rng.standard_normal((400, 20))
    sigma = 0.1
    d = (eps * sigma) @ w * 2  # score(θ+σε) − score(θ−σε) of score = w·θ
    g = es_gradient(eps, d, sigma, clip=3.0)
    cos = g @ w / np.linalg.norm(g) / np.linalg.norm(w)
    assert cos > 0.9


def test_failed_pairs_are_left_out_of_the_gradient() -> None:
    eps = np.eye(3)
    d = np.array([1.0, math.nan, -math.inf])
    g = es_gradient(eps, d, sigma=1.0, clip=3.0)
    assert g[0] > 0 and g[1] == 0 and g[2] == 0
    assert not es_gradient(eps, np.full(3, math.nan), 1.0, 3.0).any()


def test_adam_ascends_and_restores_its_state() -> None:
    adam = Adam(2, lr=0.1)
    theta = adam.step(np.zeros(2), np.array([1.0, -2.0]))
    np.testing.assert_allclose(theta, [0.1, -0.1], atol=1e-6)
    again = Adam(2, 0.1, json.loads(json.dumps(adam.state())))
    np.testing.assert_allclose(again.step(theta, np.ones(2)), adam.step(theta, np.ones(2)))
    with pytest.raises(ValueError, match="moments"):
        Adam(3, 0.1, adam.state())


def test_episode_score_is_log_speed_minus_unsafe_events() -> None:
    ok = {"mean_speed": math.e, "collisions": 0, "terminal_collision": 0}
    assert episode_score(ok, 1.0) == pytest.approx(1.0)
    # a collision counts once (terminal_collision is the same event), other terminals add
    bad = {**ok, "collisions": 1, "terminal_collision": 1, "terminal_off_road": 2}
    assert episode_score(bad, 0.5) == pytest.approx(1.0 - 0.5 * 3)
    assert episode_score({"mean_speed": None}, 1.0) == -math.inf
    waves = {"mean_speed": math.e, "speed_std": math.e / 2, "collisions": 0}
    assert episode_score(waves, 1.0, spread_weight=0.4) == pytest.approx(1.0 - 0.4 * 0.5)
    assert unsafe_events(bad) == 3 and unsafe_events(ok) == 0


@pytest.mark.parametrize(
    ("field", "value"), [("sigma", 0.0), ("lr", math.nan), ("pairs", 0), ("unsafe_penalty", -1)]
)
def test_search_config_names_a_bad_field(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field):
        SearchConfig(**{field: value})


def test_fleet_config_refuses_bad_input(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="budget"):
        FleetConfig(minutes=0)
    with pytest.raises(ValueError, match="penetrations"):
        FleetConfig(penetrations=(0.0,))
    with pytest.raises(ValueError, match="file not found"):
        FleetConfig(init=tmp_path / "none.pt")
    with pytest.raises(ValueError, match="held-out"):
        scenario_pool(("straight-eval",))
    with pytest.raises(ValueError, match="--init"):
        FleetSearch(FleetConfig(out=tmp_path / "empty"))
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path / "x"), "--minutes", "0"])
    with pytest.raises(ValueError, match="target"):
        FleetConfig(target="steer")


def test_a_gate_search_adds_a_closed_gate_and_moves_only_it(tmp_path: Path) -> None:
    """--target gate on a checkpoint without a gate: θ is the gate (d + 1 numbers, all 0, so
    every candidate starts from the checkpoint's own policy) and a candidate changes the gate
    only."""
    learner = _learner()
    init = save_checkpoint(tmp_path / "init.pt", learner)
    search = FleetSearch(FleetConfig(init=init, out=tmp_path / "run", iterations=1, target="gate"))
    d = search.learner.actor.gate.in_features
    assert search.theta.shape == (d + 1,) and not search.theta.any()
    path = search._candidate("c", np.ones(d + 1))
    cand, _ = load_checkpoint(path)
    assert cand.cfg.hold_gate
    np.testing.assert_allclose(get_theta(cand.actor, "gate"), np.ones(d + 1))
    np.testing.assert_array_equal(get_theta(cand.actor), get_theta(learner.actor))


def test_a_run_moves_theta_commits_and_resumes(tmp_path: Path) -> None:
    init = save_checkpoint(tmp_path / "init.pt", _learner())
    out = tmp_path / "run"
    short = dict(out=out, workers=1, scenarios=("ring-260m",), densities=(0.0,),
                 penetrations=(0.1,), episode_length=12.0, warmup=4.0,
                 search=SearchConfig(pairs=1), progress=False)  # fmt: skip
    first = FleetSearch(FleetConfig(init=init, iterations=1, **short))
    theta0 = first.theta.copy()
    first.run()
    state = json.loads((out / "state.json").read_text())
    assert state["iteration"] == 1 and state["episodes"] == 4
    assert not np.allclose(state["theta"], theta0)  # Adam's first step moves every entry
    learner, meta = load_checkpoint(out / "auto.pt")
    np.testing.assert_allclose(get_theta(learner.actor), state["theta"], atol=1e-6)
    assert meta["fleet_search"]["iteration"] == 1
    # a second invocation resumes from OUT (no --init needed) and appends its row
    FleetSearch(FleetConfig(iterations=2, **short)).run()
    with (out / "curves.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [int(r["iteration"]) for r in rows] == [1, 2]
    thetas = [json.loads(line) for line in (out / "thetas.jsonl").read_text().splitlines()]
    assert [t["iteration"] for t in thetas] == [1, 2]
    np.testing.assert_allclose(thetas[0]["theta"], state["theta"])
    assert all(math.isfinite(float(r["gain"])) for r in rows)


def test_train_command_runs_the_fleet_stage_and_resumes_into_it(tmp_path: Path) -> None:
    from mixed_traffic.experiments.train import main as train

    out = tmp_path / "run"
    argv = ["--workers", "1", "--scenarios", "straight-3lane", "--densities", "120",
            "--penetrations", "0.5", "--episode-length", "4", "--env-steps", "300",
            "--demo-steps", "300", "--learning-starts", "300", "--no-progress",
            "--replay-capacity", "5000", "--out", str(out), "--fleet-iterations", "1"]  # fmt: skip
    assert train(argv) == 0
    info = json.loads((out / "auto.json").read_text())
    assert info["fleet_search"]["iteration"] == 1
    fleet_theta = json.loads((out / "fleet" / "state.json").read_text())["theta"]
    np.testing.assert_allclose(get_theta(load_checkpoint(out / "auto.pt")[0].actor),
                               fleet_theta, atol=1e-6)  # fmt: skip
    # --resume with a larger budget continues the fleet stage, not the RBP-DQN one
    env_steps = info["env_steps"]
    assert train([*argv[:-1], "2", "--resume"]) == 0
    info = json.loads((out / "auto.json").read_text())
    assert info["fleet_search"]["iteration"] == 2 and info["env_steps"] == env_steps
