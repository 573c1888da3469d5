"""RBP-DQN learner (paper §IV-F eq. train_actor / train_critic) and the batched inference policy.

Batch layout (what :meth:`agents.learners.replay.ReplayBuffer.sample` returns), B = batch size:

- ``obs``, ``next_obs``: dicts of float tensors (B, ...) per DESIGN §6 (``next_obs`` includes
  ``action_mask`` (B, 3), used to mask the TD target);
- ``decision`` (B,) int64, ``params`` (B, 3, 2) float (all three rows as stored, A^t),
  ``reward`` (B,), ``done`` (B,) float (1 = terminal, no bootstrap), optional ``discount``
  (B,) float (the bootstrap's discount; NaN or absent = ``LearnerConfig.gamma``);
- optional expert labels: ``labelled`` (B,) float (1 = the demonstrator labelled the
  observation), ``label_decision`` (B,) int64 and ``label_params`` (B, 3, 2) (its action, or
  the taken action on unlabelled rows).

Deviation (expert relabelling, DAgger-style; Ross et al. 2011): the behaviour-cloning term
regresses on ``label_params`` and the DQfD margin ranks ``label_decision`` first. When the
demonstrator drove, that is the paper's BC on the taken action; when the agent drove, the
demonstrator's action for the same observation is the target, so the agent learns to recover
from the states its own errors lead to (cloning only demonstrator states compounds errors:
steering error 0.45° on demonstrator states, 3-5° on the agent's own).

Deviation from the paper's printed actor loss: it puts the behaviour-cloning term inside the
negated sum, which would *reward* drifting from the data; as in TD3+BC (the cited source) the
regulariser is added: L_a = −Σ_p α·Q(s, p, u_p(s))/AvgQ + Σ_p ‖u_p(s) − a_p‖².

Speed (issue 22; ``python -m mixed_traffic.bench --section learner``): Adam is fused, clipping
and soft updates are foreach ops, and ``compile=True`` runs the two losses through
``torch.compile``.
"""

from __future__ import annotations

import copy
from dataclasses import asdict, dataclass
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from agents.nets.fused import FusedActorCritic
from agents.nets.lca import LCAConfig
from agents.nets.networks import FOLLOW, LEAD_SPREAD, Actor, Critic, masked_q, select
from agents.rules.obs_batch import EXTRA, EXTRA_KEYS, for_policy


