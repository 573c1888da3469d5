"""Training run settings (:class:`TrainConfig`) and the env / encoder configs derived from them.

``python -m mixed_traffic.train`` builds its options from the fields of :class:`TrainConfig` (their
docstrings carry the units); :class:`agents.training.trainer.Trainer` runs one.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import Any, NoReturn

from agents.nets.lca import LCAConfig
from agents.rules.obs_batch import extra_width
from agents.rules.tuned import TEACHERS
from mixed_traffic.config import MAX_COPIES, WEATHERS, EnvConfig
from mixed_traffic.env.api import observation_space

BACKENDS = ("process", "ray")
RESIDUAL_BC_ACCEL = 0.05
"""Default weight of ‖u_accel‖² in the residual form's behaviour-cloning term [-]."""
ABLATIONS = ("none", "nohis", "nolane", "nostar", "noimp", "nomul", "novec")
BASELINES = ("none", "transfuser", "drl-mf", "head", "p-ddpg", "q-pamdp")
"""Paper §V-A methods other than RBP-DQN and BP-DQN (``--bp-dqn``); docs/studies.md."""
PAPER_FORM = ("transfuser", "drl-mf")
"""Baselines that output the parameters themselves: neither sees the map ACC-LC needs."""


@dataclass(frozen=True)
class TrainConfig:
    """Training run settings; ``python -m mixed_traffic.train`` builds its options from these."""

    workers: int = 2
    """Rollout worker processes N (1 = in-process, synchronous, deterministic)."""
    backend: str = "process"
    """Worker transport: process (multiprocessing spawn) | ray (Ray core actors)."""
    address: str = ""
    """Ray cluster address for ray.init(address=...), e.g. 'auto' or 'host:6379' ('' = local)."""
    scenarios: tuple[str, ...] = ()
    """Training scenarios sampled per episode ('' = every train-split scenario)."""
    densities: tuple[float, ...] = (60.0, 120.0, 180.0, 0.0)
    """Traffic densities sampled per episode [veh/km]; 0 = the scenario's own default (85 on
    the rings, 30 on the urban grid). Each episode samples among those its scenario can hold
    (the rings' one lane jams at 143 veh/km)."""
    penetrations: tuple[float, ...] = (0.2, 0.5, 1.0)
    """AV penetration rates sampled per episode [0-1]."""
    weathers: tuple[str, ...] = WEATHERS
    """Weather presets sampled per episode."""
    episode_length: float = 120.0
    """Simulated time per training episode [s]."""
    env_steps: int = 0
    """Budget: total transitions (AV actions) over the run including resumed parts (0 = none)."""
    minutes: float = 0.0
    """Budget: wall time of this invocation [min] (0 = none). At least one budget is needed."""
    seed: int = 0
    """Root seed: learner init, replay sampling, per-worker episode configs and exploration."""
    out: str = "runs/auto"
    """Output directory (checkpoints, curves, final auto.pt/auto.json)."""
    demo_steps: int = 20000
    """Transitions first driven by the demonstrator (ACC-LC) to seed the replay (0 = off)."""
    demo_share: float = 0.05
    """Probability that a later episode is also driven by the demonstrator [0-1]."""
    pretrain_updates: int = 0
    """Learner updates on the demonstrations alone, as soon as the demonstration phase ends
    (all ``demo_steps`` arrived, or a worker switched to its own policy), before the learned
    weights are published (0 = none)."""
    demo_policy: str = "acc-lc"
    """Demonstrator policy name for agents.policies.make_policy; with --residual also the rule
    that u corrects (``LearnerConfig.teacher``): acc-lc | acc-lc-tuned."""
    expert_labels: bool = True
    """Label every transition the learning policy drives with the demonstrator's action for
    the same observation; behaviour cloning and the DQfD margin then target it (DAgger-style
    deviation from the paper, see agents.learners.rbpdqn; off = BC on the taken action)."""
    residual: bool = True
    """Train the residual form (``LearnerConfig.residual``): the actor learns a bounded
    correction to ACC-LC, starting from zero; False = the paper's form (the actor outputs the
    parameters)."""
    copies: int = 8
    """Copies of each episode's scenario in one simulation (batched worlds: a step's fixed
    costs buy N times the transitions); scenarios that cannot be copied (urban, user
    networks) run one. 1 = one world per episode."""
    decision_interval: float = 0.5
    """Time between the policy's decisions [s], rounded to whole simulation steps; the command
    is held in between (``agents.driver``; 0.1 = the paper's one decision per step)."""
    speed_governor: bool = True
    """Residual form: the accel correction may not lift the acceleration above what the speed
    limit, the curves and the traffic lights ahead allow (``LearnerConfig.speed_governor``);
    without it, eager corrections ended AV trips for speeding before junctions and lower
    limits (docs/agent.md)."""
    rss_governor: bool = True
    """Residual form: the accel correction may not lift a row's acceleration above the
    RSS-safe one behind that lane's leaders (``LearnerConfig.rss_governor``), so the safety
    module need not cap it (docs/agent.md)."""
    multi_pass: bool = True
    """MP-DQN critic: each decision's Q sees only its own parameters, so the actor's update of
    one row is not pushed by the other decisions' Q (``LearnerConfig.multi_pass``; False = the
    paper's P-DQN critic)."""
    horizon: float = 10.0
    """Effective horizon 1/(1 - γ) of the discount [s]: γ per decision = 1 - decision_interval
    / horizon (0.95 at 0.5 s; the paper's γ = 0.9 per 0.1 s step is a 1 s horizon)."""
    n_step: int = 1
    """Decisions per stored transition [-]: n-step returns bootstrap n decisions ahead, so a
    reward reaches the values of earlier decisions n times faster
    (:mod:`agents.collection.intervals`); 1 = one-step, as runs before it."""
    set_speed: bool = False
    """Residual form with a set speed (``LearnerConfig.set_speed``): the follow row's first
    parameter sets a speed between the leader's 40 s mean (u = -1, FollowerStopper-like
    damping) and 5 m/s above it, which the row tracks unless ACC-LC brakes harder."""
    memory: bool = False
    """The policy reads the env's ``memory`` key (slow means and spreads of its own and its
    leader's speed, its last command: ``SensorConfig.memory``) in its fusion layer."""
    v2x: bool = False
    """The policy reads the env's ``downstream`` key (the V2X feed, ``EnvConfig.v2x``) in its
    fusion layer."""
    twin: bool = False
    """Twin critics against over-estimation (clipped double Q, ``LearnerConfig.twin``;
    rbp-dqn and its ablations only)."""
    steer_delta: float = 0.005
    """Residual form: largest steering correction [action units; 0.005 = 0.3°]. Held for a
    0.5 s decision at 30 m/s, 0.05 (3°) moved a car up to 2 m sideways: exploration noise on it
    collided 24 times in 176 AV trips on straight-4lane, none at 0.005 (docs/agent.md)."""
    accel_delta: float = 0.25
    """Residual form: largest accel_brake correction [action units; 0.25 = +0.75/-1.5 m/s²]."""
    teacher_bonus: float = 0.02
    """Residual form: Q bonus of ACC-LC's decision when the policy selects one [Q units, about
    the mean scaled reward per step]."""
    reward_scale: float = 0.0
    """Factor on the stored rewards [-] (0 = 1 - γ per simulation step: Q is then about the
    mean reward per step)."""
    impact_weight: float = 2.0
    """w4, weight of the impact term r4 in the training episodes' reward [-] (the paper's 0.2
    made r4 0.4 % of the reward's magnitude under ACC-LC; 2.0 makes it about 5 %, docs/agent.md).
    The NoIMP ablation sets it to 0."""
    fleet_weights: tuple[float, ...] = (0.0, 0.0, 0.0)
    """Weights of the fleet reward terms in the training episodes' reward [-]: w5
    (r5_local_speed, the traffic around the AV), w6 (r6_follower_comfort, its followers'
    accelerations) and w8 (r8_uniform_flow, Flow's desired velocity; ``RewardConfig``). An
    AV's own choice changes its own return by little; these terms pay it for the traffic's.
    Zeros = the paper's reward."""
    wave_share: float = 0.0
    """Share of each worker's agent-steps driven in wave episodes [-]: a 22-car ring of a
    length drawn from 220-270 m with one AV, or ``wave-highway`` at 5 % AVs, each at least
    300 s long (waves form after 60-90 s). A worker starts one whenever its wave share is
    below this; 0 = none."""
    wave_kinds: tuple[str, ...] = ("ring", "wave-highway")
    """The wave episodes drawn from (``auto-ring`` trains on rings alone)."""
    bootstrap_arrival: bool = True
    """Bootstrap at the end of the route from the last observation (False: arrival is a
    terminal state of value 0, which punishes progress)."""
    fleet_iterations: int = 0
    """After the RBP-DQN budget: total iterations of fleet-return search on the actor's accel
    outputs in OUT/fleet (``mixed_traffic.experiments.fleet``; 10 episodes each, 1.3-1.8 min
    with 90 s episodes on 2 cores), whose policy becomes OUT/auto.pt (0 = none). A per-agent critic cannot see a
    shared policy's gain, which the whole fleet shares (docs/agent.md)."""
    alpha: float = 0.6
    """Weight α of the normalised Q term in the actor loss after pretraining [-] (paper 0.6)."""
    lr: float = 1e-3
    """Adam learning rate of actor and critic [-] (paper 1e-3)."""
    lr_final: float = 0.0
    """Learning rate reached at the end of the ``env_steps`` budget by cosine decay from
    ``lr``, a function of transitions received, so it survives --resume and keeps one-worker
    runs deterministic [-] (0 = constant ``lr``)."""
    bc_accel_weight: float = 0.0
    """Weight of accel_brake errors in the behaviour-cloning term, relative to 1 per unit² on
    steering [-]; 0 = the form's default: 1 in the paper's form (its loss; steering weighs
    ``LearnerConfig.bc_steer_weight``), 0.05 on u in the residual form, so that the normalised
    Q term can move u against the pull of ‖u‖² (u's effect on a 0.5 s return is small)."""
    bc_accel_expectile: float = 0.5
    """Expectile τ of the accel_brake fit: errors below the label weigh 2τ, above it 2(1 − τ)
    [-] (0.5 = the paper's squared error; see ``LearnerConfig.bc_accel_expectile``)."""
    init: str = ""
    """Checkpoint whose networks (and optimiser states) start a new run: fine-tuning with a
    fresh replay and counters ('' = random init; ignored by --resume). A paper-form checkpoint
    (no ego fusion) is widened with zero weights on the ego input, so the run starts from the
    same policy."""
    ablation: str = "none"
    """Paper §V-A variant: none | nohis | nolane | nostar | noimp | nomul | novec."""
    ego_fusion: bool = True
    """The ego embedding joins LCA's lane-wise fusion (``LCAConfig.ego_fusion``); False trains
    the paper's fusion of the three lane vectors only."""
    bp_dqn: bool = False
    """Train the BP-DQN baseline (no behaviour-cloning regulariser) instead of RBP-DQN."""
    baseline: str = "none"
    """Paper §V-A method instead of RBP-DQN: transfuser (imitation of the demonstrator over
    raster and point tokens; needs --no-residual) | drl-mf (BP-DQN over a map-less raster and
    point cloud, no impact term; needs --no-residual) | head (BP-DQN, decisions and accel only,
    ACC-LC's lane keeping steers) | p-ddpg | q-pamdp (``agents.learners.variants``)."""
    local_buffer: int = 256
    """B_l: transitions a worker buffers before flushing them to the learner [transitions]."""
    replay_capacity: int = 200_000
    """B_g: GlobalBuffer capacity [transitions] (about 7 kB each)."""
    batch_size: int = 128
    """Learner mini-batch b [transitions]."""
    update_ratio: float = 1 / 32
    """Learner updates per transition received (1/32 with b=128 replays each sample ~4 times)."""
    learning_starts: int = 2000
    """Transitions in the replay before the first update."""
    max_lag: int = 64
    """Process/Ray backends: updates the learner may owe before it stops reading chunks."""
    sync_every: int = 50
    """K: learner updates between weight broadcasts to the workers."""
    epsilon: float = 0.2
    """Base ε of the Ape-X ladder: worker i uses ε^(1 + spread·i/(N−1)) [-]."""
    noise_std: float = 0.3
    """Base exploration noise σ of the ladder (same exponent) [action units]."""
    explore_hold: float = 0.0
    """Time an AV's exploration noise is held [s] (rounded to whole decisions): one perturbed
    policy for about a wave's period shows its effect on the waves in the return; 0 = a
    fresh draw at every decision, as runs before it."""
    ladder_spread: float = 3.0
    """Exponent spread of the exploration ladder over the workers [-]."""
    checkpoint_every: float = 300.0
    """Seconds between checkpoints [s]."""
    keep_snapshots: bool = True
    """Also keep each periodic checkpoint's weights as ``snapshots/<env steps>.pt`` (≈ 1 MB
    each), so a run's intermediate networks can be compared afterwards."""
    log_every: int = 20000
    """Transitions between learning-curve rows."""
    learner_threads: int = 1
    """torch threads of the learner process."""
    learner_compile: bool = False
    """Compile the learner's losses with torch.compile (inductor; needs a C++ compiler). Measured
    on a 2-core machine: 1.9x the updates/s of the pre-issue-22 learner at batch 128 (eager
    default: 1.1-1.2x), after a one-off compile of ~25-60 s (`python -m mixed_traffic.bench
    --section learner`); off by default so short runs and tests do not pay it."""
    progress: bool = True
    """Show a tqdm progress bar."""
    max_worker_restarts: int = 50
    """Give up when one worker slot has been restarted this many times."""
    crash_after_chunks: int = 0
    """Test hook: worker 0 SIGKILLs itself after sending this many chunks (0 = off)."""

    def __post_init__(self) -> None:
        """Validate the fields (ValueError naming the first bad one)."""
        self._check_topology()
        self._check_sampling()
        self._check_budgets()
        self._check_optimiser()
        self._check_learner_loop()
        self._check_form()

    def _bad(self, name: str, why: str) -> NoReturn:
        raise ValueError(f"TrainConfig.{name}={getattr(self, name)!r}: {why}")

    def _check_topology(self) -> None:
        """Workers, backend, address and ablation."""
        if self.workers < 1:
            self._bad("workers", "need at least 1 worker")
        if not isinstance(self.copies, int) or not 1 <= self.copies <= MAX_COPIES:
            self._bad("copies", f"must be an integer in 1-{MAX_COPIES}")
        if self.backend not in BACKENDS:
            self._bad("backend", f"choose from {BACKENDS}")
        if self.address and self.backend != "ray":
            self._bad("address", "only meaningful with backend='ray'")
        if not isinstance(self.seed, int) or isinstance(self.seed, bool) or self.seed < 0:
            self._bad("seed", "must be an integer >= 0")
        if self.ablation not in ABLATIONS:
            self._bad("ablation", f"choose from {ABLATIONS}")
        if self.baseline not in BASELINES:
            self._bad("baseline", f"choose from {BASELINES}")
        if self.baseline != "none" and (self.ablation != "none" or self.bp_dqn):
            self._bad("baseline", "a baseline is its own method: no --ablation or --bp-dqn")
        if (self.baseline in PAPER_FORM) == self.residual and self.baseline != "none":
            form = "--no-residual" if self.residual else "--residual"
            self._bad("residual", f"baseline {self.baseline} needs {form}")
        if self.ablation == "nomul" and self.workers != 1:
            self._bad("ablation", "NoMUL is the single-worker variant: pass --workers 1")

    def _check_sampling(self) -> None:
        """The per-episode densities, penetrations and weathers."""
        if not self.densities or any(not d >= 0 for d in self.densities):
            self._bad("densities", "need densities >= 0 (0 = the scenario's default)")
        if not self.penetrations or any(not 0 < p <= 1 for p in self.penetrations):
            self._bad("penetrations", "need penetrations in (0, 1]")
        if not self.weathers or any(w not in WEATHERS for w in self.weathers):
            self._bad("weathers", f"choose from {WEATHERS}")

    def _check_budgets(self) -> None:
        """The run's budgets and the demonstration phase."""
        if not math.isfinite(self.minutes) or self.minutes < 0:
            self._bad("minutes", "must be a finite number of minutes >= 0")
        if self.env_steps < 0:
            self._bad("env_steps", "must be >= 0")
        if self.env_steps == 0 and self.minutes == 0:
            self._bad("env_steps", "give a budget: env_steps > 0 and/or minutes > 0")
        if not 0 <= self.demo_share <= 1:
            self._bad("demo_share", "must be in [0, 1]")
        if self.demo_steps < 0:
            self._bad("demo_steps", "must be >= 0")
        if self.pretrain_updates < 0:
            self._bad("pretrain_updates", "must be >= 0")
        if self.fleet_iterations < 0:
            self._bad("fleet_iterations", "must be >= 0")

    def _check_optimiser(self) -> None:
        """The actor loss weights and the learning-rate schedule."""
        if not self.alpha >= 0:
            self._bad("alpha", "must be >= 0")
        if not self.lr > 0:
            self._bad("lr", "must be > 0")
        if not 0 <= self.lr_final <= self.lr:
            self._bad("lr_final", "must be in [0, lr] (0 = no decay)")
        if self.lr_final and not self.env_steps:
            self._bad("lr_final", "the decay runs over the env_steps budget: give env_steps > 0")
        if not self.bc_accel_weight >= 0:
            self._bad("bc_accel_weight", "must be >= 0 (0 = the form's default)")
        if not 0 < self.bc_accel_expectile < 1:
            self._bad("bc_accel_expectile", "must be in (0, 1)")

    def _check_form(self) -> None:
        """The policy's form: decision interval, horizon, residual bounds."""
        if not 0 < self.decision_interval <= 5:
            self._bad("decision_interval", "must be in (0, 5] s")
        if not self.horizon > self.decision_interval:
            self._bad("horizon", "must exceed decision_interval (γ = 1 - interval / horizon)")
        if not 0 <= self.explore_hold <= 600:
            self._bad("explore_hold", "must be in [0, 600] s")
        if self.set_speed and not self.residual:
            self._bad("set_speed", "the set speed bounds the residual form's row: use --residual")
        if not 1 <= self.n_step <= 200:
            self._bad("n_step", "must be in [1, 200] decisions")
        if self.twin and self.baseline in ("p-ddpg", "q-pamdp", "transfuser"):
            self._bad("twin", f"twin critics apply to rbp-dqn only, not baseline {self.baseline}")
        for name in ("steer_delta", "accel_delta"):
            if not 0 < getattr(self, name) <= 2:
                self._bad(name, "must be in (0, 2] action units")
        if self.residual and self.demo_policy not in TEACHERS:
            self._bad("demo_policy", f"the residual form corrects ACC-LC: use one of {TEACHERS}")
        if not 0 <= self.impact_weight <= 10:
            self._bad("impact_weight", "must be in [0, 10]")
        if len(self.fleet_weights) != 3 or not all(0 <= w <= 100 for w in self.fleet_weights):
            self._bad("fleet_weights", "must be three weights (w5, w6, w8) in [0, 100]")
        if not 0 <= self.wave_share < 1:
            self._bad("wave_share", "must be in [0, 1)")
        if not self.wave_kinds or not set(self.wave_kinds) <= {"ring", "wave-highway"}:
            self._bad("wave_kinds", "choose one or both of ring, wave-highway")
        for name in ("teacher_bonus", "reward_scale"):
            if not getattr(self, name) >= 0:
                self._bad(name, "must be >= 0")

    @property
    def accel_bc_weight(self) -> float:
        """``bc_accel_weight`` with 0 resolved to the form's default [-]."""
        return self.bc_accel_weight or (RESIDUAL_BC_ACCEL if self.residual else 1.0)

    @property
    def gamma(self) -> float:
        """Discount per decision [-]."""
        return 1.0 - self.decision_interval / self.horizon

    def _check_learner_loop(self) -> None:
        """Buffer sizes, the update ratio and the checkpoint period."""
        for name in ("local_buffer", "replay_capacity", "batch_size", "sync_every", "log_every",
                     "learner_threads", "max_lag"):  # fmt: skip
            if getattr(self, name) < 1:
                self._bad(name, "must be >= 1")
        for name in ("learning_starts", "max_worker_restarts"):
            if getattr(self, name) < 0:
                self._bad(name, "must be >= 0")
        if not (math.isfinite(self.update_ratio) and self.update_ratio >= 0):
            self._bad("update_ratio", "must be a finite number >= 0")
        if not self.checkpoint_every > 0:
            self._bad("checkpoint_every", "must be > 0")

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly fields (tuples as lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TrainConfig:
        """The config of :meth:`to_dict` (unknown keys ignored)."""
        names = {f.name for f in fields(cls)}
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()
                      if k in names})  # fmt: skip


