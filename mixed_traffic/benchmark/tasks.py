"""The benchmark's tasks: fixed configs, horizons, rewards and held-out eval variants.

A task is what two papers must share to compare numbers on this env (as Flow's benchmarks fix
ring, merge and bottleneck): the training config (scenario, AV share, horizon, reward, the
observation tier), the warm-up before metrics count, the eval configs it is scored on, the
validation configs a learner may select its checkpoints on (never the eval configs), and the
reference its score is normalised to (:mod:`mixed_traffic.benchmark.score`), and the settings
of the learner interface (:mod:`agents.longitudinal`). Ids carry a
version (``ring-v2``): a change to any of these makes a new version, never a silent edit.

The task reward is system level, as Flow's: ``r5_local_speed`` (the mean speed of the traffic
around the AV as a share of the limit; the whole ring on a ring) with the AV's own comfort
``r3_comfort`` (its acceleration changes) and safety ``r1`` terms; the paper's efficiency and
impact terms are off. The ring pays for the state its score calls 1, with the safety terms:
``r8_uniform_flow``, Flow's desired-velocity reward at the ring's uniform-flow speed, which
falls with the speeds' spread (the waves) as with their mean's shortfall (a crawl). Its learner
acts through a residual on the human model's IDM, so that the zero action drives like a human
(with a plain acceleration the zero action holds the speed the ring starts at, which by itself
keeps the ring's flow uniform from t = 0), bounded by a failsafe (as Flow's ring AV obeys
SUMO's safe speed). A ring reward must rank the known wave dampers (FollowerStopper, PI with
saturation) above a follower of the waves on a training ring (tests/test_benchmark.py checks
it). ring-v0 paid for the mean speed with the AV's comfort, and PPO settled at the humans'
speed; ring-v1 added Flow's penalty on the AV's own acceleration, which ranks the dampers last
(their commands change by about 2 m/s² every step). Every term stays in
``infos[agent]["reward_terms"]``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from mixed_traffic.config import EnvConfig, RewardConfig

#: The task reward's weights: w1 safety, w3 comfort, w5 the traffic's speed (others 0).
TASK_REWARD = RewardConfig(
    w_safety=1.0, w_efficiency=0.0, w_comfort=0.1, w_impact=0.0, w_local_speed=1.0
)
#: The ring task's reward: safety and Flow's desired-velocity reward at the ring's uniform-flow
#: speed (r8: 1 in uniform flow, 0 at a standstill).
RING_REWARD = replace(TASK_REWARD, w_comfort=0.0, w_local_speed=0.0, w_uniform=1.0)
#: The ring learner's interface: a residual on the human model's IDM (the zero action drives as a
#: human), bounded by a failsafe with SUMO's 1 s reaction time (``agents.longitudinal``).
RING_LEARNER = (("base", "idm"), ("reaction", 1.0))
#: Observation tiers: the paper's sensors, or those plus the downstream (V2X) feed.
TIERS = ("paper", "v2x")
#: What a score of 1 means: the ring's uniform flow, or the free flow of the measured road.
REFERENCES = ("uniform-flow", "free-flow")


@dataclass(frozen=True)
class Task:
    """One benchmark task. Its configs are complete: ``parallel_env(task)`` needs nothing else."""

    name: str
    """Id with version, ``<family>-v<N>``."""
    summary: str
    """One line: what the AVs face and what is scored."""
    train: EnvConfig
    """The training config (horizon = ``train.episode_length`` [s])."""
    eval: tuple[EnvConfig, ...]
    """Held-out configs the score is measured on (other ring lengths or eval variants)."""
    warmup: float
    """Simulated time before the eval's metrics count [s]."""
    tier: str
    """Observation tier (``TIERS``)."""
    reference: str
    """Score 1 (``REFERENCES``); score 0 is all-human traffic."""
    metric: str = "mean_speed"
    """The record metric the score normalises (mean speed of all vehicles in the measurement
    segment [m/s])."""
    validate: tuple[EnvConfig, ...] = ()
    """Configs a learner selects its checkpoints on (other ring lengths than train's and eval's;
    on the roads the training config, at seeds the eval does not use); () = the training
    config."""
    learner: tuple[tuple[str, Any], ...] = ()
    """Settings of the learner interface (``agents.longitudinal.LongitudinalConfig`` fields)
    that the task fixes, as (name, value) pairs; the others keep their defaults."""

    @property
    def validation(self) -> tuple[EnvConfig, ...]:
        """The configs checkpoints are selected on: ``validate``, else the training config."""
        return self.validate or (self.train,)

    def __post_init__(self) -> None:
        if self.tier not in TIERS or self.reference not in REFERENCES:
            raise ValueError(f"task {self.name}: tier {self.tier!r} / reference "
                             f"{self.reference!r} not in {TIERS} / {REFERENCES}")  # fmt: skip
        if (self.tier == "v2x") != self.train.v2x or any(
            c.v2x != self.train.v2x for c in (*self.eval, *self.validate)
        ):
            raise ValueError(f"task {self.name}: tier {self.tier!r} and the configs' v2x disagree")