@dataclass(frozen=True)
class LearnerConfig:
    """Learner hyper-parameters (paper §IV-F / DESIGN §10 defaults)."""

    gamma: float = 0.9
    """Discount per decision [-] (a transition's own ``discount`` wins where the batch has one)."""
    tau: float = 0.01
    """Soft target update rate."""
    alpha: float = 0.6
    """Weight of the normalised Q term in the actor loss."""
    lr: float = 1e-3
    batch_size: int = 128
    grad_clip: float = 10.0
    """Max global gradient norm per network."""
    regularize: bool = True
    """False → BP-DQN baseline: actor loss −Σ_p Q, no behaviour cloning, no AvgQ scaling."""
    avgq_eps: float = 1e-6
    demo_margin: float = 0.8
    """DQfD large-margin l: demonstrated decisions must beat the others by this much [Q units]."""
    demo_weight: float = 1.0
    """Weight of the DQfD margin loss on demonstrator transitions (0 = the paper's critic)."""
    bc_steer_weight: float = 100.0
    """Weight of steering errors in the behaviour-cloning term. Lane keeping needs steering to
    about a degree (0.02 of the ±60° range), while a random accel_brake error of 0.1 is
    harmless; with equal weights the fit ignores steering (1 = the paper's loss)."""
    bc_accel_weight: float = 1.0
    """Weight of accel_brake errors in the behaviour-cloning term (1 = the paper's loss). A
    *systematic* accel_brake error of 0.1 costs efficiency (the shipped fine-tune used 10, see
    ``agents/__init__.py``)."""
    bc_accel_expectile: float = 0.5
    """Expectile τ of the accel_brake fit: errors below the label weigh 2τ, above it 2(1 − τ)
    (0.5 = the paper's squared error). τ > 0.5 fits an upper expectile of the label where the
    observation cannot separate holding from going (e.g. a queue starting), and the safety
    module's clamp removes what is above ACC-LC's braking."""

    residual: bool = False
    """Residual form (issue 22): the actor's output u is a bounded correction to ACC-LC's
    parameters, executed as clip(ACC-LC + (steer_delta, accel_delta)·u, -1, 1), its last
    layer starts at zero (u = 0 is ACC-LC), and behaviour cloning is ‖u‖² (the labels are 0).
    False = the paper's form: u is the parameters themselves."""
    steer_delta: float = 0.005
    """Residual form: largest steering correction [action units; 0.005 = 0.3°]. Held for a
    0.5 s decision at 30 m/s, 0.05 (3°) moved a car up to 2 m sideways: exploration noise on it
    collided 24 times in 176 AV trips on straight-4lane, none at 0.005 (docs/agent.md)."""
    accel_delta: float = 0.25
    """Residual form: largest accel_brake correction [action units; 0.25 = +0.75 / -1.5 m/s²]."""
    teacher_bonus: float = 0.0
    """Residual form: Q bonus of ACC-LC's decision at selection; another decision is taken only
    where the critic values it higher by more than this [Q units]."""
    decision_interval: float = 0.1
    """Time between the policy's decisions [s], rounded to whole simulation steps; the command
    is held in between (``agents.driver``). 0.1 s = one decision per step, as in the paper."""
    speed_governor: bool = False
    """Residual form: the correction may raise the acceleration only up to what keeps the ego
    within its speed limit, the curve and limit targets ahead and a red or yellow light's stop
    (``agents.rules.acc_lc_longitudinal.speed_cap``), or to ACC-LC's own acceleration where
    that is higher (False = unbounded, as checkpoints before it)."""
    rss_governor: bool = False
    """Residual form: the correction may raise a row's acceleration only up to the RSS-safe
    one behind that lane's leaders (``agents.rules.rss``), or to ACC-LC's own where that is
    higher (False = unbounded, as checkpoints before it)."""
    multi_pass: bool = False
    """MP-DQN critic (``agents.nets.networks.Critic``): each decision's Q sees only its own
    parameters (False = the paper's P-DQN critic)."""
    algorithm: str = "rbp-dqn"
    """Learning rule (``agents.learners.variants``): rbp-dqn (this class; BP-DQN with
    ``regularize=False``) | p-ddpg | q-pamdp | imitation."""
    steer_control: bool = True
    """Residual form: the policy corrects the steering (False = HEAD: discrete lane decisions
    and accel only, ACC-LC's lane keeping steers)."""
    phase_updates: int = 500
    """Q-PAMDP: updates per phase of its alternation (critic only, then actor only)."""
    hold_gate: bool = False
    """Residual form: the actor has a hold gate (``Actor.gate``). Where its score is > 0 at a
    decision, the follow row holds speed until the next one: it tracks a reference speed that
    follows the leader's speed slowly (``hold_tau``) and brakes only for what ACC-LC brakes
    beyond ``hold_brake`` (docs/agent.md, "Hold gate"). The fleet search sets the gate
    (``--target gate``); False = no gate, as checkpoints before it."""
    hold_brake: float = 1.5
    """How much of ACC-LC's braking a held AV ignores [m/s²]: it brakes at a + hold_brake where
    that is below its tracking acceleration."""
    hold_tau: float = 40.0
    """Time constant of the held reference speed, an exponential mean of the leader's speed
    [s]; longer than a stop-and-go wave's period (about 30 s on the 260 m ring)."""
    hold_gain: float = 0.5
    """Gain of the held AV's speed tracking: acceleration per m/s below the reference [1/s]."""
    set_speed: bool = False
    """Residual form with a set speed (issue 43 item 3): the follow row's first parameter,
    unused for steering (ACC-LC steers, as ``steer_control=False``), sets a speed that the row
    tracks with ``hold_gain``: v_set = ref + ``set_speed_span``·(1 + u), with ref the leader's
    speed averaged over ``hold_tau``; the row's acceleration is the smaller of that tracking
    and the residual one, so ACC-LC's gap keeping still brakes. u = -1 holds ref, as
    FollowerStopper holds its mean speed (a set speed below the mean would slow a ring down
    without end), u = 0 sets ref + span and u = 1 ref + 2·span (loose). Without a leader, or
    with a signal or give-way line in view, the residual row drives."""
    set_speed_span: float = 2.5
    """Reach of the set speed above the leader's mean at u = 0 [m/s]."""
    teacher: str = "acc-lc"
    """Residual form: the rule whose parameters u corrects and whose lane plan the safety module
    and the set speed reuse: acc-lc (the default ACC-LC) | acc-lc-tuned (the scenario family's
    tuned setting, ``agents.rules.tuned``: u = 0 is then the best-tuned rule)."""
    twin: bool = False
    """Clipped double Q (TD3, Fujimoto et al. 2018) against over-estimation: a second critic,
    trained on the same target, which takes the smaller of the two target critics' Q at the
    first's best decision. The actor and the acting policy use the first critic (rbp-dqn
    only; False = one critic, as checkpoints before it)."""

    def to_dict(self) -> dict[str, float | int | bool]:
        return asdict(self)


