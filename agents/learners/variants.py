"""The paper's learning rules other than RBP-DQN (§V-A, "compared methods of reinforcement
learning" and TransFuser's imitation), on the same networks, replay and batches as
:class:`agents.learners.rbpdqn.RBPDQN`; :func:`make_learner` picks one by
``LearnerConfig.algorithm``. BP-DQN is RBP-DQN with ``regularize=False``.

- **P-DDPG** (Hausknecht & Stone 2016): the parameterized action collapsed into one continuous
  vector (3 decision scores + 6 parameters); a critic Q(s, a) of the whole vector and the DDPG
  actor update. The replay stores the executed decision, so a stored action's scores are its
  one-hot (±1); the executed decision is the masked argmax of the scores.
- **Q-PAMDP** (Masson et al. 2016): alternates learning the decisions' Q with the parameter
  policy fixed and improving the parameter policy with Q fixed, ``phase_updates`` updates each.
  Masson et al. improve the parameters by episodic natural actor-critic; here by the
  deterministic gradient of Q (as BP-DQN), so only the alternation differs.
- **Imitation** (TransFuser's training, Prakash et al. 2021): behaviour cloning of the
  demonstrator's labels only: the actor regresses its parameters, the critic ranks its decision
  first (the DQfD large margin alone, no TD term).
"""

from __future__ import annotations

import torch
from torch import Tensor

from agents.learners.rbpdqn import RBPDQN, LearnerConfig, _soft_update
from agents.nets.lca import LCAConfig
from agents.nets.networks import N_DECISIONS

ALGORITHMS = ("rbp-dqn", "p-ddpg", "q-pamdp", "imitation")


class PDDPG(RBPDQN):
    """P-DDPG: one Q of the whole (scores, parameters) vector; actor loss −Q(s, μ(s))."""

    def _masked_action(self, out: Tensor, action_mask: Tensor) -> Tensor:
        """Actor output (B, 3, 3) with the scores of masked decisions at −1 (their floor)."""
        scores = out[..., 2].masked_fill(action_mask <= 0.5, -1.0)
        return torch.cat((out[..., :2], scores[..., None]), dim=-1)

    def td_target(self, batch: dict) -> Tensor:
        nxt = batch["next_obs"]
        with torch.no_grad():
            act = self._masked_action(self.actor_targ(nxt), nxt["action_mask"])
            best = self.critic_targ(nxt, act)[:, 0]
            gamma = self.cfg.gamma
            if "discount" in batch:
                gamma = torch.nan_to_num(batch["discount"], nan=gamma)
            return batch["reward"] + gamma * (1.0 - batch["done"]) * best

    def critic_loss(self, batch: dict) -> Tensor:
        y = self.td_target(batch)
        onehot = torch.nn.functional.one_hot(batch["decision"], N_DECISIONS).float() * 2 - 1
        act = torch.cat((batch["params"], onehot[..., None]), dim=-1)
        return 0.5 * (y - self.critic(batch["obs"], act)[:, 0]).pow(2).mean()

    def actor_loss(self, batch: dict) -> Tensor:
        obs = batch["obs"]
        act = self._masked_action(self.actor(obs), obs["action_mask"])
        return -self.critic(obs, act)[:, 0].mean()


class QPAMDP(RBPDQN):
    """Q-PAMDP: critic-only and actor-only phases of ``phase_updates`` updates in turn."""

    def update(self, batch: dict) -> dict[str, float]:
        """One step of the current phase's network and its target; the other's loss is NaN."""
        critic_phase = (self.steps // self.cfg.phase_updates) % 2 == 0
        critic_loss, actor_loss = self._losses()
        net, opt, targ = ((self.critic, self.critic_opt, self.critic_targ) if critic_phase
                          else (self.actor, self.actor_opt, self.actor_targ))  # fmt: skip
        self.critic.requires_grad_(critic_phase)  # the actor's phase builds no critic grads
        try:
            loss = critic_loss(batch) if critic_phase else actor_loss(batch)
            norm = self._step(loss, net, opt)
        finally:
            self.critic.requires_grad_(True)
        _soft_update(targ, net, self.cfg.tau)
        self.steps += 1
        nan = float("nan")
        c, a = (float(loss.detach()), nan) if critic_phase else (nan, float(loss.detach()))
        return {"critic_loss": c, "actor_loss": a, "critic_grad_norm": float(norm) if critic_phase
                else 0.0, "actor_grad_norm": 0.0 if critic_phase else float(norm)}  # fmt: skip


class Imitation(RBPDQN):
    """Behaviour cloning of the demonstrator's labels (TransFuser's training)."""

    def critic_loss(self, batch: dict) -> Tensor:
        """The DQfD margin on labelled rows: the demonstrator's decision ranks first."""
        q_all = self.critic(batch["obs"], batch.get("label_params", batch["params"]))
        return self.margin_loss(q_all, batch)

    def actor_loss(self, batch: dict) -> Tensor:
        """The behaviour-cloning term alone (α = 0)."""
        u = self.actor(batch["obs"])
        w = u.new_tensor([self.cfg.bc_steer_weight, self.cfg.bc_accel_weight])
        target = batch.get("label_params", batch["params"])
        return ((u - target).pow(2) * w).sum(dim=(1, 2)).mean()


def make_learner(
    lca: LCAConfig, cfg: LearnerConfig | None = None, seed: int = 0, compile: bool = False
) -> RBPDQN:
    """The learner of ``cfg.algorithm`` (ValueError naming an unknown one)."""
    cfg = cfg or LearnerConfig()
    classes = {"rbp-dqn": RBPDQN, "p-ddpg": PDDPG, "q-pamdp": QPAMDP, "imitation": Imitation}
    if cfg.algorithm not in classes:
        raise ValueError(f"LearnerConfig.algorithm={cfg.algorithm!r}: choose from {ALGORITHMS}")
    if cfg.twin and cfg.algorithm != "rbp-dqn":
        raise ValueError(
            f"LearnerConfig.twin: twin critics apply to rbp-dqn only, not {cfg.algorithm!r}"
        )
    return classes[cfg.algorithm](lca, cfg, seed=seed, compile=compile)


__all__ = ["ALGORITHMS", "PDDPG", "QPAMDP", "Imitation", "make_learner"]
