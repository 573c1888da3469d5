"""Agents: LCA/actor/critic shapes, masked selection, learner, replay, checkpoints, fused path.

Pure torch/numpy (no SUMO), small sizes, fast.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from agents.bench_inference import random_obs
from agents.checkpoint import load_checkpoint, load_policy, save_checkpoint
from agents.learners.rbpdqn import RBPDQN, LearnerConfig, Policy, obs_to_torch
from agents.learners.replay import ReplayBuffer
from agents.learners.variants import make_learner
from agents.nets.fused import FusedActorCritic
from agents.nets.lca import LCA, LCAConfig
from agents.nets.networks import FOLLOW, Actor, Critic, masked_q, select

ABLATIONS = [
    {},
    {"ego_fusion": False},  # the paper's fusion of the lane vectors only
    {"history": False},
    {"lane_wise": False},
    {"star": False},
    {"history": False, "lane_wise": False, "star": False},
]


def _obs(b: int, cfg: LCAConfig, seed: int = 0) -> dict[str, torch.Tensor]:
    return obs_to_torch(random_obs(b, cfg, np.random.default_rng(seed)))


def _batch(b: int, cfg: LCAConfig, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    buf = ReplayBuffer(b, cfg)
    obs, nxt = random_obs(b, cfg, rng), random_obs(b, cfg, rng)
    buf.add_batch(
        obs,
        rng.integers(0, 3, b),
        rng.uniform(-1, 1, (b, 3, 2)).astype(np.float32),
        rng.normal(size=b).astype(np.float32),
        nxt,
        (rng.random(b) < 0.1).astype(np.float32),
    )
    return buf.sample(b, rng)


@pytest.mark.parametrize("flags", ABLATIONS)
@pytest.mark.parametrize("b", [1, 7])
def test_shapes(flags: dict, b: int) -> None:
    cfg = LCAConfig(z=4, m=6, **flags)  # non-default z, m: nothing may be hard-coded
    obs = _obs(b, cfg)
    assert LCA(cfg)(obs).shape == (b, cfg.d)
    params = Actor(cfg)(obs)
    assert params.shape == (b, 3, 2)
    assert params.abs().max() <= 1.0
    q = Critic(cfg)(obs, params)
    assert q.shape == (b, 3)
    assert select(q, obs["action_mask"]).shape == (b,)


def test_config_from_shapes() -> None:
    cfg = LCAConfig(z=3, m=7)
    assert LCAConfig.from_obs_shapes(cfg.obs_shapes()) == cfg


def test_fully_masked_lane_no_nan() -> None:
    cfg = LCAConfig()
    obs = _obs(5, cfg)
    obs["node_mask"][:] = 0.0
    for flags in ABLATIONS:
        c = LCAConfig(**flags)
        assert torch.isfinite(LCA(c)(obs)).all()


def test_masked_decision_never_chosen() -> None:
    g = torch.Generator().manual_seed(0)
    for _ in range(50):
        q = torch.randn(64, 3, generator=g) * 10
        mask = torch.rand(64, 3, generator=g) < 0.5
        # Include rows with exactly one allowed decision.
        mask[:8] = False
        mask[torch.arange(8), torch.randint(0, 3, (8,), generator=g)] = True
        mask[8] = False  # all masked → documented fallback
        dec = select(q, mask)
        ok = mask[torch.arange(64), dec]
        some = mask.any(1)
        assert ok[some].all()
        assert (dec[~some] == FOLLOW).all() and not some[8]
        # Among allowed ones it is the argmax.
        best = q.masked_fill(~mask, -1e30).argmax(1)
        assert torch.equal(dec[:8], best[:8])


def test_policy_respects_mask_with_exploration() -> None:
    cfg = LCAConfig()
    learner = RBPDQN(cfg)
    pol = Policy(learner.actor, learner.critic, epsilon=0.5)
    rng = np.random.default_rng(1)
    obs = random_obs(40, cfg, rng)
    obs["action_mask"][:] = 0.0
    obs["action_mask"][np.arange(40), rng.integers(0, 3, 40)] = 1.0
    for explore in (False, True):
        dec, params = pol.act(obs, explore=explore, rng=rng)
        assert dec.shape == (40,) and params.shape == (40, 3, 2)
        assert (obs["action_mask"][np.arange(40), dec] == 1).all()
        assert np.abs(params).max() <= 1.0


@pytest.mark.parametrize(
    ("ego_fusion", "multi_pass", "extra"),
    [(True, False, 0), (False, False, 0), (True, True, 0), (True, False, 18), (False, True, 12)],
)
@pytest.mark.parametrize("b", [1, 7, 128])
def test_fused_matches_reference(b: int, ego_fusion: bool, multi_pass: bool, extra: int) -> None:
    """Also with the observation's extra vector (memory and downstream) in the fusion."""
    cfg = LCAConfig(ego_fusion=ego_fusion, extra=extra)
    torch.manual_seed(3)
    actor, critic = Actor(cfg), Critic(cfg, multi_pass=multi_pass)
    obs = _obs(b, cfg, seed=b)
    obs["node_mask"][0] = 0.0  # a fully masked agent
    with torch.no_grad():
        p_ref = actor(obs)
        q_ref = critic(obs, p_ref)
    p, q, hold = FusedActorCritic(actor, critic)(obs)
    assert hold is None
    torch.testing.assert_close(p, p_ref, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(q, q_ref, atol=1e-5, rtol=1e-4)
    if extra:  # the vector is read: another extra changes the answer
        obs["extra"] = obs["extra"] + 0.5
        assert not torch.allclose(FusedActorCritic(actor, critic)(obs)[0], p)


def test_multi_pass_q_sees_only_its_own_parameters() -> None:
    """MP-DQN: dQ_p/du_r = 0 for r != p, and each pass equals the single-pass critic fed only
    row p (the others zeroed)."""
    cfg = LCAConfig()
    torch.manual_seed(4)
    critic = Critic(cfg, multi_pass=True)
    obs = _obs(5, cfg)
    u = torch.rand(5, 3, 2, requires_grad=True)
    q = critic(obs, u)
    for p in range(3):
        (g,) = torch.autograd.grad(q[:, p].sum(), u, retain_graph=True)
        others = [r for r in range(3) if r != p]
        assert torch.equal(g[:, others], torch.zeros_like(g[:, others]))
        assert g[:, p].abs().sum() > 0
    single = Critic(cfg)
    single.load_state_dict(critic.state_dict())
    with torch.no_grad():
        for p in range(3):
            only = torch.zeros_like(u)
            only[:, p] = u[:, p]
            torch.testing.assert_close(q[:, p], single(obs, only)[:, p])


def test_policy_sync_after_update() -> None:
    cfg = LCAConfig()
    learner = RBPDQN(cfg)
    pol = Policy(learner.actor, learner.critic)
    obs = _obs(6, cfg)
    learner.update(_batch(16, cfg))
    pol.sync()
    q, p, _ = pol.q_and_params(obs)
    with torch.no_grad():
        torch.testing.assert_close(p, learner.actor(obs), atol=1e-5, rtol=1e-4)
        torch.testing.assert_close(q, learner.critic(obs, p), atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("regularize", [True, False])
def test_learner_lowers_critic_loss(regularize: bool) -> None:
    cfg = LCAConfig()
    learner = RBPDQN(cfg, LearnerConfig(regularize=regularize), seed=0)
    batch = _batch(64, cfg)
    first = learner.critic_loss(batch).item()
    for _ in range(30):
        out = learner.update(batch)
    assert np.isfinite(out["actor_loss"])
    assert learner.critic_loss(batch).item() < first


def test_expert_labels_are_the_cloning_and_margin_targets() -> None:
    cfg = LCAConfig()
    learner = RBPDQN(cfg, LearnerConfig(alpha=0.0, lr=3e-3), seed=0)
    batch = _batch(64, cfg)
    batch["obs"]["action_mask"][:] = 1.0
    batch["labelled"][:] = 1.0
    batch["label_decision"][:] = 2
    batch["label_params"][:] = torch.tensor([[0.1, -0.5]] * 3)
    for _ in range(150):
        learner.update(batch)
    with torch.no_grad():
        u = learner.actor(batch["obs"])
        q = learner.critic(batch["obs"], batch["params"])
    # the actor clones the labels, not the (random) taken params
    assert (u - batch["label_params"]).abs().max() < 0.05
    assert (u - batch["params"]).abs().mean() > 0.3
    assert (q.argmax(dim=1) == 2).float().mean() > 0.95


def test_bc_weights_scale_each_parameter_error() -> None:
    cfg = LCAConfig()
    batch = _batch(16, cfg)
    losses = {}
    for w in (1.0, 10.0):
        learner = RBPDQN(cfg, LearnerConfig(alpha=0.0, bc_accel_weight=w), seed=0)
        with torch.no_grad():
            u = learner.actor(batch["obs"])
        batch["label_params"] = u.clone()
        batch["label_params"][..., 1] += 0.2  # an accel_brake error only
        losses[w] = learner.actor_loss(batch).item()
    # Σ over 3 decisions of w·0.2²
    assert losses[1.0] == pytest.approx(3 * 0.04, rel=1e-4)
    assert losses[10.0] == pytest.approx(10 * losses[1.0], rel=1e-4)


def test_accel_expectile_weighs_errors_below_the_label_more() -> None:
    cfg = LCAConfig()
    batch = _batch(16, cfg)
    learner = RBPDQN(cfg, LearnerConfig(alpha=0.0, bc_accel_expectile=0.8), seed=0)
    with torch.no_grad():
        u = learner.actor(batch["obs"])
    losses = {}
    for sign in (1.0, -1.0):  # label above (actor too low) / below (actor too high)
        batch["label_params"] = u.clone()
        batch["label_params"][..., 1] += sign * 0.2
        batch["label_params"][..., 0] += 0.01  # a steering error keeps its symmetric weight
        losses[sign] = learner.actor_loss(batch).item()
    steer = 3 * 100.0 * 0.01**2
    assert losses[1.0] - steer == pytest.approx(3 * 1.6 * 0.04, rel=1e-4)
    assert losses[-1.0] - steer == pytest.approx(3 * 0.4 * 0.04, rel=1e-4)


def _bootstrap_case(b: int) -> tuple[RBPDQN, dict, torch.Tensor]:
    """A fresh learner, a batch of ``b`` non-terminal rows and the target networks' Q (b, 3)
    of their next observations."""
    cfg = LCAConfig()
    learner = RBPDQN(cfg)
    batch = _batch(b, cfg)
    batch["done"][:] = 0.0
    nxt = batch["next_obs"]
    with torch.no_grad():
        q = learner.critic_targ(nxt, learner.actor_targ(nxt))
    return learner, batch, q


def test_td_target_ignores_masked_decisions() -> None:
    learner, batch, q = _bootstrap_case(8)
    nxt = batch["next_obs"]
    nxt["action_mask"][:] = 0.0
    nxt["action_mask"][:, 2] = 1.0
    y = learner.td_target(batch)
    torch.testing.assert_close(y, batch["reward"] + 0.9 * q[:, 2])


def test_td_target_uses_each_rows_discount() -> None:
    """A decision interval cut short discounts less; NaN rows fall back to the learner's γ."""
    learner, batch, q = _bootstrap_case(4)
    best = masked_q(q, batch["next_obs"]["action_mask"]).max(dim=1).values
    batch["discount"] = torch.tensor([0.95, 0.99, float("nan"), 0.5])
    y = learner.td_target(batch)
    gamma = torch.tensor([0.95, 0.99, 0.9, 0.5])
    torch.testing.assert_close(y, batch["reward"] + gamma * best)


def test_twin_critics_take_the_smaller_target_at_the_first_critics_best_decision(tmp_path) -> None:
    cfg = LCAConfig()
    learner = RBPDQN(cfg, LearnerConfig(twin=True))
    single = RBPDQN(cfg)  # the same seed: the first pair is the one-critic learner's
    assert all(torch.equal(a, b) for a, b in zip(learner.critic.parameters(),
                                                 single.critic.parameters()))  # fmt: skip
    batch = _batch(16, cfg)
    batch["done"][:] = 0.0
    nxt = batch["next_obs"]
    with torch.no_grad():
        u = learner.actor_targ(nxt)
        q1 = masked_q(learner.critic_targ(nxt, u), nxt["action_mask"])
        best, arg = q1.max(dim=1)
        q2 = learner.critic2_targ(nxt, u).gather(1, arg[:, None])[:, 0]
    assert not torch.equal(q2, best)  # the twin is its own draw
    torch.testing.assert_close(learner.td_target(batch),
                               batch["reward"] + 0.9 * torch.minimum(best, q2))  # fmt: skip
    assert (learner.td_target(batch) <= single.td_target(batch) + 1e-6).all()
    before = [p.detach().clone() for p in learner.critic2.parameters()]
    learner.update(batch)  # both critics learn
    assert any(not torch.equal(a, b) for a, b in zip(before, learner.critic2.parameters()))
    path = save_checkpoint(tmp_path / "twin.pt", learner)
    loaded, _ = load_checkpoint(path)
    assert loaded.cfg.twin and all(
        torch.equal(a, b) for a, b in zip(loaded.critic2.parameters(), learner.critic2.parameters())
    )
    batch2 = _batch(16, cfg, seed=3)
    assert loaded.update(batch2) == learner.update(batch2)  # resumes with the twin's optimiser
    with pytest.raises(ValueError, match="twin critics apply to rbp-dqn only"):
        make_learner(cfg, LearnerConfig(twin=True, algorithm="p-ddpg"))


def test_residual_form_starts_at_zero() -> None:
    """The residual learner's actor outputs u = 0 and its critic Q = 0 everywhere at start."""
    cfg = LCAConfig()
    learner = RBPDQN(cfg, LearnerConfig(residual=True))
    obs = _obs(6, cfg)
    u = learner.actor(obs)
    assert torch.equal(u, torch.zeros_like(u))
    assert torch.equal(learner.critic(obs, u), torch.zeros(6, 3))


def test_determinism() -> None:
    cfg = LCAConfig()

    def run() -> list[torch.Tensor]:
        learner = RBPDQN(cfg, seed=11)
        for i in range(3):
            learner.update(_batch(32, cfg, seed=i))
        return [p.detach().clone() for p in learner.actor.parameters()] + [
            p.detach().clone() for p in learner.critic.parameters()
        ]

    for a, b in zip(run(), run(), strict=True):
        assert torch.equal(a, b)


def test_replay_shapes_and_wraparound() -> None:
    cfg = LCAConfig(z=3, m=4)
    rng = np.random.default_rng(0)
    buf = ReplayBuffer(10, cfg)
    for step in range(3):  # 3 × 4 = 12 > 10: wraps
        n = 4
        obs = random_obs(n, cfg, rng)
        buf.add_batch(
            obs,
            np.full(n, step),
            np.zeros((n, 3, 2), np.float32),
            np.full(n, float(step), np.float32),
            random_obs(n, cfg, rng),
            np.zeros(n, np.float32),
        )
    assert len(buf) == 10 and buf.pos == 2
    # Slots 0, 1 hold the newest step (2); slots 2..9 hold steps 0 (2 left) and 1.
    assert list(buf.reward) == [2, 2, 0, 0, 1, 1, 1, 1, 2, 2]
    batch = buf.sample(5, rng)
    for k, s in cfg.obs_shapes().items():
        assert batch["obs"][k].shape == (5, *s)
        assert batch["next_obs"][k].shape == (5, *s)
    assert batch["params"].shape == (5, 3, 2)
    assert batch["decision"].dtype == torch.int64
    # Round trip through state_dict.
    other = ReplayBuffer(10, cfg)
    other.load_state_dict(buf.state_dict())
    assert other.pos == buf.pos and len(other) == len(buf)
    np.testing.assert_array_equal(other.obs["lanes"], buf.obs["lanes"])
    assert np.isnan(other.discount[:10]).all()  # none given: the learner's γ
    buf.add_batch(obs, np.zeros(4), np.zeros((4, 3, 2)), np.zeros(4), obs, np.zeros(4),
                  discount=np.full(4, 0.95))  # fmt: skip
    other.load_state_dict(buf.state_dict())
    np.testing.assert_allclose(other.discount[2:6], 0.95)


def test_checkpoint_round_trip(tmp_path) -> None:
    cfg = LCAConfig()
    learner = RBPDQN(cfg)
    learner.update(_batch(16, cfg))
    path = save_checkpoint(tmp_path / "ck.pt", learner, {"env_steps": 5})
    loaded, meta = load_checkpoint(path, z=cfg.z, m=cfg.m)
    assert meta["env_steps"] == 5 and meta["lca"]["z"] == cfg.z
    assert loaded.steps == learner.steps
    obs = _obs(7, cfg)
    with torch.no_grad():
        pa, pb = learner.actor(obs), loaded.actor(obs)
        assert torch.equal(pa, pb)
        assert torch.equal(learner.critic(obs, pa), loaded.critic(obs, pb))
    # Training resumes identically (optimiser state included).
    batch = _batch(16, cfg, seed=9)
    assert learner.update(batch) == loaded.update(batch)
    assert not list(tmp_path.glob(".*.tmp"))  # no temp files left behind
    pol = load_policy(path)
    dec, params = pol.act({k: v.numpy() for k, v in obs.items()}, explore=False)
    assert dec.shape == (7,) and params.shape == (7, 3, 2)


def test_paper_form_checkpoint_widens_to_the_same_policy(tmp_path) -> None:
    paper = LCAConfig(ego_fusion=False)
    old = RBPDQN(paper, seed=1)
    old.update(_batch(16, paper))
    path = save_checkpoint(tmp_path / "paper.pt", old)
    # a checkpoint written before the field existed is the paper's form
    data = torch.load(path, weights_only=True)
    del data["meta"]["lca"]["ego_fusion"]
    torch.save(data, path)
    assert load_checkpoint(path)[0].lca_cfg == paper
    new = RBPDQN(LCAConfig())
    with pytest.raises(
        ValueError, match=r"paper\.pt.*ego_fusion: checkpoint False vs requested True"
    ):
        load_checkpoint(path, learner=new)  # only an explicit widen changes the model
    load_checkpoint(path, learner=new, widen=True)
    obs = _obs(9, paper, seed=3)
    with torch.no_grad():
        p_old, p_new = old.actor(obs), new.actor(obs)
        torch.testing.assert_close(p_new, p_old, atol=0.0, rtol=0.0)
        torch.testing.assert_close(new.critic(obs, p_new), old.critic(obs, p_old))
    # the new ego columns start at zero, then learn (they get gradients); their Adam second
    # moments start at the row means of the old columns, not at zero
    d = paper.d
    assert new.actor.lca.fuse[0].weight[:, 3 * d :].abs().max() == 0
    i = [p is new.actor.lca.fuse[0].weight for p in new.actor.parameters()].index(True)
    v = new.actor_opt.state_dict()["state"][i]["exp_avg_sq"]
    torch.testing.assert_close(v[:, 3 * d :], v[:, : 3 * d].mean(1, keepdim=True).expand(-1, d))
    assert v[:, 3 * d :].max() > 0
    new.update(_batch(16, paper, seed=4))
    assert new.actor.lca.fuse[0].weight[:, 3 * paper.d :].abs().max() > 0


def test_checkpoint_errors(tmp_path) -> None:
    cfg = LCAConfig()
    good = save_checkpoint(tmp_path / "good.pt", RBPDQN(cfg))

    with pytest.raises(ValueError, match=r"missing\.pt.*not found"):
        load_checkpoint(tmp_path / "missing.pt")

    trunc = tmp_path / "trunc.pt"
    trunc.write_bytes(good.read_bytes()[:500])
    with pytest.raises(ValueError, match=r"trunc\.pt.*corrupt"):
        load_checkpoint(trunc)

    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"\x00not a checkpoint" * 50)
    with pytest.raises(ValueError, match=r"garbage\.pt.*corrupt"):
        load_checkpoint(garbage)

    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(3)}, other)
    with pytest.raises(ValueError, match=r"other\.pt.*not an RBP-DQN checkpoint"):
        load_checkpoint(other)

    with pytest.raises(
        ValueError,
        match=r"good\.pt.*mismatch.*lanes: checkpoint \(3, 5, 40\) vs requested \(3, 5, 24\)",
    ):
        load_checkpoint(good, m=6)
    with pytest.raises(
        ValueError, match=r"good\.pt.*mismatch.*ego: checkpoint \(5, 5\) vs requested \(4, 5\)"
    ):
        load_checkpoint(good, z=4)


