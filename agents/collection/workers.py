"""Rollout workers (paper §IV-F, Algorithm 1: worker with a LocalBuffer) and their transports.

A :class:`RolloutWorker` owns one env (libsumo allows one simulation per process), a local
copy of the actor/critic wrapped in a single-threaded :class:`agents.learners.rbpdqn.Policy`, and a
:class:`LocalBuffer`. :meth:`RolloutWorker.collect` drives the env until at least ``n``
transitions are buffered and returns them as one :data:`Chunk` (the LocalBuffer flush). The
episode in progress carries over between calls.

Each episode samples its env config (scenario × density × penetration × weather) and its env
seed from ``np.random.default_rng([seed, worker_id, run, incarnation, episode])``; the same
generator drives exploration, so a worker's trajectory is a pure function of those numbers and
the weights it is given.

Transports (the learner side lives in :mod:`agents.training.trainer`):

- in-process: the learner calls ``collect`` directly (``--workers 1``: deterministic);
- :func:`process_main`: a spawned process sends chunks through its own pipe and reads weights
  from :class:`SharedWeights` (a seqlock over shared memory: no lock a dying worker could hold);
- Ray: the learner wraps :class:`RolloutWorker` in ``ray.remote`` and calls ``collect``.
"""

from __future__ import annotations

import contextlib
import os
import signal
import time
import traceback
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch
from torch.nn.utils import parameters_to_vector, vector_to_parameters

from agents.collection.intervals import Intervals, Rows
from agents.driver import Driver
from agents.learners.rbpdqn import LearnerConfig, Policy, build_nets
from agents.nets.lca import LCAConfig
from agents.nets.networks import Actor, Critic
from agents.policies import make_policy, stack_obs, to_actions
from agents.rules.tuned import cap_factor, teacher_rule
from mixed_traffic.config import EnvConfig
from mixed_traffic.env import parallel_env
from mixed_traffic.world.copies import copyable
from mixed_traffic.world.registry import load_scenario

TERMINAL_REASONS = ("collision", "off_road", "route_deviation", "red_light", "speed_limit")

Chunk = dict[str, Any]
"""A LocalBuffer flush of transitions, one per decision (:mod:`agents.collection.intervals`):
``obs``/``next_obs`` dicts of float32 (n, ...) arrays, ``decision`` (n,) int64, ``params``
(n, 3, 2) float32 (the network output u the agent held), ``reward``, ``done`` and ``discount``
(n,) float32, the expert labels ``labelled`` (n,) float32, ``label_decision`` (n,) int64 and
``label_params`` (n, 3, 2) float32 (see :class:`agents.learners.replay.ReplayBuffer`); plus
``worker_id``, ``incarnation``, ``seq`` (1-based chunk number of this incarnation), ``demo``
(decisions in the chunk taken by the demonstrator), ``sim_steps`` (simulation steps taken),
``trips``/``terminals``/``collisions`` (AV trips that ended in the chunk: arrived or terminal;
terminal events; collisions) and ``episodes`` (list of :func:`episode_stats` dicts of the
episodes that ended)."""


@dataclass(frozen=True)
class WorkerSpec:
    """Everything one worker needs (picklable; built by the trainer from its TrainConfig)."""

    worker_id: int
    env_base: EnvConfig
    """Env fields not sampled per episode (sensors, reward weights, episode length, ...)."""
    lca: LCAConfig
    scenarios: tuple[str, ...]
    densities: tuple[float, ...]
    penetrations: tuple[float, ...]
    weathers: tuple[str, ...]
    seed: int = 0
    """Root seed [-]."""
    run: int = 0
    """Resume count of the training run (fresh episode seeds after a resume)."""
    incarnation: int = 0
    """Restart count of this worker (fresh episode seeds after a crash)."""
    noise_std: float = 0.1
    """Gaussian exploration noise on the parameters [action units, -1..1]."""
    epsilon: float = 0.05
    """Probability of a random allowed decision per agent and step [-]."""
    demo_quota: int = 0
    """Transitions this worker still drives with the demonstrator before its own policy."""
    demo_share: float = 0.0
    """Probability that a later episode is driven by the demonstrator [-]."""
    demo_policy: str = "acc-lc"
    expert_labels: bool = False
    """Label the transitions the policy drives with the demonstrator's action (DAgger; the
    paper's form only: the residual form's label is always u = 0)."""
    learner: LearnerConfig = field(default_factory=LearnerConfig)
    """The policy's form (residual or not, decision interval, deltas, bonus) and γ per
    decision."""
    reward_scale: float = 0.0
    """Factor on the rewards stored [-] (0 = 1 - γ per simulation step, so Q is about the
    mean reward per step)."""
    bootstrap_arrival: bool = True
    """An arrival at the end of the route bootstraps from its last observation (False: a
    terminal state of value 0, as every other trip end)."""
    n_step: int = 1
    """Decisions per stored transition (n-step returns, ``agents.collection.intervals``)."""
    explore_hold: float = 0.0
    """Time an AV's exploration noise is held [s] (0: a fresh draw at every decision)."""
    wave_share: float = 0.0
    """Share of the agent-steps driven in wave episodes (``wave_episode``) [-]."""
    wave_kinds: tuple[str, ...] = ("ring", "wave-highway")
    """The wave episodes drawn from."""
    crash_after_chunks: int = 0
    """Test hook: SIGKILL itself after sending this many chunks (incarnation 0 only)."""
    extra: dict[str, Any] = field(default_factory=dict)


