"""Multi-worker training (agents.training.trainer, agents.collection.workers, mixed_traffic.experiments.train) on real SUMO.

Tiny budgets: a few thousand transitions of 2 s episodes on one straight scenario.
"""

from __future__ import annotations

import csv
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.checkpoint import load_checkpoint
from agents.collection.workers import RolloutWorker
from agents.rules.acc_lc import AccLcPolicy
from agents.rules.obs_batch import stack_obs, with_extra
from agents.training.config import TrainConfig
from agents.training.trainer import Trainer
from mixed_traffic.config import EnvConfig, SensorConfig
from mixed_traffic.env import parallel_env
from mixed_traffic.experiments.runner import run_episode
from mixed_traffic.experiments.train import main
from mixed_traffic.world.registry import load_scenario

DEMO = "acc-lc"

TINY = dict(
    scenarios=("straight-3lane",), densities=(120.0,), penetrations=(0.5,),
    episode_length=2.0, demo_steps=400, demo_policy=DEMO, learning_starts=400,
    update_ratio=0.02, local_buffer=256, log_every=1000, progress=False, sync_every=5,
    replay_capacity=20_000, copies=1,
)  # fmt: skip


def _cfg(tmp: Path, **kw) -> TrainConfig:
    return TrainConfig(**{**TINY, "out": str(tmp), **kw})


def _curves(out: Path) -> list[dict[str, str]]:
    with (out / "curves.csv").open() as f:
        return list(csv.DictReader(f))


def test_two_worker_smoke_cli(tmp_path: Path) -> None:
    out = tmp_path / "run"
    argv = ["--workers", "2", "--scenarios", "straight-3lane", "--densities", "120",
            "--penetrations", "0.5", "--episode-length", "2", "--env-steps", "3000",
            "--demo-steps", "400", "--demo-policy", DEMO, "--learning-starts", "400",
            "--update-ratio", "0.02", "--log-every", "1000", "--no-progress",
            "--replay-capacity", "20000", "--out", str(out)]  # fmt: skip
    assert main(argv) == 0
    for name in ("COMMIT", "checkpoint.pt", "curves.csv", "auto.pt", "auto.json"):
        assert (out / name).is_file(), name
    (commit,) = (out / "commits").iterdir()  # older commits are removed
    assert sorted(p.name for p in commit.iterdir()) == ["checkpoint.pt", "replay.pt", "state.json"]
    info = json.loads((out / "auto.json").read_text())
    assert info["env_steps"] >= 3000 and info["updates"] > 0
    assert info["command"].startswith("python -m mixed_traffic.train --workers 2")
    assert info["train_config"]["workers"] == 2 and info["git_revision"]
    rows = _curves(out)
    assert len(rows) >= 2 and int(rows[-1]["env_steps"]) == info["env_steps"]
    from agents.policies import AutoPolicy

    assert AutoPolicy(out / "auto.pt").checkpoint.is_file()


def test_a_run_with_memory_and_v2x_reads_the_opt_in_keys(tmp_path: Path) -> None:
    """The env's ``memory`` and ``downstream`` keys reach the replay and the fusion layer, and
    the trained policy refuses an env without them."""
    from agents.policies import make_policy

    info = Trainer(_cfg(tmp_path, workers=1, env_steps=800, memory=True, v2x=True)).run()
    assert info["updates"] > 0
    learner, _ = load_checkpoint(tmp_path / "auto.pt")
    assert learner.lca_cfg.extra == 12 + 3 * 2
    # the runner switches on the keys the checkpoint was trained with
    plain = EnvConfig(scenario="straight-3lane", density=60.0, penetration=0.2, episode_length=2.0)
    record = run_episode(plain, "auto", 0.0, checkpoint=tmp_path / "auto.pt")
    assert record["status"] == "ok"
    assert record["config"]["v2x"] and record["config"]["sensors"]["memory"]
    for memory in (True, False):
        policy = make_policy("auto", checkpoint=tmp_path / "auto.pt")
        env = parallel_env(config=EnvConfig(scenario="straight-3lane", density=60.0,
                                            penetration=0.2, episode_length=2.0, v2x=True,
                                            sensors=SensorConfig(memory=memory)))  # fmt: skip
        try:
            obs, _ = env.reset(seed=0)
            batch = stack_obs(obs, env.agents)
            if memory:
                decision, _ = policy.act(batch, env.agents)
                assert decision.shape == (len(env.agents),)
            else:
                with pytest.raises(ValueError, match="reads 18 opt-in observation features"):
                    policy.act(batch, env.agents)
        finally:
            env.close()


