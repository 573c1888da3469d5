"""AUTO's driver: the network decides every k simulation steps and the command is held between.

Decision interval (issue 22): ``LearnerConfig.decision_interval`` [s] is rounded to
k = max(1, round(interval / step_length)) steps of the scenario. An agent decides when it
enters and then every k steps; in between its decision and the network's output u are held.
A held lane change becomes ``follow`` once the lane switch happened (the ego's lateral offset
jumps by more than ``SWITCH_JUMP``: it is now measured from the new lane), and a held decision
the mask forbids now becomes the teacher's (the residual form) or ``follow``.

Two forms (``LearnerConfig.residual``):

- paper: u is the parameters themselves; held for k steps they are the executed command.
- residual: u is a bounded correction to ACC-LC (``agents.rules.acc_lc``), which is evaluated
  on every step's observation: params = clip(ACC-LC's params + (steer_delta, accel_delta)·u,
  -1, 1); with ``speed_governor`` the accel_brake correction lifts no row above what the speed
  limits, curves and traffic lights ahead allow (ACC-LC's ``speed_cap``), and with
  ``rss_governor`` none above the RSS-safe acceleration behind that row's leaders
  (``agents.rules.rss``). ACC-LC is the
  low-level controller that tracks the held command: it keeps the lane centre, keeps the gap
  and only shifts towards a changed lane while its gap checks accept it.
  The decision is the critic's masked argmax of Q + ``teacher_bonus`` on ACC-LC's decision.
  With a hold gate (``hold_gate``) that is open at a decision, the follow row holds speed
  until the next decision (:func:`held_accel`): it tracks a reference speed, the exponential
  mean over ``hold_tau`` of its leader's speed (kept for every agent on every step), and
  brakes only for what ACC-LC brakes beyond ``hold_brake``; the governors still bound it.
  Without a leader, or with a signal or give-way line in view, ACC-LC drives.

Modes of :meth:`Driver.act`: ``greedy`` (evaluation), ``explore`` (Gaussian noise on u and
ε-random decisions; needs an rng) and ``teacher`` (ACC-LC drives: u = 0 in the residual form,
ACC-LC's parameters in the paper's). An agent's noise is held for ``noise_hold`` decisions
(1: a fresh draw at each), so that an exploring AV drives one perturbed policy long enough for
its effect on the traffic (a wave forming or damped) to show in the return.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np

from agents.learners.rbpdqn import LearnerConfig, Policy
from agents.nets.networks import FOLLOW, LEAD_SPREAD
from agents.rules.acc_lc import AccLcPlan, AccLcPolicy
from agents.rules.acc_lc_config import LANE_C
from agents.rules.acc_lc_longitudinal import from_ab, to_ab
from agents.rules.rss import RssConfig
from mixed_traffic.env.api import EGO_SCALE

MODES = ("greedy", "explore", "teacher")
SWITCH_JUMP = 1.5
"""Jump of the ego's lateral offset between two frames that marks a lane switch [m]."""


class Command(NamedTuple):
    """What :meth:`Driver.act` decided for A agents."""

    decision: np.ndarray
    """(A,) int64 executed decision."""
    params: np.ndarray
    """(A, 3, 2) float32 executed (steering, accel_brake) of every decision."""
    due: np.ndarray
    """(A,) bool: the agent decided at this step (a transition starts)."""
    u: np.ndarray
    """(A, 3, 2) float32 network output being held (the stored action of a transition)."""
    hold: np.ndarray
    """(A,) bool: the hold gate is open (the follow row holds speed)."""
    teacher_decision: np.ndarray
    """(A,) int64 ACC-LC's decision (FOLLOW where ACC-LC was not evaluated)."""
    teacher_params: np.ndarray
    """(A, 3, 2) float32 ACC-LC's parameters (zeros where not evaluated)."""