def build_nets(lca: LCAConfig, cfg: LearnerConfig) -> tuple[Actor, Critic]:
    """The (actor, critic) pair of ``cfg.algorithm``: P-DDPG's actor also scores the decisions
    and its critic values the whole action; the others are the paper's networks."""
    joint = cfg.algorithm == "p-ddpg"
    actor = Actor(lca, scores=joint, gate=cfg.hold_gate)
    return actor, Critic(lca, multi_pass=cfg.multi_pass and not joint, joint=joint)


def _soft_update(target: nn.Module, source: nn.Module, tau: float) -> None:
    """target ← (1 − τ)·target + τ·source, in place (one foreach op: same values as a loop)."""
    with torch.no_grad():
        torch._foreach_lerp_(list(target.parameters()), list(source.parameters()), tau)


def _fused_adam(opt: torch.optim.Optimizer) -> None:
    """Use the fused Adam kernel (one op for all parameters instead of ~10 per parameter; same
    update up to rounding). Also after ``load_state_dict``, which restores the saved flags."""
    for group in opt.param_groups:
        group["foreach"], group["fused"] = None, True


class RBPDQN:
    """Actor, critic, their targets and optimisers; :meth:`update` does one gradient step each."""

    def __init__(
        self, lca: LCAConfig, cfg: LearnerConfig | None = None, seed: int = 0, compile: bool = False
    ) -> None:
        """``compile``: run the losses through ``torch.compile`` (see :meth:`_losses`)."""
        self.lca_cfg = lca
        self.cfg = cfg or LearnerConfig()
        # Parameter init is the only randomness in the learner; seed it without touching the
        # caller's global torch RNG.
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.actor, self.critic = build_nets(lca, self.cfg)
            # the twin's own draw (after the first pair's: their weights are unchanged)
            self.critic2 = build_nets(lca, self.cfg)[1] if self.cfg.twin else None
        if self.cfg.residual:  # u = 0 and Q = 0: the teacher bonus picks ACC-LC's decisions
            self.actor.zero_output()
            for critic in self._critics():
                critic.zero_output()
        self.actor_targ = copy.deepcopy(self.actor).requires_grad_(False)
        self.critic_targ = copy.deepcopy(self.critic).requires_grad_(False)
        self.critic2_targ = copy.deepcopy(self.critic2)
        self.actor_opt = torch.optim.Adam(
            self.actor.gradient_parameters(), lr=self.cfg.lr, fused=True
        )
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=self.cfg.lr, fused=True)
        self.critic2_opt = None
        if self.critic2 is not None:
            self.critic2_targ.requires_grad_(False)
            self.critic2_opt = torch.optim.Adam(self.critic2.parameters(), lr=self.cfg.lr,
                                                fused=True)  # fmt: skip
        self.steps = 0
        self.compile = compile
        self._compiled: tuple | None = None

    def _critics(self) -> list[nn.Module]:
        return [self.critic] if self.critic2 is None else [self.critic, self.critic2]

    def td_target(self, batch: dict) -> Tensor:
        """y (B,) = r + γ(1 − done)·max over unmasked next decisions of Q_targ(s', p, u_targ(s')),
        with the batch's per-row ``discount`` as γ where it has one (decision intervals cut
        short by the episode's end span fewer steps). Twin critics: the smaller of the two
        targets' Q at the first's best decision."""
        nxt = batch["next_obs"]
        with torch.no_grad():
            u_next = self.actor_targ(nxt)
            q_next = masked_q(self.critic_targ(nxt, u_next), nxt["action_mask"])
            best, arg = q_next.max(dim=-1)
            if self.critic2_targ is not None:
                q2 = self.critic2_targ(nxt, u_next).gather(1, arg[:, None])[:, 0]
                best = torch.minimum(best, q2)
            # A row with every decision masked has no successor value; treat it as 0 rather
            # than letting -inf poison the loss (the env never emits such a row, DESIGN §6).
            best = torch.where(torch.isfinite(best), best, torch.zeros_like(best))
            gamma = self.cfg.gamma
            if "discount" in batch:  # NaN rows: the learner's γ
                gamma = torch.nan_to_num(batch["discount"], nan=gamma)
            return batch["reward"] + gamma * (1.0 - batch["done"]) * best

    def critic_loss(self, batch: dict) -> Tensor:
        """½·mean (y − Q(s, p_taken, A_taken))² + λ·DQfD margin loss on demonstrations, summed
        over the critics (each has its own parameters, so each gets its own gradient)."""
        y = self.td_target(batch)
        loss = y.new_zeros(())
        for critic in self._critics():
            q_all = critic(batch["obs"], batch["params"])  # (B, 3)
            q = q_all.gather(1, batch["decision"][:, None])[:, 0]
            loss = loss + 0.5 * (y - q).pow(2).mean()
            if self.cfg.demo_weight > 0 and "labelled" in batch:
                loss = loss + self.cfg.demo_weight * self.margin_loss(q_all, batch)
        return loss

    def margin_loss(self, q_all: Tensor, batch: dict) -> Tensor:
        """DQfD (Hester et al. 2018): max_p [Q(s,p) + l·(p ≠ p_E)] − Q(s,p_E) on labelled rows.

        Q of decisions the demonstrator never took is otherwise unconstrained (extrapolation),
        and the argmax then picks them; the margin ranks the demonstrator's decision p_E first.
        Masked decisions are excluded from the max.
        """
        demo = batch["labelled"]
        if float(demo.sum()) == 0:
            return q_all.new_zeros(())
        expert = batch["label_decision"][:, None]
        margin = torch.full_like(q_all, self.cfg.demo_margin)
        margin.scatter_(1, expert, 0.0)
        best = masked_q(q_all + margin, batch["obs"]["action_mask"]).max(dim=1).values
        gap = torch.where(torch.isfinite(best), best - q_all.gather(1, expert)[:, 0], 0.0)
        return (gap * demo).sum() / demo.sum()

    def actor_loss(self, batch: dict) -> Tensor:
        """RBP-DQN: −Σ_p α·Q(s,p,u_p)/AvgQ + Σ_p w·(u_p − a_p)²; BP-DQN: −Σ_p Q (batch mean).

        a_p: the expert label (``label_params``) when the batch has one, else the taken params.
        """
        obs = batch["obs"]
        u = self.actor(obs)  # (B, 3, 2)
        q = self.critic(obs, u)  # (B, 3)
        if not self.cfg.regularize:
            return -q.sum(dim=1).mean()
        avg_q = q.abs().mean().detach() + self.cfg.avgq_eps
        w = u.new_tensor([self.cfg.bc_steer_weight, self.cfg.bc_accel_weight])
        target = batch.get("label_params", batch["params"])
        err = u - target  # (B, 3, 2)
        tau = self.cfg.bc_accel_expectile
        side = torch.where(err[..., 1:] < 0, 2 * tau, 2 * (1 - tau))  # (B, 3, 1), accel only
        bc = (err.pow(2) * w * torch.cat((torch.ones_like(side), side), dim=-1)).sum(dim=(1, 2))
        return (-(self.cfg.alpha / avg_q) * q.sum(dim=1) + bc).mean()

    def update(self, batch: dict) -> dict[str, float]:
        """One critic step, one actor step (critic frozen), soft target update. → losses."""
        critic_loss, actor_loss = self._losses()
        c_loss = critic_loss(batch)
        c_norm = self._step(c_loss, self.critic, self.critic_opt)
        if self.critic2 is not None:  # its gradient came with the first's backward
            self._clip_and_step(self.critic2, self.critic2_opt)
            _soft_update(self.critic2_targ, self.critic2, self.cfg.tau)
        # Freeze the critic so the actor loss does not build critic parameter gradients.
        self.critic.requires_grad_(False)
        try:
            a_loss = actor_loss(batch)
            a_norm = self._step(a_loss, self.actor, self.actor_opt)
        finally:
            self.critic.requires_grad_(True)
        _soft_update(self.critic_targ, self.critic, self.cfg.tau)
        _soft_update(self.actor_targ, self.actor, self.cfg.tau)
        self.steps += 1
        return {
            "critic_loss": float(c_loss.detach()),
            "actor_loss": float(a_loss.detach()),
            "critic_grad_norm": float(c_norm),
            "actor_grad_norm": float(a_norm),
        }

    def _losses(self) -> tuple:
        """(critic_loss, actor_loss), compiled on first use with ``compile``: inductor fuses
        each GRU step's elementwise ops (and their backward) into one kernel, ~1.6x the eager
        updates/s, after a one-off compile (~40-60 s; seconds with a warm inductor cache;
        changing ``cfg`` values recompiles once per new value)."""
        if not self.compile:
            return self.critic_loss, self.actor_loss
        if self._compiled is None:
            self._compiled = (torch.compile(self.critic_loss), torch.compile(self.actor_loss))
        return self._compiled

    def _step(self, loss: Tensor, net: nn.Module, opt: torch.optim.Optimizer) -> Tensor:
        """Backward, clip to ``grad_clip``, optimiser step. → gradient norm before clipping."""
        opt.zero_grad(set_to_none=True)
        loss.backward()
        return self._clip_and_step(net, opt)

    def _clip_and_step(self, net: nn.Module, opt: torch.optim.Optimizer) -> Tensor:
        norm = nn.utils.clip_grad_norm_(net.parameters(), self.cfg.grad_clip, foreach=True)
        opt.step()
        opt.zero_grad(set_to_none=True)
        return norm

    def state_dict(self) -> dict:
        """Tensors and plain values only (loadable with ``torch.load(weights_only=True)``)."""
        return {
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "actor_targ": self.actor_targ.state_dict(),
            "critic_targ": self.critic_targ.state_dict(),
            "actor_opt": self.actor_opt.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "steps": self.steps,
            **self._twin_state(),
        }

    def _twin_state(self) -> dict:
        if self.critic2 is None:
            return {}
        return {"critic2": self.critic2.state_dict(), "critic2_targ": self.critic2_targ.state_dict(),
                "critic2_opt": self.critic2_opt.state_dict()}  # fmt: skip

    def load_state_dict(self, sd: dict) -> None:
        self.actor.load_state_dict(sd["actor"])
        self.critic.load_state_dict(sd["critic"])
        self.actor_targ.load_state_dict(sd["actor_targ"])
        self.critic_targ.load_state_dict(sd["critic_targ"])
        self.actor_opt.load_state_dict(sd["actor_opt"])
        self.critic_opt.load_state_dict(sd["critic_opt"])
        if self.critic2 is not None and "critic2" in sd:  # else (one-critic weights) its own init
            self.critic2.load_state_dict(sd["critic2"])
            self.critic2_targ.load_state_dict(sd["critic2_targ"])
            self.critic2_opt.load_state_dict(sd["critic2_opt"])
            _fused_adam(self.critic2_opt)
        self.set_lr(self.cfg.lr)  # the config's rate, not the saved one
        _fused_adam(self.actor_opt)
        _fused_adam(self.critic_opt)
        self.steps = int(sd["steps"])

    def set_lr(self, lr: float) -> None:
        """Learning rate of both optimisers from the next update on [-]."""
        for opt in filter(None, (self.actor_opt, self.critic_opt, self.critic2_opt)):
            for group in opt.param_groups:
                group["lr"] = lr