def lca_config(cfg: TrainConfig, env_base: EnvConfig) -> LCAConfig:
    """Encoder config from the env's sensors, the ablation and the baseline."""
    flags = {"nohis": {"history": False}, "nolane": {"lane_wise": False},
             "nostar": {"star": False}, "novec": {"encoder": "bev"}}.get(cfg.ablation, {})  # fmt: skip
    flags |= {"transfuser": {"encoder": "transfuser"}, "drl-mf": {"encoder": "mf"}}.get(
        cfg.baseline, {}
    )
    s = env_base.sensors
    shapes = {k: v.shape for k, v in observation_space(env_base).spaces.items()}
    return LCAConfig(z=s.history, m=s.waypoints, ego_fusion=cfg.ego_fusion,
                     lidar_range=s.lidar_range, camera_range=s.camera_range,
                     extra=extra_width(shapes), **flags)  # fmt: skip


def env_base_config(cfg: TrainConfig, env_base: EnvConfig | None = None) -> EnvConfig:
    """Fixed env fields for every episode: episode length, copies and w_impact (0 for NoIMP and
    DRL-MF, which ignores its impact on the traffic behind)."""
    base = replace(env_base or EnvConfig(), episode_length=cfg.episode_length, copies=cfg.copies)
    base = replace(
        base,
        v2x=base.v2x or cfg.v2x,
        sensors=replace(base.sensors, memory=base.sensors.memory or cfg.memory),
    )
    w4 = 0.0 if cfg.ablation == "noimp" or cfg.baseline == "drl-mf" else cfg.impact_weight
    w5, w6, w8 = cfg.fleet_weights
    reward = replace(base.reward, w_impact=w4, w_local_speed=w5, w_follower_comfort=w6,
                     w_uniform=w8)  # fmt: skip
    return replace(base, reward=reward)