WAVE_RING = (220.0, 270.0)
"""Lengths a wave episode's 22-car ring is drawn from [m] (the ring task's training range)."""
WAVE_SECONDS = 300.0
"""Shortest recorded part of a wave episode [s]: waves form after 60-90 s and take minutes to
clear."""
WAVE_WARMUP = 120.0
"""Longest random warm-up of a wave episode [s], before its recorded part: the teacher drives
the AVs and nothing is recorded, so that transitions also start among formed waves."""


def wave_episode(
    base: EnvConfig, rng: np.random.Generator, kinds: tuple[str, ...]
) -> tuple[EnvConfig, float]:
    """A wave episode of ``base``'s settings, of a kind drawn from ``kinds``: one AV on a 22-car
    ring of a drawn length, or ``wave-highway`` at 5 % AVs (its default density); and its
    warm-up [s], drawn up to ``WAVE_WARMUP``, after which at least ``WAVE_SECONDS`` remain."""
    kind, warmup = str(rng.choice(kinds)), float(rng.uniform(0.0, WAVE_WARMUP))
    length = max(base.episode_length, WAVE_SECONDS) + warmup
    if kind == "ring":
        return replace(base, scenario="ring", density=None, ring_length=WAVE_RING,
                       ring_vehicles=22, penetration=1 / 22, episode_length=length), warmup  # fmt: skip
    return replace(base, scenario="wave-highway", density=None, penetration=0.05,
                   episode_length=length), warmup  # fmt: skip


def exploration_ladder(n_workers: int, base_eps: float, base_noise: float, spread: float) -> list:
    """Ape-X style per-worker exploration: worker i gets base·base^(spread·i/(N−1)) → [(ε, σ)].

    With one worker it is (base_eps, base_noise); worker N−1 gets base^(1+spread).
    """
    out = []
    for i in range(n_workers):
        k = 1.0 + (spread * i / (n_workers - 1) if n_workers > 1 else 0.0)
        out.append((base_eps**k, base_noise**k))
    return out


def weight_vector(actor: Actor, critic: Critic) -> np.ndarray:
    """Flat float32 copy of all actor then critic parameters (no buffers exist in either)."""
    with torch.no_grad():
        params = [*actor.parameters(), *critic.parameters()]
        return parameters_to_vector(params).detach().numpy().astype(np.float32).copy()


def episode_stats(
    env: Any, reward_sum: float, actions: int, acted: int, demo: bool, cfg: EnvConfig
) -> dict:
    """Summary of one finished episode.

    Keys: ``return_per_av`` (summed reward / AVs that acted), ``reward_sum``, ``actions``,
    ``av_trips``, ``terminals`` (sum of the terminal_* counts), ``collisions`` (AVs terminated
    by a collision), each over all the batch's copies; ``demo`` (some step was driven by the
    demonstrator) and the env cell.
    """
    copies = [env.episode_metrics(c) for c in range(cfg.copies)]

    def total(key: str) -> float:  # over the batch's copies
        return float(sum(m.get(key) or 0.0 for m in copies))

    trips = total("av_trips")
    terminals = sum(total(f"terminal_{r}") for r in TERMINAL_REASONS)
    return {
        "return_per_av": reward_sum / max(acted, 1),
        "reward_sum": reward_sum,
        "actions": actions,
        "av_trips": trips,
        "terminals": terminals,
        "collisions": total("terminal_collision"),
        "demo": demo,
        "scenario": cfg.scenario,
        "density": cfg.density,
        "penetration": cfg.penetration,
        "weather": cfg.weather,
        "seed": cfg.seed,
        "copies": cfg.copies,
    }


