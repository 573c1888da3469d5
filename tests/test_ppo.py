"""The benchmark's learner interface and the SB3 PPO recipe, on real SUMO rings."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from agents.longitudinal import LongitudinalConfig, LongitudinalInterface
from agents.rules.acc_lc import FOLLOW, AccLcPolicy
from agents.rules.obs_batch import stack_obs
from analysis import benchmark_report
from mixed_traffic.benchmark import parallel_env, selection, task_config
from mixed_traffic.benchmark.interface import LongitudinalWrapper

pytest.importorskip("stable_baselines3")


def test_features_read_the_ring_and_actions_keep_acc_lc_lane_keeping() -> None:
    env = parallel_env("ring-v2", split="eval", index=0, episode_length=5.0)  # 22 on 210 m
    try:
        obs, _ = env.reset(seed=3)
        agents = list(obs)
        batch = stack_obs(obs, agents)
        iface = LongitudinalInterface()
        f = iface.observe(batch, agents)[0]
        assert f[0] == pytest.approx(obs[agents[0]]["ego"][-1, 0] * 40 / 10), "speed / 10 m/s"
        gap = f[2] * 50
        assert 1.0 < gap < 210 / 22, "a bumper gap shorter than the mean spacing of 9.5 m"
        assert f[5] == pytest.approx(f[0]), "the mean speed of one observed step is the speed"
        assert f[6] == 0 and f[7] == pytest.approx(1.0), "nothing commanded, no road cap at 30 m/s"
        decision, params = iface.command(np.array([1.0]))
        rule = AccLcPolicy().plan(batch)
        assert decision[0] == FOLLOW
        assert params[0, FOLLOW, 0] == pytest.approx(rule.params[0, FOLLOW, 0]), "ACC-LC steers"
        assert params[0, FOLLOW, 1] == pytest.approx(1.0), "+1 -> +3 m/s², the env's full throttle"
        _, params = iface.command(np.array([-1.0]))
        assert params[0, FOLLOW, 1] == pytest.approx(-0.5), "-1 -> -3 m/s² of the env's -6"
        assert iface.observe(batch, agents)[0, 6] == pytest.approx(-1.0), "the last command"
        with pytest.raises(ValueError, match="finite"):
            iface.command(np.array([np.nan]))
        # a residual: the zero action is the human model's IDM behind the perceived leader
        human = LongitudinalInterface(LongitudinalConfig(base="idm"))
        f = human.observe(batch, agents)[0]
        _, params = human.command(np.array([0.0]))
        v, gap, lead = f[0] * 10, f[2] * 50, (f[0] + f[1]) * 10
        h = human.human
        s_star = h.min_gap + v * h.headway + v * (v - lead) / (2 * np.sqrt(h.accel * h.decel))
        idm = h.accel * (1 - (v / 30.0) ** h.delta - (s_star / gap) ** 2)
        accel = params[0, FOLLOW, 1] * (3.0 if params[0, FOLLOW, 1] > 0 else 6.0)
        assert accel == pytest.approx(idm, rel=1e-3, abs=1e-3)
    finally:
        env.close()


def test_wrapper_holds_each_action_for_half_a_second() -> None:
    env = LongitudinalWrapper(parallel_env("ring-v2", episode_length=3.0))
    try:
        obs, _ = env.reset(seed=0)
        assert env.observation_space("av_0").contains(obs["av_0"])
        t0 = env.unwrapped.sim_time
        obs, rew, *_ = env.step({"av_0": np.array([0.2], np.float32)})
        assert env.unwrapped.sim_time == pytest.approx(t0 + 0.5)
        assert rew["av_0"] != 0 and obs["av_0"][6] == pytest.approx(0.2), "held, summed"
        with pytest.raises(ValueError, match="av_0"):
            env.step({})
    finally:
        env.close()


def test_the_failsafe_keeps_a_full_throttle_av_from_its_leader() -> None:
    """Full throttle for 40 s on the short eval ring: with the failsafe (Gipps's safe speed,
    1 s reaction) the AV never comes closer than its leader's braking allows; without it, it
    collides."""
    events = {}
    for reaction in (1.0, 0.0):
        env = LongitudinalWrapper(parallel_env("ring-v2", split="eval", index=0,
                                               episode_length=40.0),
                                  LongitudinalConfig(reaction=reaction))  # fmt: skip
        try:
            env.reset(seed=0)
            while env.agents:
                _, _, _, _, infos = env.step({"av_0": np.array([1.0])})
            events[reaction] = infos["av_0"]["event"]
        finally:
            env.close()
    assert events == {1.0: "", 0.0: "collision"}
    with pytest.raises(ValueError, match="reaction"):
        LongitudinalConfig(reaction=-1.0)
    with pytest.raises(ValueError, match="base='pid'"):
        LongitudinalConfig(base="pid")


@pytest.mark.parametrize("task", ["ring-v2", "merge-v1"])
def test_wrapped_tasks_pass_the_parallel_api_test(task: str) -> None:
    parallel_api_test(LongitudinalWrapper(parallel_env(task, episode_length=20.0)), num_cycles=60)


def test_ppo_trains_in_legs_resumes_and_drives_through_the_runner(tmp_path) -> None:
    from stable_baselines3 import PPO

    from agents.policies import make_policy
    from mixed_traffic.benchmark.ppo import PpoConfig, read_curves, train
    from mixed_traffic.experiments.runner import run_episode

    small = dict(steps=128, leg=64, n_steps=64, batch_size=32, n_epochs=2, episode_length=15.0,
                 val_seeds=1, out=tmp_path / "run", copies=2)  # fmt: skip
    train(PpoConfig(**small), progress=False)
    curve = tmp_path / "run" / "curves.csv"  # a kill after leg 2's checkpoint, before its row
    curve.write_text("".join(curve.read_text().splitlines(keepends=True)[:2]))
    meta = train(PpoConfig(**{**small, "steps": 192}), progress=False)  # resumes
    rows = read_curves(tmp_path / "run")
    assert [r["timesteps"] for r in rows] == [64, 128, 192] and meta["timesteps"] == 192
    assert rows[1]["episodes"] == 0 and rows[0]["episodes"] > 0  # leg 2's returns were lost
    assert rows[-1]["train_seconds"] > rows[0]["train_seconds"] > 0
    assert rows[0]["decisions_per_s"] > 0
    assert all(np.isfinite(r["val_std_ratio"]) and r["val_std_ratio"] > 0 for r in rows)
    best = json.loads((tmp_path / "run" / "best.json").read_text())  # the best leg is kept
    ranked = min(rows, key=selection.rank)
    assert best["leg"] == ranked["leg"] and best["val_std_ratio"] == ranked["val_std_ratio"]
    assert (tmp_path / "run" / "best.zip").stat().st_size > 0
    interface = json.loads((tmp_path / "run" / "model.json").read_text())["interface"]
    assert interface["hold"] == 5 and interface["reaction"] == 1.0  # the ring task's failsafe
    assert interface["base"] == "idm"
    norm = tmp_path / "run" / "reward_norm.pkl"  # the reward scaler resumes with the weights
    assert pickle.loads(norm.read_bytes()).ret_rms.count > 192
    model = PPO.load(tmp_path / "run" / "model.zip", device="cpu")
    assert model.use_sde and model.sde_sample_freq == 60, "exploration held 30 s"
    # a curriculum: a new run from the first one's weights keeps its decisions and time
    meta = train(PpoConfig(**{**small, "steps": 256, "out": tmp_path / "next",
                              "init": tmp_path / "run" / "model.zip"}), progress=False)  # fmt: skip
    assert [r["timesteps"] for r in read_curves(tmp_path / "next")] == [256]
    assert meta["train_seconds"] > rows[-1]["train_seconds"]
    curves = benchmark_report.read_curves([tmp_path / "run", tmp_path / "none"])
    assert list(curves) == ["run"]
    assert benchmark_report.plot_training(curves, tmp_path / "ppo.png").stat().st_size > 0

    ckpt = tmp_path / "run" / "model.zip"
    policy = make_policy("ppo", checkpoint=ckpt, family="ring")
    calls = []
    predict = policy.model.predict
    policy.model.predict = lambda x, **kw: (calls.append(len(x)), predict(x, **kw))[1]
    env = parallel_env("ring-v2", episode_length=2.0)
    try:
        obs, _ = env.reset(seed=1)
        while env.agents:
            agents = list(obs)
            decision, params = policy.act(stack_obs(obs, agents), agents)
            obs, *_ = env.step({a: {"decision": int(decision[i]), "params": params[i]}
                                for i, a in enumerate(agents)})  # fmt: skip
    finally:
        env.close()
    assert len(calls) == 4, "20 env steps, one decision every 5"
    config = task_config("ring-v2", "eval", episode_length=15.0)
    record = run_episode(config, "ppo", 0.0, checkpoint=ckpt)
    assert record["status"] == "ok" and record["metrics"]["mean_speed"] > 0


def test_bad_ppo_checkpoints_and_configs_are_named(tmp_path) -> None:
    from agents.policies import make_policy
    from agents.ppo_policy import check_ppo_checkpoint
    from mixed_traffic.benchmark.ppo import PpoConfig, main, training_env

    with pytest.raises(ValueError, match="needs --checkpoint"):
        make_policy("ppo")
    bad = tmp_path / "model.zip"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=r"model\.json"):
        check_ppo_checkpoint(bad)
    bad.with_suffix(".json").write_text(json.dumps({"interface": {}}))
    with pytest.raises(ValueError, match="unreadable"):
        check_ppo_checkpoint(bad)
    bad.with_suffix(".json").write_text(json.dumps({"interface": {"hold": 0}}))
    with pytest.raises(ValueError, match="hold"):
        check_ppo_checkpoint(bad)
    with pytest.raises(ValueError, match="hold"):
        LongitudinalConfig(hold=0)
    with pytest.raises(SystemExit):
        main(["--steps", "0", "--out", str(tmp_path / "x")])
    with pytest.raises(SystemExit):
        main(["--explore-hold", "-1", "--out", str(tmp_path / "x")])
    with pytest.raises(ValueError, match="--val-seeds=0"):
        PpoConfig(val_seeds=0)
    with pytest.raises(ValueError, match="--val-seed"):
        PpoConfig(val_seed=-1)
    with pytest.raises(SystemExit):
        main(["--init", str(bad.with_suffix(".zip.x")), "--out", str(tmp_path / "x")])
    assert not (tmp_path / "x").exists(), "nothing is written for a bad config"
    run = tmp_path / "corrupt"
    run.mkdir()
    (run / "reward_norm.pkl").write_bytes(b"not a pickle")
    with pytest.raises(ValueError, match="reward statistics"):
        training_env(PpoConfig(out=run))


def test_the_shipped_ring_policy_loads_with_its_lineage() -> None:
    from agents.policies import PPO_RING, make_policy
    from mixed_traffic.experiments.runner import check_checkpoint

    check_checkpoint(PPO_RING)
    policy = make_policy("ppo-ring", family="ring")
    assert policy.params["task"].startswith("ring-v") and policy.params["timesteps"] > 0
    assert policy.interface.cap_factor == pytest.approx(0.95), "the tuned ring rule's cap"
    meta = json.loads(PPO_RING.with_suffix(".json").read_text())
    assert {"revision", "sumo", "library", "train_seconds", "config"} <= set(meta)


def test_selection_keeps_the_best_validated_leg(tmp_path) -> None:
    """Safe legs that keep the humans' speed rank first, then the lowest std; a leg without
    validation numbers (an older run's) never counts; only a better leg replaces best.zip."""

    def row(leg: int, std: float, speed: float = 1.1, col: int = 0) -> dict:
        return {"leg": leg, "val_std_ratio": std, "val_speed_ratio": speed, "val_collisions": col}

    old = {"leg": 1, "val_std_ratio": float("nan")}
    rows = [old]
    for leg, (zip_text, r, kept) in enumerate(
        [(b"a", row(2, 0.6), True), (b"b", row(3, 0.3, speed=0.9), False),
         (b"c", row(4, 0.2, col=1), False), (b"d", row(5, 0.5), True), (b"e", row(6, 0.5), False)],
        start=2,
    ):  # fmt: skip
        (tmp_path / "model.zip").write_bytes(zip_text)
        rows.append(r)
        assert selection.keep_best(tmp_path, r, rows, {"timesteps": leg}) is kept, leg
    assert (tmp_path / "best.zip").read_bytes() == b"d"
    assert json.loads((tmp_path / "best.json").read_text())["leg"] == 5
    assert sorted(rows[1:], key=selection.rank)[-1]["leg"] == 4  # a collision ranks last
    assert selection.validation_configs("ring-v2", 1000, 2)[1].seed == 1001
    lengths = [c.ring_length for c in selection.validation_configs("ring-v2", 7, 1)]
    evals = [task_config("ring-v2", "eval", i).ring_length for i in (0, 1)]
    assert lengths == [(215.0,), (275.0,)] and not set(lengths) & set(evals)