OBS_KEYS = ("ego", "lanes", "vehicles", "lights", "node_mask", "action_mask")
#: Steering ±1 is ±60°, so the same noise as on accel_brake (±1 = +3/−6 m/s²) would swerve the
#: car off the road within a second; lane keeping needs about a degree of steering.
STEER_NOISE_FACTOR = 0.05


def obs_to_torch(obs: dict[str, np.ndarray]) -> dict[str, Tensor]:
    """numpy (A, ...) → float32 tensors, zero-copy when already float32 and contiguous (the
    network's keys, its ``EXTRA`` vector and the hold gate's ``LEAD_SPREAD`` where given)."""
    keys = (*OBS_KEYS, *(k for k in (EXTRA, LEAD_SPREAD) if k in obs))
    return {k: torch.from_numpy(np.ascontiguousarray(obs[k], dtype=np.float32)) for k in keys}


class Policy:
    """Batched inference for all agents of a step: one forward of actor + critic + selection.

    Uses the fused path (:mod:`agents.nets.fused`) for the default LCA and the reference modules for
    ablations. Holds a snapshot of the weights: call :meth:`sync` after the learner updates.
    """

    def __init__(
        self,
        actor: Actor,
        critic: Critic,
        noise_std: float = 0.1,
        epsilon: float = 0.05,
        threads: int | None = None,
        fused: bool = True,
        steer_noise_factor: float = STEER_NOISE_FACTOR,
        extra_keys: tuple[str, ...] = EXTRA_KEYS,
    ) -> None:
        """``steer_noise_factor``: the steering column's share of ``noise_std`` [-] (1 in the
        residual form, whose steering bound already scales it). ``extra_keys``: the opt-in
        observation keys the networks were trained on; others the env gives are ignored."""
        if threads is not None:
            torch.set_num_threads(threads)  # rollout workers: one core each, no oversubscription
        self.actor, self.critic = actor, critic
        self.noise_std = noise_std
        self.steer_noise_factor = steer_noise_factor
        self.epsilon = epsilon
        c = getattr(actor.lca, "cfg", None)
        default = c is not None and c.history and c.lane_wise and c.star and c.encoder == "lca"
        self._fused = (
            FusedActorCritic(actor, critic) if fused and default and not actor.scores else None
        )
        self.extra = getattr(c, "extra", 0)
        """X: width of the ``EXTRA`` vector the networks read (0: none)."""
        self.extra_keys = extra_keys if self.extra else ()

    def sync(self) -> None:
        """Re-snapshot weights after the networks were updated or loaded."""
        if self._fused is not None:
            self._fused.refresh()

    @torch.inference_mode()
    def q_and_params(
        self, obs: dict[str, Tensor], noise: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        """→ (q (A, 3), params (A, 3, 2), hold score (A,) or None without a gate): the
        actor's output plus ``noise`` (A, 3, 2) if given, clipped to [-1, 1], and the
        critic's Q of exactly those params."""
        if self._fused is not None:
            params, q, hold = self._fused(obs, noise=noise)
            return q, params, hold
        params, hold = self.actor.with_hold(obs)
        if self.actor.scores:  # P-DDPG: the actor's scores rank the decisions
            scores, params = params[..., 2], params[..., :2].contiguous()
        if noise is not None:
            params = (params + noise).clamp_(-1.0, 1.0)
        q = scores if self.actor.scores else self.critic(obs, params)
        return q, params, hold

    def act(
        self,
        obs: dict[str, np.ndarray],
        explore: bool,
        rng: np.random.Generator | None = None,
        bonus: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """obs numpy (A, ...) → (decision (A,) int64, params (A, 3, 2) float32 in [-1, 1]);
        :meth:`choose` without the hold gate's answer."""
        choice = self.choose(obs, explore, rng, bonus)
        return choice.decision, choice.params

    def choose(
        self,
        obs: dict[str, np.ndarray],
        explore: bool,
        rng: np.random.Generator | None = None,
        bonus: np.ndarray | None = None,
        noise: np.ndarray | None = None,
    ) -> Choice:
        """obs numpy (A, ...) → :class:`Choice`.

        ``bonus`` (A, 3), if given, is added to Q before the masked argmax. Exploration:
        Gaussian noise (``noise`` (A, 3, 2) if given, else :meth:`draw_noise`) on all params,
        clipped to [-1, 1], and the critic scores the *noisy* params (they are what gets
        executed and stored); then with probability ``epsilon`` a uniformly random unmasked
        decision replaces the argmax. The gate is never explored.
        """
        # opt-in keys the networks were not trained on are ignored
        obs = for_policy(obs, self.extra_keys)
        self.check_extra(obs)
        t = obs_to_torch(obs)
        mask = t["action_mask"] > 0.5
        if explore:
            if rng is None:
                raise ValueError("explore=True needs an rng")
            noise = self.draw_noise(rng, len(mask)) if noise is None else noise
        noise = torch.from_numpy(noise) if explore else None
        q, params, score = self.q_and_params(t, noise)
        if bonus is not None:
            q = q + torch.from_numpy(np.asarray(bonus, np.float32))
        dec = select(q, mask).numpy().copy()
        if explore:
            dec = explore_decisions(dec, mask.numpy(), self.epsilon, rng)
        hold = np.zeros(len(dec), bool) if score is None else (score > 0).numpy()
        return Choice(dec, params.numpy().copy(), hold)

    def check_extra(self, obs: dict[str, np.ndarray]) -> None:
        """ValueError unless ``obs`` holds the ``EXTRA`` vector the networks were trained on
        (a policy trained without opt-in keys gets none: :meth:`choose` drops them)."""
        got = np.shape(obs[EXTRA])[-1] if EXTRA in obs else 0
        if got != self.extra:
            raise ValueError(f"the policy reads {self.extra} opt-in observation features "
                             f"(sensors.memory: 12, v2x: 3 segments x 2), the env gives {got}: "
                             "run the env with the keys it was trained with")  # fmt: skip

    def draw_noise(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """(n, 3, 2) float32 Gaussian noise: std ``noise_std``, times ``steer_noise_factor`` for
        the steering column."""
        std = self.noise_std * np.array([self.steer_noise_factor, 1.0], np.float32)
        return gaussian(rng, n, std)


class Choice(NamedTuple):
    """What :meth:`Policy.choose` decided for A agents."""

    decision: np.ndarray
    """(A,) int64 decision."""
    params: np.ndarray
    """(A, 3, 2) float32 parameters in [-1, 1]."""
    hold: np.ndarray
    """(A,) bool: the hold gate is open (always False without a gate)."""


def gaussian(rng: np.random.Generator, n: int, std: np.ndarray) -> np.ndarray:
    """(n, 3, 2) float32 Gaussian noise with ``std`` per parameter column (2,)."""
    return (rng.normal(0.0, 1.0, size=(n, 3, 2)) * std).astype(np.float32)


def explore_decisions(
    dec: np.ndarray, mask: np.ndarray, epsilon: float, rng: np.random.Generator
) -> np.ndarray:
    """``dec`` (A,) with each row replaced, with probability ``epsilon``, by a uniformly random
    allowed decision of ``mask`` (A, 3) (in place; FOLLOW if none is allowed)."""
    rand_rows = rng.random(len(dec)) < epsilon
    for i in np.flatnonzero(rand_rows):  # ε rows only: a short loop
        ok = np.flatnonzero(mask[i])
        dec[i] = rng.choice(ok) if len(ok) else FOLLOW
    return dec
