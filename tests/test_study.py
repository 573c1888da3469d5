"""The comparison studies: raster and fusion encoders, the other learning rules, the study's
training legs (resume from weights alone), its CLI errors and its report from real episodes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from pypdf import PdfReader

from agents.bench_inference import random_obs
from agents.learners.rbpdqn import LearnerConfig, Policy, build_nets, obs_to_torch
from agents.learners.variants import PDDPG, QPAMDP, Imitation, make_learner
from agents.nets.lca import LCAConfig
from agents.nets.raster import CHANNELS, COLS_PER_LANE, ROWS, rasterize
from mixed_traffic.experiments import study
from mixed_traffic.experiments.study_methods import Budget, installed_steps, train_method

from .test_agents import _batch

ENCODERS = ("bev", "mf", "transfuser")


def _one_car_ahead(z: int = 2, m: int = 4) -> dict[str, torch.Tensor]:
    """One ego (10 m/s, centred) and one car 30 m ahead on its left lane, nothing else."""
    cfg = LCAConfig(z=z, m=m)
    obs = {k: torch.zeros(1, *s) for k, s in cfg.obs_shapes().items()}
    obs["ego"][0, :, :4] = torch.tensor([10 / 40, 0.0, 0.45, 0.36])
    car = torch.tensor([30 / 90, 0.1, 0.0, 0.45, 0.36, 0.0])
    obs["vehicles"][0, 0, :, :6] = car  # left lane, front slot
    obs["node_mask"][0, :, 0] = 1
    return obs


def test_raster_draws_the_car_ahead_on_its_lane_and_the_ego_at_the_centre() -> None:
    ras = rasterize(_one_car_ahead(), 90.0, 60.0)
    assert ras.shape == (1, 2 * CHANNELS, ROWS, 3 * COLS_PER_LANE)
    occ = ras[0, CHANNELS]  # the newest frame's vehicle channel
    rows, cols = torch.nonzero(occ, as_tuple=True)
    step = 180.0 / ROWS
    centres = -90.0 + step * (rows.float() + 0.5)
    assert torch.all((centres - 30.0).abs() <= 2.25 + step)  # 4.5 m car, half a cell grown
    assert set(cols.tolist()) <= set(range(COLS_PER_LANE))  # the left lane's columns
    ego = ras[0, 2 * CHANNELS - 1]
    assert ego[ROWS // 2 - 1 : ROWS // 2 + 1, COLS_PER_LANE + 1].min() == pytest.approx(0.25)
    assert ego[:, :COLS_PER_LANE].abs().sum() == 0  # not on the left lane
    mapless = rasterize(_one_car_ahead(), 90.0, 60.0, with_map=False)
    assert mapless[0, CHANNELS + 2 : CHANNELS + 4].abs().sum() == 0  # DRL-MF: no map channels


@pytest.mark.parametrize("encoder", ENCODERS)
def test_encoders_learn_through_actor_and_critic(encoder: str) -> None:
    cfg = LCAConfig(z=3, m=5, encoder=encoder)
    learner = make_learner(cfg, LearnerConfig(), seed=0)
    batch = _batch(16, cfg)
    before = [p.clone() for p in learner.actor.lca.parameters()]
    out = learner.update(batch)
    assert all(np.isfinite(v) for v in out.values())
    moved = [not torch.equal(a, b) for a, b in zip(before, learner.actor.lca.parameters())]
    assert any(moved)
    policy = Policy(learner.actor.eval(), learner.critic.eval())
    dec, params = policy.act(random_obs(5, cfg, np.random.default_rng(1)), explore=False)
    assert dec.shape == (5,) and params.shape == (5, 3, 2)


def test_p_ddpg_scores_decide_and_its_critic_values_the_whole_action() -> None:
    cfg = LCAConfig(z=3, m=5)
    learner = make_learner(cfg, LearnerConfig(algorithm="p-ddpg"), seed=0)
    assert isinstance(learner, PDDPG)
    assert learner.actor(obs_to_torch(random_obs(4, cfg, np.random.default_rng(0)))).shape == (
        4, 3, 3,
    )  # fmt: skip
    learner.update(_batch(16, cfg))
    obs = random_obs(6, cfg, np.random.default_rng(2))
    obs["action_mask"][:] = [1, 0, 0]  # only a left change allowed
    dec, params = Policy(learner.actor, learner.critic).act(obs, explore=False)
    assert (dec == 0).all() and params.shape == (6, 3, 2)


def test_q_pamdp_alternates_critic_and_actor_phases() -> None:
    cfg = LCAConfig(z=3, m=5)
    learner = make_learner(cfg, LearnerConfig(algorithm="q-pamdp", phase_updates=2), seed=0)
    assert isinstance(learner, QPAMDP)
    batch = _batch(16, cfg)
    for step in range(4):
        actor = [p.clone() for p in learner.actor.parameters()]
        critic = [p.clone() for p in learner.critic.parameters()]
        out = learner.update(batch)
        a_moved = any(not torch.equal(a, b) for a, b in zip(actor, learner.actor.parameters()))
        c_moved = any(not torch.equal(a, b) for a, b in zip(critic, learner.critic.parameters()))
        critic_phase = step < 2
        assert (c_moved, a_moved) == (critic_phase, not critic_phase), step
        assert np.isnan(out["actor_loss"] if critic_phase else out["critic_loss"])


def test_imitation_fits_the_labels_without_td() -> None:
    cfg = LCAConfig(z=3, m=5)
    learner = make_learner(cfg, LearnerConfig(algorithm="imitation", lr=3e-3), seed=0)
    assert isinstance(learner, Imitation)
    batch = _batch(32, cfg)
    batch["labelled"] = torch.ones(32)
    batch["label_decision"] = torch.ones(32, dtype=torch.int64)
    batch["label_params"] = torch.full((32, 3, 2), 0.3)
    first = learner.actor_loss(batch).item()
    for _ in range(150):
        learner.update(batch)
    assert learner.actor_loss(batch).item() < 0.2 * first
    q = learner.critic(batch["obs"], batch["label_params"])
    assert (q.argmax(1) == 1).float().mean() > 0.9  # the labelled decision ranks first


def test_head_keeps_acc_lc_steering() -> None:
    from agents.driver import Driver

    cfg = LearnerConfig(residual=True, steer_control=False)
    actor, critic = build_nets(LCAConfig(z=3, m=5), cfg)
    driver = Driver(Policy(actor, critic), cfg, 0.1)
    u = np.ones((2, 3, 2), np.float32)
    t_par = np.zeros((2, 3, 2), np.float32)
    out = driver._execute(u, t_par, np.ones((2, 3)))
    assert (out[..., 0] == 0).all() and (out[..., 1] > 0).all()


@pytest.fixture(scope="module")
def head(tmp_path_factory) -> Path:
    """HEAD trained on 1,500 transitions, installed in a checkpoints folder."""
    root = tmp_path_factory.mktemp("study")
    train_method("head", Budget(env_steps=1500, workers=1), root / "ck", root / "runs")
    return root


def test_training_continues_from_the_installed_weights_alone(head: Path) -> None:
    """A fresh machine has only the installed checkpoint: the next leg starts from it."""
    ck = head / "ck"
    first = installed_steps("head", ck)
    assert 1500 <= first < 3000
    rows = len((ck / "head.csv").read_text().splitlines())
    runs = head / "runs2"  # no run folder
    train_method("head", Budget(env_steps=first + 1000, workers=1), ck, runs)
    info = json.loads((ck / "head.json").read_text())
    assert info["env_steps"] >= first + 1000 and info["earlier_legs"][0]["env_steps"] == first
    assert "--init" in info["study_command"]
    steps = [int(r.split(",")[0]) for r in (ck / "head.csv").read_text().splitlines()[1:]]
    assert len(steps) > rows - 1 and steps == sorted(steps)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--seeds", "0"], "at least 2 distinct seeds"),
        (["--env-steps", "0"], "budget must be > 0"),
        (["--scenario", "nope"], "unknown scenario"),
        (["--workers", "0"], "--workers"),
    ],
)
def test_bad_study_options_exit_before_any_work(argv, message, capsys) -> None:
    with pytest.raises(SystemExit) as e:
        study.parse_args(argv)
    assert e.value.code == 2 and message in capsys.readouterr().err


def test_study_command_reports_and_resumes_without_rerunning(head: Path) -> None:
    """A study run writes the paper-style report; a second run trains and runs nothing."""
    res, ck = head / "res", head / "ck"
    argv = ["--baselines", "--policies", "acc-lc", "head", "--reference", "acc-lc",
            "--env-steps", "1500", "--checkpoints", str(ck), "--runs", str(head / "runs"),
            "--seeds", "0", "1", "--episode-length", "40", "--warmup", "10", "--out", str(res),
            "--pdf", str(head / "t.pdf")]  # fmt: skip
    assert study.main(argv) == 0
    lines = (res / "records.jsonl").read_text().splitlines()
    records = [json.loads(line) for line in lines]
    assert len(records) == 4 and {r["status"] for r in records} == {"ok"}
    assert {r["checkpoint"] for r in records if r["cell"]["policy"] == "head"} == {
        str((ck / "head.pt").resolve())
    }
    text = "\n".join(p.extract_text() for p in PdfReader(head / "t.pdf").pages)
    for part in ("Paired differences to acc-lc", "AvgR", "MinTTC-A", "Training lineage",
                 "Learning curves", "same pipeline"):  # fmt: skip
        assert part in text, part
    weights = (ck / "head.pt").stat().st_mtime_ns
    assert study.main(argv) == 0
    assert (res / "records.jsonl").read_text().splitlines() == lines
    assert (ck / "head.pt").stat().st_mtime_ns == weights
    # other weights at the same path (a retrained method) are other cells: head runs again
    data = torch.load(ck / "head.pt", weights_only=True)
    data["meta"]["note"] = "retrained"
    torch.save(data, ck / "head.pt")
    assert study.main(argv) == 0
    again = [json.loads(line) for line in (res / "records.jsonl").read_text().splitlines()]
    assert sorted(r["cell"]["policy"] for r in again[4:]) == ["head", "head"]


def test_every_shipped_study_policy_drives_straight_eval() -> None:
    """Each study policy loads its own committed checkpoint (none is an alias of another) and
    acts on a real straight-eval observation batch within the action space."""
    from agents.policies import STUDY_CHECKPOINTS, make_policy, stack_obs
    from mixed_traffic import mixed_traffic_v0
    from mixed_traffic.provenance import file_digest
    from mixed_traffic.schema import STUDY_POLICIES

    env = mixed_traffic_v0.parallel_env(scenario="straight-eval", penetration=0.2, seed=0)
    obs, _ = env.reset(seed=0)
    agents = list(env.agents)
    batch = stack_obs(obs, agents)
    env.close()
    digests = set()
    for name in STUDY_POLICIES:
        policy = make_policy(name, z=batch["ego"].shape[1], m=batch["lanes"].shape[-1] // 4)
        assert policy.name == name and policy.checkpoint == STUDY_CHECKPOINTS / f"{name}.pt"
        digests.add(file_digest(policy.checkpoint))
        decision, params = policy.act(batch, agents)
        assert decision.shape == (len(agents),) and np.abs(params).max() <= 1.0
        assert batch["action_mask"][np.arange(len(agents)), decision].all(), name
    assert len(digests) == len(STUDY_POLICIES)


def test_a_policy_the_safety_module_drives_is_called_out() -> None:
    import pandas as pd

    from analysis.study_report import fallback_notes

    ok = pd.DataFrame({"policy": ["drl-mf", "drl-mf", "head"], "sm_share": [100.0, 96.0, 1.0]})
    notes = fallback_notes(ok)
    assert len(notes) == 1 and notes[0].startswith("drl-mf: the safety module changed 98 %")