class Lead(NamedTuple):
    """What the hold tracks of each agent's leader (:meth:`Driver._track`)."""

    ref: np.ndarray
    """(A,) reference speed [m/s]: the leader's speed, averaged over ``hold_tau``."""
    free: np.ndarray
    """(A,) bool: the hold may act (a leader seen, no signal or give-way line in view)."""
    spread: np.ndarray
    """(A,) float32 the leader's speed spread about ``ref`` over ``hold_tau``, divided by ``ref``
    (at least 1 m/s) [-]: the gate's ``LEAD_SPREAD``."""


def steps_per_decision(interval: float, step_length: float) -> int:
    """k: the decision interval [s] in whole simulation steps of ``step_length`` [s], >= 1."""
    return max(1, round(interval / step_length))


def track_leader(ref: np.ndarray, var: np.ndarray, v: np.ndarray, v_lead: np.ndarray,
                 lead: np.ndarray, alpha: float) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(A,) reference speeds [m/s] and the leader's speed variance about them [m²/s²] one step
    on. ``ref`` (NaN: a new agent, which starts at its own speed ``v`` and variance 0) moves by
    ``alpha`` (step / τ) towards the leader's speed ``v_lead`` where a leader is seen
    (``lead``), the variance towards the squared deviation; both stay where none is."""
    new = np.isnan(ref)
    ref, var = np.where(new, v, ref), np.where(new, 0.0, var)
    ref = np.where(lead, ref + alpha * (v_lead - ref), ref)
    var = np.where(lead, var + alpha * ((v_lead - ref) ** 2 - var), var)
    return ref, var


def held_accel(a: np.ndarray, v: np.ndarray, ref: np.ndarray, free: np.ndarray, gain: float,
               brake: float) -> np.ndarray:  # fmt: skip
    """(A,) acceleration [m/s²] of a held follow row: ``gain`` (ref − v) towards the reference
    speed, but never above ACC-LC's a + ``brake`` (ACC-LC's braking beyond ``brake`` passes);
    ACC-LC's a where the hold may not act (``free`` False: no leader seen, or a signal in
    view)."""
    return np.where(free, np.minimum(gain * (ref - v), a + brake), a)


def lane_switched(ego: np.ndarray) -> np.ndarray:
    """(A,) bool: the ego's lateral offset jumped between the last two frames of ``ego``
    (A, z, 5) (a lane switch), False with a single frame or an unobserved previous one."""
    if ego.shape[1] < 2:
        return np.zeros(len(ego), bool)
    d = ego[:, -2:, 4] * EGO_SCALE[4]
    seen = ego[:, -2, 2] > 0
    return seen & (np.abs(d[:, 1] - d[:, 0]) > SWITCH_JUMP)


class Driver:
    """Batched decisions for the agents of one env step, with the hold between decisions."""

    def __init__(self, policy: Policy | None, cfg: LearnerConfig, step_length: float,
                 teacher: AccLcPolicy | None = None, noise_hold: int = 1) -> None:  # fmt: skip
        """``policy`` may be None for teacher-only driving; ``teacher`` defaults to ACC-LC;
        ``noise_hold``: decisions an exploration draw is held [-]."""
        if noise_hold < 1:
            raise ValueError(f"noise_hold={noise_hold} must be >= 1 decision")
        self.policy, self.cfg, self.noise_hold = policy, cfg, noise_hold
        self.k = steps_per_decision(cfg.decision_interval, step_length)
        self.teacher = teacher if teacher is not None else AccLcPolicy(dt=step_length)
        # HEAD and the set-speed form: ACC-LC steers
        steer = cfg.steer_delta if cfg.steer_control and not cfg.set_speed else 0.0
        self.delta = np.array([steer, cfg.accel_delta], np.float32)
        self.rss = RssConfig()
        self.cap_factor = 1.0
        """The speed governor's cap as a share of the limit (that of the ACC-LC compared with)."""
        self.plan: AccLcPlan | None = None
        """ACC-LC's plan of the last :meth:`act` (None where ACC-LC was not evaluated)."""
        # per agent: [steps left, held decision, held u (3, 2), hold gate open]
        self._held: dict[str, list] = {}
        # per exploring agent: [decisions left, held noise (3, 2)]
        self._noise: dict[str, list] = {}
        self.fixed_u: np.ndarray | None = None
        """(3, 2) u that replaces the network's at every decision (``auto-mean``; None: the
        network's own)."""
        # the network's u at its decisions: sum, sum of squares, count
        self._u_sum, self._u_sq, self._u_count = np.zeros((3, 2)), np.zeros((3, 2)), 0
        # per agent: the hold's reference speed [m/s] and the leader's variance about it
        self._ref: dict[str, tuple[float, float]] = {}
        self._alpha = min(1.0, step_length / cfg.hold_tau)
        self._steps = self._holds = 0  # agent-steps driven, and of them with the gate open

    @property
    def u_mean(self) -> np.ndarray | None:
        """(3, 2) mean of the network's u over its decisions so far (None before any)."""
        return self._u_sum / self._u_count if self._u_count else None

    @property
    def u_std(self) -> np.ndarray | None:
        """(3, 2) spread of the network's u over its decisions so far (None before any): 0
        for a policy whose parameters do not depend on the state."""
        if not self._u_count:
            return None
        mean = self._u_sum / self._u_count
        return np.sqrt(np.maximum(self._u_sq / self._u_count - mean**2, 0.0))

    @property
    def u_decisions(self) -> int:
        """Decisions the network took so far (the count behind :attr:`u_mean`)."""
        return self._u_count

    @property
    def hold_share(self) -> float | None:
        """Share of the agent-steps driven so far with the hold gate open [%] (None before
        any)."""
        return 100.0 * self._holds / self._steps if self._steps else None

    def act(self, obs: Mapping[str, np.ndarray], agents: Sequence[str], mode: str = "greedy",
            rng: np.random.Generator | None = None, labels: bool = False) -> Command:  # fmt: skip
        """Stacked observations (A, ...) of ``agents`` → :class:`Command`. ``labels``: also
        evaluate ACC-LC in the paper's form (its action labels the transitions)."""
        if mode not in MODES:
            raise ValueError(f"Driver mode {mode!r} is not one of {MODES}")
        if mode == "explore" and rng is None:
            raise ValueError("Driver mode 'explore' needs an rng")
        agents = list(agents)
        n = len(agents)
        self._forget(agents)
        mask = np.asarray(obs["action_mask"]) > 0.5
        with_teacher = self.cfg.residual or labels or mode == "teacher"
        self.plan = None
        t_dec, t_par, cap = self._teacher(obs, n) if with_teacher else _no_teacher(n)
        tracks = self.cfg.hold_gate or self.cfg.set_speed
        lead = self._track(agents) if tracks and self.plan is not None else None
        due = np.array([self._held.get(a, (0,))[0] <= 0 for a in agents], bool)
        if due.any():
            spread = None if lead is None else lead.spread
            self._decide(obs, agents, np.flatnonzero(due), t_dec, t_par, mode, rng, spread)
        decision, u, hold = self._hold(agents, obs, mask, t_dec)
        self._steps += n
        self._holds += int(hold.sum())
        held = None if lead is None or not self.cfg.hold_gate else self._held_ab(t_par, hold, lead)
        params = self._execute(u, t_par, cap, held)
        if lead is not None and self.cfg.set_speed:
            params[:, FOLLOW, 1] = self._set_speed_ab(params[:, FOLLOW, 1], u, lead)
        return Command(decision, params, due, u, hold, t_dec, t_par)

    # ------------------------------------------------------------------ steps of act()
    def _forget(self, agents: list[str]) -> None:
        """Drop the hold of agents that are gone (ended trips; a new episode)."""
        if len(self._held) > len(agents) or any(a not in self._held for a in agents):
            live = set(agents)
            self._held = {a: h for a, h in self._held.items() if a in live}
            self._noise = {a: h for a, h in self._noise.items() if a in live}

    def _teacher(self, obs: Mapping[str, np.ndarray], n: int) -> tuple[np.ndarray, ...]:
        """ACC-LC's (decision (A,), params (A, 3, 2), the governors' accel_brake cap (A, 3))."""
        if n == 0:
            return _no_teacher(0)
        self.plan = plan = self.teacher.plan(obs)
        c = self.teacher.c
        cap = np.ones((n, 3))
        if self.cfg.residual and self.cfg.speed_governor:
            cap = np.minimum(cap, to_ab(plan.speed_cap(self.cap_factor), c)[:, None])
        if self.cfg.residual and self.cfg.rss_governor:
            cap = np.minimum(cap, to_ab(plan.rss_caps(self.rss), c))
        return plan.decision.astype(np.int64), plan.params.astype(np.float32), cap

    def _track(self, agents: list[str]) -> Lead:
        """Moves every agent's reference speed and the leader's variance one step on."""
        f = self.plan.features
        lead = f["present"][:, LANE_C, 0]
        v_lead = f["v"] + np.where(lead, f["vrel"][:, LANE_C, 0], 0.0)
        old = np.array([self._ref.get(a, (np.nan, 0.0)) for a in agents]).reshape(-1, 2)
        ref, var = track_leader(old[:, 0], old[:, 1], f["v"], v_lead, lead, self._alpha)
        # a signal or give-way line in view: ACC-LC stops for it, and the hold restarts from
        # the leader's speed beyond it (a held AV ran a red light, and lagged at green)
        signal = np.isfinite(f["light_dist"][:, LANE_C])
        ref = np.where(signal & lead, v_lead, ref)
        self._ref = dict(zip(agents, zip(ref.tolist(), var.tolist())))  # forgets the gone
        spread = np.sqrt(var) / np.maximum(ref, 1.0)
        return Lead(ref, lead & ~signal, spread.astype(np.float32))

    def _held_ab(self, t_par: np.ndarray, hold: np.ndarray, lead: Lead) -> np.ndarray:
        """(A,) the follow row's accel_brake of the agents that ``hold``, NaN for the others."""
        c, cfg = self.teacher.c, self.cfg
        a = held_accel(from_ab(t_par[:, FOLLOW, 1], c), self.plan.features["v"], lead.ref,
                       lead.free, cfg.hold_gain, cfg.hold_brake)  # fmt: skip
        return np.where(hold, to_ab(a, c), np.nan)

    def _set_speed_ab(self, ab: np.ndarray, u: np.ndarray, lead: Lead) -> np.ndarray:
        """(A,) the follow row's accel_brake ``ab`` bounded by the tracking of the set speed
        that u's follow row sets (``LearnerConfig.set_speed``), where the leader is tracked."""
        c, cfg = self.teacher.c, self.cfg
        v_set = lead.ref + cfg.set_speed_span * (1.0 + u[:, FOLLOW, 0])
        track = to_ab(cfg.hold_gain * (v_set - self.plan.features["v"]), c)
        return np.where(lead.free, np.minimum(ab, track), ab).astype(np.float32)

    def _decide(self, obs: Mapping[str, np.ndarray], agents: list[str], idx: np.ndarray,
                t_dec: np.ndarray, t_par: np.ndarray, mode: str,
                rng: np.random.Generator | None,
                spread: np.ndarray | None = None) -> None:  # fmt: skip
        """New decisions and u of the agents at ``idx``, held for k steps from now
        (``spread`` (A,): the hold gate's ``LEAD_SPREAD``)."""
        residual = self.cfg.residual
        hold = np.zeros(len(idx), bool)
        if mode == "teacher":
            dec = t_dec[idx]
            u = np.zeros((len(idx), 3, 2), np.float32) if residual else t_par[idx]
        else:
            if self.policy is None:
                raise ValueError("this Driver has no network: only mode='teacher' can drive")
            bonus = None
            if residual and self.cfg.teacher_bonus:
                bonus = np.zeros((len(idx), 3), np.float32)
                bonus[np.arange(len(idx)), t_dec[idx]] = self.cfg.teacher_bonus
            sub = {k: np.asarray(v)[idx] for k, v in obs.items()}
            if spread is not None:
                sub[LEAD_SPREAD] = spread[idx]
            noise = (
                self._held_noise([agents[i] for i in idx.tolist()], rng)
                if mode == "explore"
                else None
            )
            dec, u, hold = self.policy.choose(sub, mode == "explore", rng, bonus, noise)
            self._u_sum += u.sum(axis=0)
            self._u_sq += np.square(u, dtype=np.float64).sum(axis=0)
            self._u_count += len(u)
            if self.fixed_u is not None:
                u = np.broadcast_to(self.fixed_u, u.shape).astype(np.float32)
        hold &= residual
        for j, i in enumerate(idx.tolist()):
            self._held[agents[i]] = [self.k, int(dec[j]), u[j], bool(hold[j])]

    def _held_noise(self, names: list[str], rng: np.random.Generator) -> np.ndarray:
        """(D, 3, 2) exploration noise of the deciding agents ``names``: a fresh draw for each
        (the rng's stream does not depend on the holds), kept where an agent's is still held."""
        fresh = self.policy.draw_noise(rng, len(names))
        for j, a in enumerate(names):
            h = self._noise.get(a)
            if h is None or h[0] <= 0:
                h = self._noise[a] = [self.noise_hold, fresh[j].copy()]
            fresh[j] = h[1]
            h[0] -= 1
        return fresh

    def _hold(self, agents: list[str], obs: Mapping[str, np.ndarray], mask: np.ndarray,
              t_dec: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
        """(decision (A,), u (A, 3, 2), hold (A,)) held by every agent; counts the step down."""
        n = len(agents)
        held = [self._held[a] for a in agents]
        decision = np.fromiter((h[1] for h in held), np.int64, n)
        hold = np.fromiter((h[3] for h in held), bool, n)
        u = np.stack([h[2] for h in held]) if n else np.zeros((0, 3, 2), np.float32)
        switched = lane_switched(np.asarray(obs["ego"])) & (decision != FOLLOW)
        fallback = t_dec if self.cfg.residual else np.full(n, FOLLOW, np.int64)
        decision = np.where(switched, FOLLOW, decision)
        forbidden = ~mask[np.arange(n), decision] if n else np.zeros(0, bool)
        decision = np.where(forbidden, fallback, decision)
        for h, d in zip(held, decision.tolist()):
            h[0] -= 1
            h[1] = d
        return decision, u.astype(np.float32), hold

    def _execute(self, u: np.ndarray, t_par: np.ndarray, cap: np.ndarray,
                 held: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
        """(A, 3, 2) executed parameters of the held u; ``held`` (A,) replaces the follow row's
        accel_brake where it is not NaN (None: nowhere); the accel_brake lifts no row above
        ``cap`` (A, 3) unless ACC-LC's own is higher."""
        if not self.cfg.residual:
            return u
        out = np.clip(t_par + self.delta * u, -1.0, 1.0)
        if held is not None:
            out[:, FOLLOW, 1] = np.where(np.isnan(held), out[:, FOLLOW, 1], held)
        ceiling = np.maximum(t_par[:, :, 1], cap)
        out[:, :, 1] = np.minimum(out[:, :, 1], ceiling)
        return out.astype(np.float32)


def _no_teacher(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.full(n, FOLLOW, np.int64), np.zeros((n, 3, 2), np.float32), np.ones((n, 3))