def test_bench_runs() -> None:
    from agents.bench_inference import avg_inference_us

    us = avg_inference_us(n_agents=16, repeats=1, iters=2)
    assert us > 0


def test_policy_fused_equals_reference_with_exploration() -> None:
    cfg = LCAConfig()
    learner = RBPDQN(cfg, seed=4)
    obs = random_obs(30, cfg, np.random.default_rng(2))
    outs = []
    for fused in (True, False):
        pol = Policy(learner.actor, learner.critic, epsilon=0.2, fused=fused)
        outs.append(pol.act(obs, explore=True, rng=np.random.default_rng(5)))
    np.testing.assert_array_equal(outs[0][0], outs[1][0])
    np.testing.assert_allclose(outs[0][1], outs[1][1], atol=1e-5)


def test_fused_varying_batch_sizes() -> None:
    cfg = LCAConfig()
    torch.manual_seed(0)
    actor, critic = Actor(cfg), Critic(cfg)
    fused = FusedActorCritic(actor, critic)
    for b in (3, 9, 3, 20, 1, 5, 9, 2):  # growing and shrinking batches
        obs = _obs(b, cfg, seed=b)
        _p, q, _ = fused(obs)
        with torch.no_grad():
            torch.testing.assert_close(q, critic(obs, actor(obs)), atol=1e-5, rtol=1e-4)
    (arena,) = fused.nodes_gru._arenas.values()
    assert arena.cap == 3 * 20  # the largest batch's rows (B x 3 lanes); smaller ones reuse it


def test_bench_env_json_prints_one_object_per_policy_and_penetration(capsys) -> None:
    """``bench --section env --json``: one JSON line per (env policy, penetration) on straight,
    then the one-AV ring, with the keys issues 25 and 45 name, a positive ratio measured
    against the physical limit."""
    import json

    from mixed_traffic.experiments.bench import main

    argv = ["--section", "env", "--json", "--env-policy", "keep", "--penetrations", "0.2", "1.0",
            "--env-steps", "10", "--block", "5", "--env-density", "40"]  # fmt: skip
    assert main(argv) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    recs = [json.loads(x) for x in lines]
    rows = [(r["scenario"], r["env_policy"], r["penetration"]) for r in recs]
    assert rows == [("straight", "keep", 0.2), ("straight", "keep", 1.0),
                    ("ring", "keep", pytest.approx(1 / 22))]  # fmt: skip
    assert recs[-1]["agents"] == 1.0 and recs[-1]["vehicles"] == 22.0
    for r in recs:
        assert {"ratio", "agent_steps_per_s", "ms_per_step"} <= set(r)
        assert r["ratio"] > 0 and r["ms_per_step"] > 0 and r["agent_steps_per_s"] > 0