@pytest.mark.parametrize(("name", "unread"), [("auto", ("memory", "downstream")),
                                              ("auto-ring", ("downstream",))])  # fmt: skip
def test_a_policy_ignores_opt_in_keys_it_was_not_trained_on(name: str, unread: tuple) -> None:
    """The shipped AUTO reads no opt-in key and ``auto-ring`` reads ``memory`` only; where the
    env gives more (a benchmark task with memory and the V2X feed) each drives as it does
    without the keys it never saw."""
    from agents.policies import make_policy

    env = parallel_env(config=EnvConfig(scenario="straight-3lane", density=60.0, penetration=0.2,
                                        episode_length=2.0, v2x=True,
                                        sensors=SensorConfig(memory=True)))  # fmt: skip
    try:
        obs, _ = env.reset(seed=0)
        batch = stack_obs(obs, env.agents)
        assert batch["extra"].shape[1] == 18
        plain = with_extra({k: v for k, v in batch.items() if k not in (*unread, "extra")})
        outs = [make_policy(name).act(b, env.agents) for b in (batch, plain)]  # fresh state
    finally:
        env.close()
    np.testing.assert_array_equal(outs[0][0], outs[1][0])
    np.testing.assert_array_equal(outs[0][1], outs[1][1])


def test_resume_continues_counters(tmp_path: Path) -> None:
    first = Trainer(_cfg(tmp_path, workers=1, env_steps=1500, checkpoint_every=1e-9)).run()
    snaps = sorted((tmp_path / "snapshots").glob("*.pt"))  # one per periodic checkpoint
    assert len(snaps) >= 2
    for snap in snaps:
        assert load_checkpoint(snap)[1]["env_steps"] == int(snap.stem) <= first["env_steps"]
    tr = Trainer(_cfg(tmp_path, workers=1, env_steps=3000), resume=True)
    assert tr.c["env_steps"] == first["env_steps"] and tr.c["run"] == 1
    assert len(tr.replay) == first["env_steps"]
    second = tr.run()
    assert second["env_steps"] >= 3000 and second["updates"] > first["updates"]
    assert len(second["commands"]) == 2  # provenance keeps every invocation
    steps = [int(r["env_steps"]) for r in _curves(tmp_path)]
    assert steps == sorted(steps) and len(set(steps)) == len(steps)
    with pytest.raises(FileExistsError):
        Trainer(_cfg(tmp_path, workers=1, env_steps=3000))


def test_resume_before_the_first_commit_starts_afresh(tmp_path: Path) -> None:
    tmp_path.mkdir(exist_ok=True)
    (tmp_path / "curves.csv").write_text("env_steps,wall_time\n250,1.0\n")  # a killed run's rows
    (tmp_path / ".checkpoint.pt.x1.tmp").write_bytes(b"torn")
    logs: list[str] = []
    tr = Trainer(_cfg(tmp_path, workers=1, env_steps=10), resume=True, log=logs.append)
    assert tr.c["env_steps"] == 0 and tr.c["run"] == 0 and "starting afresh" in logs[0]
    assert _curves(tmp_path) == [] and not list(tmp_path.glob("*.tmp"))


def test_provenance_names_the_revision_the_run_started_at(tmp_path: Path, monkeypatch) -> None:
    from mixed_traffic import provenance

    tr = Trainer(_cfg(tmp_path, workers=1, env_steps=300, demo_steps=300))
    started = tr.c["revisions"][-1]
    monkeypatch.setattr(provenance, "git_revision", lambda: "committed-while-training")
    info = tr.run()
    assert info["git_revision"] == started != "committed-while-training"
    assert load_checkpoint(tmp_path / "checkpoint.pt")[1]["git_revisions"] == [started]