def _road(scenario: str, eval_scenario: str, share: float, horizon: float, v2x: bool) -> tuple:
    train = EnvConfig(scenario=scenario, penetration=share, episode_length=horizon,
                      reward=TASK_REWARD, v2x=v2x)  # fmt: skip
    return train, (replace(train, scenario=eval_scenario),)


def _ring() -> tuple:
    train = EnvConfig(scenario="ring", ring_length=(220.0, 270.0), ring_vehicles=22,
                      penetration=1 / 22, episode_length=300.0, reward=RING_REWARD)  # fmt: skip
    return train, tuple(replace(train, ring_length=(x,)) for x in (210.0, 280.0))


#: The ring's validation lengths [m]: outside the training range, as the eval's, but not them.
RING_VALIDATION = (215.0, 275.0)


def _tasks() -> dict[str, Task]:
    ring, ring_eval = _ring()
    wave, wave_eval = _road("wave-highway", "wave-highway-eval", 0.05, 420.0, v2x=True)
    merge, merge_eval = _road("merge", "merge-eval", 0.1, 300.0, v2x=False)
    neck, neck_eval = _road("bottleneck", "bottleneck-eval", 0.1, 300.0, v2x=False)
    tasks = (
        Task("ring-v2", "one AV among 22 vehicles on a ring of 220-270 m (eval 210 and 280 m): "
             "damp the stop-and-go waves", ring, ring_eval, 0.0, "paper", "uniform-flow",
             validate=tuple(replace(ring, ring_length=(x,)) for x in RING_VALIDATION),
             learner=RING_LEARNER),
        Task("wave-highway-v1", "5 % AVs on one lane upstream of a slow zone, with the V2X "
             "feed: damp the waves it sends upstream", wave, wave_eval, 120.0, "v2x",
             "free-flow"),
        Task("merge-v1", "10 % AVs on a highway with an on-ramp", merge, merge_eval, 60.0,
             "paper", "free-flow"),
        Task("bottleneck-v1", "10 % AVs through a lane drop", neck, neck_eval, 60.0, "paper",
             "free-flow"),
    )  # fmt: skip
    return {t.name: t for t in tasks}


#: Every task by id.
TASKS: dict[str, Task] = _tasks()


def get_task(name: str) -> Task:
    """The task ``name`` (an id such as ``ring-v2``; a bare family means its newest version).
    ``ValueError`` names the known ids."""
    if name in TASKS:
        return TASKS[name]
    versions = sorted((t for t in TASKS if t.rsplit("-v", 1)[0] == name),
                      key=lambda t: int(t.rsplit("-v", 1)[1]))  # fmt: skip
    if versions:
        return TASKS[versions[-1]]
    raise ValueError(f"unknown benchmark task {name!r}; known: {sorted(TASKS)}")