class LocalBuffer:
    """Closed transitions (:data:`agents.collection.intervals.Rows`); :meth:`take`
    concatenates and empties (the B_l flush)."""

    def __init__(self) -> None:
        self._parts: list[Rows] = []
        self.size = 0

    def add(self, rows: Rows) -> None:
        n = len(rows["decision"])
        if n:
            self._parts.append(rows)
            self.size += n

    def take(self) -> Chunk:
        parts, self._parts, self.size = self._parts, [], 0
        cat = np.concatenate
        out: Chunk = {k: {o: cat([p[k][o] for p in parts]).astype(np.float32)
                          for o in parts[0][k]} for k in ("obs", "next_obs")}  # fmt: skip
        for k, dtype in _ROW_DTYPES.items():
            out[k] = cat([p[k] for p in parts]).astype(dtype)
        return out


_ROW_DTYPES = {"decision": np.int64, "params": np.float32, "reward": np.float32,
               "done": np.float32, "discount": np.float32, "labelled": np.float32,
               "label_decision": np.int64, "label_params": np.float32}  # fmt: skip


class RolloutWorker:
    """One env + local policy copy + LocalBuffer (Algorithm 1 of the paper)."""

    def __init__(self, spec: WorkerSpec) -> None:
        torch.set_num_threads(1)
        self.spec = spec
        # each scenario's feasible densities, once (an episode samples among them)
        self._densities = {n: load_scenario(n).feasible_densities(spec.densities)
                           for n in set(spec.scenarios)}  # fmt: skip
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)  # overwritten by the first set_weights
            self.actor, self.critic = build_nets(spec.lca, spec.learner)
            self.actor.eval(), self.critic.eval()
        self.policy = Policy(self.actor, self.critic, spec.noise_std, spec.epsilon, threads=1,
                             **({"steer_noise_factor": 1.0} if spec.learner.residual else {}))  # fmt: skip
        self.has_weights = False
        self._demos: dict[tuple[str | None, float], Any] = {}
        self.demo_done = 0
        self.episode = 0
        self._steps = {"wave": 0, "other": 0}  # agent-steps driven per kind of episode
        self.wave = False
        self.seq = 0
        self.env: Any = None
        self._buf = LocalBuffer()
        self._episodes: list[dict] = []
        self._demo_in_buf = 0
        self._sim_steps = 0
        self._trips = self._terminals = self._collisions = 0

    # ------------------------------------------------------------------ weights
    def set_weights(self, vec: np.ndarray) -> None:
        """Load a :func:`weight_vector` from the learner."""
        with torch.no_grad():
            t = torch.from_numpy(np.asarray(vec, dtype=np.float32))
            vector_to_parameters(t, [*self.actor.parameters(), *self.critic.parameters()])
        self.policy.sync()
        self.has_weights = True

    # ------------------------------------------------------------------ episodes
    def _demonstrator(self, family: str | None) -> Any:
        """The demonstrator policy for scenario ``family``, built on first use: in the residual
        form the rule u corrects, built as evaluation builds it (``teacher_rule``)."""
        s, dt = self.spec, self.env.config.step_length
        if (family, dt) not in self._demos:
            self._demos[family, dt] = (
                teacher_rule(s.learner.teacher, family, dt)
                if s.learner.residual
                else make_policy(s.demo_policy, seed=s.seed, family=family)
            )
        return self._demos[family, dt]

    def _start_episode(self) -> None:
        """Sample the next episode's env config and seed, and reset a fresh env."""
        s = self.spec
        self.rng = np.random.default_rng([s.seed, s.worker_id, s.run, s.incarnation, self.episode])
        self.episode += 1
        self.wave = self._steps["wave"] < s.wave_share * sum(self._steps.values())
        self.warmup = 0.0  # [s] of teacher driving that is not recorded
        if self.wave:
            cfg, self.warmup = wave_episode(s.env_base, self.rng, s.wave_kinds)
        else:
            scenario = str(self.rng.choice(s.scenarios))
            densities = self._densities[scenario]
            cfg = replace(s.env_base, scenario=scenario,
                          density=densities[int(self.rng.integers(len(densities)))],
                          penetration=float(self.rng.choice(s.penetrations)))  # fmt: skip
        cfg = replace(
            cfg,
            weather=str(self.rng.choice(s.weathers)),
            seed=int(self.rng.integers(2**31 - 1)),
            second_instance="error",  # never a silent slow TraCI fallback in a worker
            copies=cfg.copies if copyable(load_scenario(cfg.scenario)) else 1,
        )
        self.demo_episode = bool(self.rng.random() < s.demo_share)
        self.any_demo = False
        if self.env is not None:
            self.env.close()  # frees libsumo for the next simulation in this process
        self.env_cfg = cfg
        self.env = parallel_env(config=cfg)
        self.acted: set[str] = set()
        self.obs, _ = self.env.reset(seed=cfg.seed, options={"allow_no_agents": True})
        self.ep_reward, self.ep_actions = 0.0, 0
        lc = s.learner
        hold = max(1, round(s.explore_hold / lc.decision_interval))
        family = self.env.scenario.family
        self.driver = Driver(self.policy, lc, self.env.config.step_length,
                             self._demonstrator(family), noise_hold=hold)  # fmt: skip
        self.driver.cap_factor = cap_factor(family)  # the governors' cap, as in evaluation
        # γ per decision_interval, so per simulation step of any scenario's length
        gamma_step = lc.gamma ** (self.env.config.step_length / lc.decision_interval)
        self.intervals = Intervals(gamma_step, s.reward_scale or 1.0 - gamma_step,
                                   s.bootstrap_arrival, s.n_step)  # fmt: skip

    def _step(self) -> None:
        """One env step for all current agents; closed transitions go to the LocalBuffer."""
        env = self.env
        agents, before = list(env.agents), env.sim_time
        if not agents:  # AVs queued upstream: let the simulation run on
            self.obs, *_ = env.step({})
        elif env.sim_time < self.warmup - 1e-6:
            self._warm_up(env, agents)
        else:
            self._step_agents(env, agents)
        # a step runs on until an AV enters when the last one leaves mid-episode
        self._sim_steps += round((env.sim_time - before) / env.config.step_length)
        if not env.agents and env.sim_time >= env.config.episode_length - 1e-6:
            self._end_episode(env)

    def _mode(self) -> str:
        """The driver's mode: ``teacher`` until this worker's demonstration quota is met
        (switching mid-episode) and for whole episodes with probability demo_share after,
        else ``explore``."""
        is_demo = self.demo_episode or self.demo_done < self.spec.demo_quota
        self.any_demo |= is_demo
        if not is_demo and not self.has_weights:
            raise RuntimeError("worker has no weights from the learner yet")
        return "teacher" if is_demo else "explore"

    def _labels(self, cmd: Any, mode: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(labelled, label_decision, label_params) of every agent: the residual form labels
        u = 0 (behaviour cloning pulls towards ACC-LC) and marks teacher-driven rows for the
        DQfD margin; the paper's form labels ACC-LC's action (expert relabelling) or, without
        labels, the taken action."""
        n = len(cmd.decision)
        teacher = np.full(n, mode == "teacher", np.float32)
        if self.spec.learner.residual:
            return teacher, cmd.teacher_decision, np.zeros_like(cmd.u)
        if mode == "teacher" or self.spec.expert_labels:
            return np.ones(n, np.float32), cmd.teacher_decision, cmd.teacher_params
        return teacher, cmd.decision, cmd.u

    def _warm_up(self, env: Any, agents: list[str]) -> None:
        """One step of a wave episode's warm-up: the teacher drives, nothing is recorded."""
        cmd = self.driver.act(stack_obs(self.obs, agents), agents, "teacher", self.rng)
        self.obs, *_ = env.step(to_actions(agents, cmd.decision, cmd.params))

    def _step_agents(self, env: Any, agents: list[str]) -> None:
        """Act for ``agents``, step the env, and buffer the transitions that closed."""
        batch = stack_obs(self.obs, agents)
        mode = self._mode()
        cmd = self.driver.act(batch, agents, mode, self.rng, labels=self.spec.expert_labels)
        due = np.flatnonzero(cmd.due)
        self._buf.add(self.intervals.decide(agents, batch, due, cmd.decision, cmd.u,
                                            self._labels(cmd, mode)))  # fmt: skip
        obs2, rew, term, trunc, info = env.step(to_actions(agents, cmd.decision, cmd.params))
        self._count_trips(agents, info)
        r = np.array([rew[a] for a in agents], np.float32)
        self.intervals.reward(agents, r)
        ended = [a for a in agents if term[a] or trunc[a]]
        if ended:
            arrived = np.array([info[a].get("event") == "arrived" for a in ended])
            terminal = np.array([bool(term[a]) for a in ended])
            self._buf.add(self.intervals.end(ended, stack_obs(obs2, ended), terminal, arrived))
        self.acted.update(agents)
        self._steps["wave" if self.wave else "other"] += len(agents)
        self.ep_reward += float(r.sum())
        self.ep_actions += len(agents)
        if mode == "teacher":
            self.demo_done += len(due)
            self._demo_in_buf += len(due)
        self.obs = obs2

    def _count_trips(self, agents: list[str], info: dict) -> None:
        """Trips that ended this step, by reason (curves need no episode end)."""
        for a in agents:
            ev = info.get(a, {}).get("event", "")
            if ev == "arrived" or ev in TERMINAL_REASONS:
                self._trips += 1
                self._terminals += ev in TERMINAL_REASONS
                self._collisions += ev == "collision"

    def _end_episode(self, env: Any) -> None:
        """Record the finished episode's stats and close its env."""
        self._episodes.append(
            episode_stats(
                env,
                self.ep_reward,
                self.ep_actions,
                len(self.acted),
                self.any_demo,
                self.env_cfg,
            )
        )
        self.env.close()
        self.env = None

    def collect(self, n: int) -> Chunk:
        """Step until ≥ n transitions are buffered → the flushed :data:`Chunk`."""
        s = self.spec
        if s.crash_after_chunks and s.incarnation == 0 and self.seq >= s.crash_after_chunks:
            os.kill(os.getpid(), signal.SIGKILL)  # test hook: a hard crash, like a segfault
        while self._buf.size < n:
            if self.env is None:
                self._start_episode()
            self._step()
        self.seq += 1
        chunk = self._buf.take()
        chunk.update(
            worker_id=s.worker_id, incarnation=s.incarnation, seq=self.seq,
            demo=self._demo_in_buf, sim_steps=self._sim_steps, episodes=self._episodes,
            trips=self._trips, terminals=self._terminals, collisions=self._collisions,
        )  # fmt: skip
        self._episodes, self._demo_in_buf, self._sim_steps = [], 0, 0
        self._trips = self._terminals = self._collisions = 0
        return chunk

    def collect_with(self, n: int, weights: np.ndarray | None) -> Chunk:
        """Ray entry point: optionally load new weights, then :meth:`collect`."""
        if weights is not None:
            self.set_weights(weights)
        return self.collect(n)

    def close(self) -> None:
        """Close the env of the episode in progress."""
        if self.env is not None:
            self.env.close()
            self.env = None


class SharedWeights:
    """Latest learner weights in shared memory, published with a seqlock (single writer).

    The version is even when stable and odd while the learner writes; a reader copies and
    accepts only when the version was even and unchanged across the copy. Nothing is locked, so
    a worker killed mid-read cannot block anyone.
    """

    def __init__(self, ctx: Any, n: int) -> None:
        self.n = n
        self.buf = ctx.RawArray("f", n)
        self.version = ctx.RawValue("q", -2)

    def publish(self, vec: np.ndarray) -> None:
        v = self.version.value
        self.version.value = v + 1
        np.frombuffer(self.buf, np.float32)[:] = vec
        self.version.value = v + 2

    def read(self, last: int) -> tuple[int, np.ndarray] | None:
        """→ (version, copy) when a stable version newer than ``last`` exists, else None."""
        for _ in range(100):
            v1 = self.version.value
            if v1 == last or v1 < 0:
                return None
            if v1 % 2:
                time.sleep(0.001)
                continue
            vec = np.frombuffer(self.buf, np.float32).copy()
            if self.version.value == v1:
                return v1, vec
        return None


def process_main(spec: WorkerSpec, conn: Any, weights: SharedWeights, stop: Any, n: int) -> None:
    """Body of a spawned worker process: collect chunks of ≥ n transitions and send them.

    Sends ``("chunk", Chunk)``; on a Python exception sends ``("error", traceback)`` and exits.
    ``conn.send`` writes synchronously, so a chunk whose send returned survives a later crash.
    """
    worker: RolloutWorker | None = None
    try:
        worker = RolloutWorker(spec)
        version = -2
        while not stop.is_set():
            got = weights.read(version)
            if got is not None:
                version, vec = got
                worker.set_weights(vec)
            conn.send(("chunk", worker.collect(n)))
    except (BrokenPipeError, EOFError, KeyboardInterrupt):
        return
    except BaseException:
        with contextlib.suppress(OSError):
            conn.send(("error", traceback.format_exc()))
    finally:
        if worker is not None:
            worker.close()