def test_init_fine_tunes_from_a_checkpoint(tmp_path: Path) -> None:
    first = Trainer(_cfg(tmp_path / "a", workers=1, env_steps=1000)).run()
    src = tmp_path / "a" / "auto.pt"
    # the second stage adds twin critics and 3-step returns: the one-critic weights fill the
    # first critic, the twin keeps its own initialisation
    stage = dict(workers=1, demo_steps=0, twin=True, n_step=3)
    tr = Trainer(_cfg(tmp_path / "b", env_steps=800, init=str(src), **stage))
    source, _ = load_checkpoint(src)
    for pa, pb in zip(tr.learner.actor.parameters(), source.actor.parameters(), strict=True):
        assert torch.equal(pa, pb)
    assert tr.learner.critic2 is not None
    assert tr.c["env_steps"] == 0 and len(tr.replay) == 0 and tr.learner.steps == 0
    info = tr.run()
    assert info["init"]["env_steps"] == first["env_steps"] and info["init"]["path"] == str(src)
    assert info["updates"] > 0 and info["env_steps"] >= 800
    assert load_checkpoint(tmp_path / "b" / "auto.pt")[0].cfg.twin
    resumed = Trainer(_cfg(tmp_path / "b", env_steps=900, **stage), resume=True)
    assert resumed.c["init"]["path"] == str(src)  # provenance survives a resume
    src.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match=r"auto\.pt.*corrupt"):
        Trainer(_cfg(tmp_path / "c", workers=1, env_steps=10, init=str(src)))


def test_learning_rate_decays_over_the_env_steps_budget(tmp_path: Path) -> None:
    tr = Trainer(_cfg(tmp_path, workers=1, env_steps=1000, lr=1e-3, lr_final=1e-4))
    expect = {0: 1e-3, 500: 5.5e-4, 1000: 1e-4, 5000: 1e-4}  # cosine: halfway is the mean
    for steps, lr in expect.items():
        tr.c["env_steps"] = steps
        assert tr.lr_now() == pytest.approx(lr)
    tr.c["env_steps"] = 0
    info = tr.run()
    assert info["updates"] > 0
    for opt in (tr.learner.actor_opt, tr.learner.critic_opt):
        assert opt.param_groups[0]["lr"] < 2e-4  # the last updates ran near lr_final
    assert Trainer(_cfg(tmp_path / "c", workers=1, env_steps=10)).lr_now() == 1e-3


def test_one_worker_is_deterministic(tmp_path: Path) -> None:
    runs = []
    for name in ("a", "b"):
        tr = Trainer(_cfg(tmp_path / name, workers=1, env_steps=2000, seed=3))
        tr.run()
        runs.append(tr)
    a, b = ([{k: v for k, v in r.items() if k != "wall_time"} for r in _curves(t.out)]
            for t in runs)  # fmt: skip
    assert a == b and len(a) >= 2
    assert runs[0].c["updates"] == runs[1].c["updates"] > 0
    for pa, pb in zip(runs[0].learner.actor.parameters(), runs[1].learner.actor.parameters(),
                      strict=True):  # fmt: skip
        assert torch.equal(pa, pb)


def test_policy_transitions_carry_the_demonstrators_labels(tmp_path: Path) -> None:
    """The paper's form with expert relabelling: ACC-LC's action labels every transition."""
    tr = Trainer(_cfg(tmp_path, workers=1, env_steps=1, demo_steps=0, residual=False,
                      decision_interval=0.1))  # fmt: skip
    worker = RolloutWorker(tr.worker_specs()[0])
    worker.set_weights(tr.weights())  # an untrained policy drives
    try:
        chunk = worker.collect(200)
    finally:
        worker.close()
    assert chunk["demo"] == 0 and chunk["labelled"].min() == 1.0
    dec, par = AccLcPolicy().act(chunk["obs"])
    np.testing.assert_array_equal(chunk["label_decision"], dec)
    np.testing.assert_allclose(chunk["label_params"], par, atol=1e-6)
    # the labels are the demonstrator's, not copies of what the policy did
    assert np.abs(chunk["label_params"] - chunk["params"]).max() > 0.1


def _collect(out: Path, n: int, **kw) -> dict:
    """One worker's first chunk of ``n`` transitions of an untrained residual policy (6 s
    episodes, no demonstrations)."""
    tr = Trainer(_cfg(out, workers=1, env_steps=1, demo_steps=0, episode_length=6.0, **kw))
    worker = RolloutWorker(tr.worker_specs()[0])
    worker.set_weights(tr.weights())
    try:
        return worker.collect(n)
    finally:
        worker.close()


def test_residual_transitions_span_the_decision_interval(tmp_path: Path) -> None:
    """The residual form: one transition per 0.5 s decision (discount γ = 0.95 over a whole
    interval, more where a trip ended sooner), labels u = 0 and ACC-LC's decision, and an
    untrained network drives as ACC-LC plus the exploration noise on u."""
    chunk = _collect(tmp_path / "n1", 200, n_step=1)
    n = len(chunk["decision"])
    assert chunk["labelled"].max() == 0.0 and not chunk["label_params"].any()
    np.testing.assert_array_equal(chunk["label_decision"], AccLcPolicy().act(chunk["obs"])[0])
    full = np.isclose(chunk["discount"], 0.95, atol=1e-5)
    assert full.mean() > 0.8 and (chunk["discount"][~full] > 0.95).all()
    assert chunk["sim_steps"] * 0.5 > n / 5 * 0.1  # far fewer transitions than agent-steps
    assert 0 < np.abs(chunk["params"]).max() <= 1.0  # u: exploration noise around 0
    # 3-step returns: three whole intervals discount 0.95^3, the ends of trips less
    chunk = _collect(tmp_path / "n3", 200, n_step=3)
    full = np.isclose(chunk["discount"], 0.95**3, atol=1e-5)
    assert full.mean() > 0.6 and (chunk["discount"][~full] > 0.95**3).all()


def test_wave_episodes_take_their_share_with_the_fleet_reward(tmp_path: Path) -> None:
    """With ``wave_share`` a worker starts a wave episode (a drawn ring with one AV, or the
    wave road at 5 % AVs, 300 s after a random warm-up that records nothing) once its wave
    agent-steps fall below the share; the training reward carries the fleet terms."""
    tr = Trainer(_cfg(tmp_path, workers=1, env_steps=1, demo_steps=0, wave_share=0.5,
                      fleet_weights=(1.0, 0.5, 0.0)))  # fmt: skip
    worker = RolloutWorker(tr.worker_specs()[0])
    worker.set_weights(tr.weights())
    try:
        worker.collect(20)  # the first episode: straight-3lane, 2 s
        assert not worker.wave and worker.env_cfg.scenario == "straight-3lane"
        while not worker.wave:
            worker.collect(20)
        cfg, warmup = worker.env_cfg, worker.warmup
        assert 0 < warmup <= 120.0 and cfg.episode_length == pytest.approx(300.0 + warmup)
        assert cfg.scenario in ("ring", "wave-highway")
        assert cfg.penetration == (1 / 22 if cfg.scenario == "ring" else 0.05)
        assert cfg.reward.w_local_speed == 1.0 and cfg.reward.w_follower_comfort == 0.5
        # collect() returns once it has its transitions: none came from the warm-up
        assert worker.env.sim_time >= warmup > 10.0  # (this seed's draw: 29 s)
        worker.collect(50)
        assert worker._steps["wave"] > 0 and worker._steps["other"] > 0
    finally:
        worker.close()


def test_a_worker_collects_from_batched_worlds(tmp_path: Path) -> None:
    """With ``copies`` a worker's episode runs that many copies of its scenario in one
    simulation, and its transitions and episode stats come from all of them; a scenario that
    cannot be copied (urban) runs one."""
    tr = Trainer(_cfg(tmp_path / "straight", workers=1, env_steps=1, demo_steps=0, copies=3,
                      episode_length=4.0))  # fmt: skip
    worker = RolloutWorker(tr.worker_specs()[0])
    worker.set_weights(tr.weights())
    try:
        worker.collect(60)
        assert worker.env_cfg.copies == 3
        assert set(worker.env.agent_copy.tolist()) == {0, 1, 2}
        while worker.env is not None:  # to the episode's end
            worker._step()
        (ep,) = worker._episodes
        assert ep["copies"] == 3 and ep["av_trips"] >= 3
    finally:
        worker.close()
    tr = Trainer(_cfg(tmp_path / "urban", workers=1, env_steps=1, demo_steps=0, copies=3,
                      scenarios=("urban",), densities=(0.0,)))  # fmt: skip
    worker = RolloutWorker(tr.worker_specs()[0])
    worker.set_weights(tr.weights())
    try:
        worker.collect(5)
        assert worker.env_cfg.copies == 1
    finally:
        worker.close()


def test_a_worker_corrects_the_tuned_rule_of_each_episodes_family(tmp_path: Path) -> None:
    """With ``--demo-policy acc-lc-tuned`` the worker's driver corrects the rule that
    evaluation builds for the episode's family, and caps at its speed factor."""
    from agents.policies import make_policy
    from agents.rules.tuned import cap_factor

    tr = Trainer(_cfg(tmp_path, workers=1, env_steps=1, demo_steps=0,
                      demo_policy="acc-lc-tuned", scenarios=("merge-ramp",)))  # fmt: skip
    worker = RolloutWorker(tr.worker_specs()[0])
    worker.set_weights(tr.weights())
    try:
        worker.collect(20)
        family = worker.env.scenario.family
        assert worker.driver.teacher.c == make_policy("acc-lc-tuned", family=family).c
        assert worker.driver.teacher.c != make_policy("acc-lc").c
        assert worker.driver.cap_factor == cap_factor(family)
    finally:
        worker.close()


def test_each_scenario_samples_the_densities_it_can_hold() -> None:
    ring = load_scenario("ring-220m")
    assert ring.feasible_densities((60.0, 180.0, 0.0)) == (60.0, None)
    assert load_scenario("straight-3lane").feasible_densities((60.0, 180.0)) == (60.0, 180.0)
    with pytest.raises(ValueError, match="ring-220m"):
        ring.feasible_densities((180.0,))


def test_worker_crash_is_recovered(tmp_path: Path) -> None:
    tr = Trainer(_cfg(tmp_path, workers=2, env_steps=3500, crash_after_chunks=2))
    info = tr.run()
    assert info["worker_restarts"] >= 1 and info["env_steps"] >= 3500
    # every chunk worker 0 flushed before the SIGKILL arrived, in order, and nothing else lost
    assert tr.received[(0, 0, 0)] == 2
    assert tr.collector.specs[0].incarnation == 1  # respawned with fresh seeds and env
    assert tr.gaps == 0
    assert len(tr.replay) == tr.c["env_steps"]


@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="ray is not installed")
def test_ray_backend_smoke_with_crash(tmp_path: Path) -> None:
    tr = Trainer(_cfg(tmp_path, workers=2, backend="ray", env_steps=2500, crash_after_chunks=2))
    info = tr.run()
    assert info["env_steps"] >= 2500 and info["worker_restarts"] >= 1
    assert tr.received[(0, 0, 0)] == 2 and tr.gaps == 0
    assert len(tr.replay) == tr.c["env_steps"]
    assert (tmp_path / "auto.pt").is_file()


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--scenarios", "straight-eval", "--env-steps", "10"], "held-out"),
        (["--scenarios", "nope", "--env-steps", "10"], "unknown scenario"),
        (["--workers", "2"], "budget"),
        (["--baseline", "transfuser", "--env-steps", "10"], "needs --no-residual"),
        (["--baseline", "head", "--bp-dqn", "--env-steps", "10"], "its own method"),
        (["--densities", "5000", "--env-steps", "10"], "--densities"),
        (["--minutes", "1", "--lr-final", "1e-4"], "env_steps budget"),
        (["--env-steps", "10", "--lr-final", "0.1"], "lr_final"),
        (["--env-steps", "10", "--decision-interval", "0"], "decision_interval"),
        (["--env-steps", "10", "--horizon", "0.4"], "horizon"),
        (["--env-steps", "10", "--n-step", "0"], "TrainConfig.n_step=0"),
        (["--env-steps", "10", "--copies", "0"], "TrainConfig.copies=0"),
        (["--env-steps", "10", "--set-speed", "--no-residual"], "TrainConfig.set_speed=True"),
        (
            ["--env-steps", "10", "--twin", "--baseline", "p-ddpg"],
            "twin critics apply to rbp-dqn only",
        ),
        (["--env-steps", "10", "--demo-policy", "random"], "residual form corrects ACC-LC"),
        (["--env-steps", "10", "--scenarios", "ring-220m", "--densities", "180"], "ring-220m"),
    ],
)
def test_cli_errors(argv: list[str], message: str, capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit):
        main(argv)
    assert message in capsys.readouterr().err
