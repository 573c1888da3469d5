"""MixedTrafficEnv: a PettingZoo ParallelEnv in which the AVs of a SUMO simulation are agents.

MDP (DESIGN §3, §6-§9; paper §III-IV)
-------------------------------------
Agents
    ``possible_agents = av_0 … av_{N-1}``: every AV the episode's demand contains (fixed for a
    config). An AV becomes an agent when it enters the network and stops being one when it
    arrives (terminated, ``event="arrived"``), collides or commits another terminal event;
    ids are never reused within an episode; ``step`` runs on until an AV enters, so ``agents``
    is empty only at the end. ``fixed_fleet=True``: all AVs are agents from reset until
    truncation; an AV that arrives or fails re-enters upstream under the same id (a failure
    still gives its penalty and ``event``; on a .sumocfg a pool of agents drives the file's AV
    trips in turn, ``world.fleet_pool``); one waiting to (re-)enter gets the empty observation
    (only ``follow`` allowed) and its actions are ignored.
Observation
    ``Dict(ego (z,5), lanes (3,z,4m), vehicles (3,z,12), lights (3,z,4), limits (3,k,2),
    give_way (3,), node_mask (3,3), action_mask (3,))``, see ``mixed_traffic.sensing.
    observation`` for features and scales; ``v2x=True`` adds ``downstream (S,2)``, the mean
    speed ahead on the route from a roadside or probe feed (``mixed_traffic.sensing.v2x``).
    Sensors (LiDAR vehicles, camera lights, GNSS/IMU ego) apply the weather preset's noise and
    misdetection; rewards, terminations and metrics use ground truth.
Action
    ``Dict(decision=Discrete(3), params=Box(-1, 1, (3, 2)))``: decision 0 left change, 1 follow,
    2 right change; the chosen row ``(steering, accel_brake)`` is executed: steering ±1 =
    ±60° (+ = left), accel_brake +1 = +3 m/s², −1 = −6 m/s² (``VehicleConfig``). A kinematic
    bicycle model integrates it and SUMO applies it (setSpeed + changeSublane) with its own
    safety checks off. Invalid actions (NaN, out of the space, missing for a live agent, given
    to an agent that is not live) raise ``ValueError`` naming the agent.
Reward
    ``0.9·r1 + 0.8·r2 + 0.6·r3 + 0.2·r4`` (``RewardConfig``), every term by name in
    ``infos[agent]["reward_terms"]``: r1_ttc, r1_lane, r1_terminal, r2_speed, r2_lane_change,
    r3_comfort, r4_impact (``mixed_traffic.env.reward``), and, weighted 0 by default, the
    traffic around the agent: r5_local_speed, r6_follower_comfort (``env.traffic_terms``).
Termination / truncation
    Terminated on arrival or a terminal event (``infos[agent]["event"]`` = collision,
    off_road, route_deviation, red_light, speed_limit; the vehicle leaves SUMO). All live
    agents are truncated when the simulated time reaches ``episode_length``.
Metrics
    ``episode_metrics()`` (also in the last step's infos under ``"episode"``): DT-TF, AvgDT-A,
    AvgAT-C, AvgDI-C, MinTTC-A, AvgOFF-A, AvgVEL-A, AvgJERK-A, AvgDEC-C, PT-RT, AvgR and
    safety counts (``mixed_traffic.schema``).

Arguments: every field of ``EnvConfig`` as a keyword (``parallel_env(density=180, ...)``) or a
whole ``config=EnvConfig(...)``; ``render_mode`` ``"rgb_array"`` (headless bird's-eye view) or
``"human"`` (sumo-gui, needs a display); ``warmup`` [s] before flow metrics count (default:
the scenario's where the episode is longer, else 0);
``trace=True`` keeps every vehicle's trajectory in the measurement segment (``trajectories()``);
``metrics=False`` records no metrics (a training env: its observations, rewards and infos are
the same, each step is cheaper, and ``episode_metrics()`` raises);
``sumo_drives_avs=True`` hands the AVs back to SUMO's own car-following and lane-change models
(they are then no agents: the all-human reference of the studies drives this way).
"""

from __future__ import annotations

import contextlib
import shutil
from collections.abc import Sequence
from dataclasses import replace
from functools import partial
from itertools import compress
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv
from pettingzoo.utils.conversions import parallel_to_aec

from mixed_traffic.config import EnvConfig
from mixed_traffic.env import checks
from mixed_traffic.env.action import (
    action_space,
    allowed_decisions,
    no_actions,
    stack_actions,
    stack_batch,
    to_physical,
)
from mixed_traffic.env.agent_table import FOLLOW, AgentTable, Rows, StepMemory
from mixed_traffic.env.control import BicycleController
from mixed_traffic.env.obs_batch import StepBatches
from mixed_traffic.env.recorders import Recorders
from mixed_traffic.env.reward import agent_rewards
from mixed_traffic.env.step_output import BatchStep, add_entered, api_dicts, batch_step
from mixed_traffic.env.step_truth import av_step, step_memory
from mixed_traffic.env.sumo_sync import fan_choices, follow_sumo_routes, give_way_gates
from mixed_traffic.env.termination import agent_events
from mixed_traffic.env.truth import SpeedView, StepViews
from mixed_traffic.paths import scratch_dir
from mixed_traffic.sensing.extras import ExtraKeys
from mixed_traffic.sensing.frame import PerceptionFrame
from mixed_traffic.sensing.observation import ObservationBuilder, observation_space
from mixed_traffic.sensing.perception import Perception
from mixed_traffic.world.backend import SumoBackend
from mixed_traffic.world.boundary import PeriodicBoundary
from mixed_traffic.world.copies import Boundaries, vehicle_copy
from mixed_traffic.world.episode import Worlds
from mixed_traffic.world.fleet_pool import FleetPool
from mixed_traffic.world.registry import load_scenario
from mixed_traffic.world.scenario import sumo_args
from mixed_traffic.world.snapshot import TrafficSnapshot

TRACE_INTERVAL = 0.5
"""Time between the samples of a traced trajectory [s]."""


class NoAgentError(RuntimeError):
    """reset() found no AV in the network and none entered before its wait ran out."""


class MixedTrafficEnv(ParallelEnv):
    __doc__ = __doc__
    metadata: ClassVar[dict[str, Any]] = {
        "name": "mixed_traffic_v0",
        "render_modes": ["rgb_array", "human"],
        "render_fps": 10,
    }

    def __init__(
        self,
        config: EnvConfig | None = None,
        render_mode: str | None = None,
        warmup: float | None = None,
        sumo_drives_avs: bool = False,
        trace: bool = False,
        metrics: bool = True,
        **kwargs: Any,
    ) -> None:
        checks.check_config_args(config, kwargs)
        cfg = config if config is not None else EnvConfig(**kwargs)
        checks.check_render_mode(render_mode, self.metadata["render_modes"])
        self.render_mode = render_mode
        self.sumo_drives_avs = sumo_drives_avs
        self.trace = trace
        self.metrics = metrics
        self._bundled = load_scenario(cfg.scenario)
        self.config = cfg = self._bundled.configure(cfg)
        self.warmup = self._bundled.default_warmup(warmup, 0.0, cfg.episode_length)
        checks.check_warmup(self.warmup, cfg.episode_length)
        checks.warn_coarse_step(cfg.step_length)
        self._worlds = Worlds(self._bundled, cfg)  # the copies, sized on the longest ring
        self.scenario = self._worlds.sizing.views[0]  # what SUMO loads
        # ring_lengths: each copy's ring circumference [m] (None: no ring); the longest first
        self.ring_lengths = (self._worlds.longest_length,) * cfg.copies
        self._desired = np.zeros(0)  # (L,) r8's reference speed by lane [m/s] (0 = limits)
        self.possible_agents = [f"av_{i}" for i in range(len(self._worlds.agent_copy))]
        self._agent_copy = self._worlds.agent_copy
        self._vehicle_copy = partial(vehicle_copy, per_copy=self._worlds.per_copy)
        self._table = AgentTable(self.possible_agents)
        self._obs_space = observation_space(cfg)
        self._act_space = action_space()
        self._empty_obs = {k: np.zeros(s.shape, s.dtype) for k, s in self._obs_space.spaces.items()}
        self._empty_obs["action_mask"][FOLLOW] = 1  # a waiting AV may only follow
        self._backend = SumoBackend("traci" if render_mode == "human" else cfg.backend, cfg.second_instance,
                                    gui=render_mode == "human")  # fmt: skip
        self._renderer: Any = None
        self._use_map()
        self._extras = ExtraKeys(cfg, len(self.possible_agents), self.scenario.ring)
        self._tmp = scratch_dir()
        self._episode_rng = np.random.default_rng(cfg.seed)
        # per episode, set by reset()
        self._snap: TrafficSnapshot | None = None
        self._boundary: PeriodicBoundary | FleetPool | Boundaries | None = None
        self._noise_rng: np.random.Generator | None = None
        self._rec = Recorders(metrics)
        self._tls: dict[str, str] = {}
        self._tls_prev: dict[str, str] = {}
        self._memory = StepMemory()
        self._step_views: tuple[Rows, StepViews] | None = None
        self._batches = StepBatches()  # observation arrays (observation_batch, last ones)
        self._phase = "new"  # new -> running -> ended (time limit) | closed
        self._replaced: set[str] = set()  # agents whose decision the mask forbade this step

    def _use_map(self) -> None:
        """Build the network's stages: HD map, sensors, bicycle model, observations, lane table."""
        cfg = self.config
        self.hdmap = self.scenario.hdmap
        self._perception = Perception(cfg.sensors, self.hdmap, cfg.weather)
        self._controller = BicycleController(cfg.vehicle, self.hdmap, cfg.step_length)
        self._builder = ObservationBuilder(cfg, self.hdmap)
        self._backend.set_lane_table(self.hdmap.lane_ids, self.hdmap.lane_edge)
        self._renderer = None

    @property
    def agents(self) -> list[str]:
        """The live agents (PettingZoo)."""
        return self._table.agents

    @property
    def agent_copy(self) -> np.ndarray:
        """(P,) int32 the copy of the scenario each possible agent drives in."""
        return self._agent_copy

    @property
    def ring_length(self) -> float | None:
        """This episode's ring centre-line length [m] (copy 0's; ``ring_lengths``: each copy's);
        None off a ring."""
        return self.ring_lengths[0]

    @property
    def sim_time(self) -> float:
        """Simulated time of the current episode [s] (0 before the first reset)."""
        return self._snap.time if self._snap is not None else 0.0

    # ------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> spaces.Dict:
        return self._obs_space

    def action_space(self, agent: str) -> spaces.Dict:
        return self._act_space

    # ------------------------------------------------------------------ reset
    def reset(self, seed: int | None = None, options: dict | None = None):
        checks.check_reset_args(seed, options)
        if seed is None:
            seed = int(self._episode_rng.integers(2**31 - 1))
        if self._phase == "closed":  # reopened: a new scratch folder for the route file
            self._tmp = scratch_dir()
        self._phase = "running"
        cfg = replace(self.config, seed=int(seed))
        # the first words are those of generate_state(3): scenarios without V2X or a drawn
        # ring seed as before
        words = np.random.SeedSequence(int(seed)).generate_state(5)
        demand_seed, sumo_seed, noise_seed, v2x_seed, ring_seed = words
        episode = self._worlds.episode(cfg, int(demand_seed), np.random.default_rng(ring_seed))
        self.ring_lengths = episode.ring_lengths
        moved = episode.batch.net_file != self.scenario.net_file  # drawn ring lengths
        self.scenario = episode.scenario
        if moved:
            self._use_map()
        self._desired = episode.desired[episode.batch.lane_copy]
        route_file = Path(self._tmp) / "demand.rou.xml"
        fleet = self.possible_agents if cfg.fixed_fleet else None
        self._boundary = self._worlds.start(episode, cfg, route_file, self.sumo_drives_avs, fleet)
        self._backend.start(sumo_args(self.scenario, cfg, route_file, seed=int(sumo_seed) % 2**31))
        self._noise_rng = np.random.default_rng(noise_seed)
        self._controller.reset()
        self._builder.reset()
        self._extras.reset(np.random.default_rng(v2x_seed))
        every = max(1, round(TRACE_INTERVAL / cfg.step_length)) if self.trace else 0
        self._rec.start(self.hdmap, [v.measurement for v in episode.batch.views], cfg,
                        self.warmup, every, self._vehicle_copy)  # fmt: skip
        self._table.reset(list(self.possible_agents) if cfg.fixed_fleet else [])
        self._batches.reset()
        self._memory = StepMemory()
        snap = self._advance()
        self._backend.drop_pending(episode.demand.placed_ids)
        obs = self._start_from(snap)
        if not self.agents and self.possible_agents and not self.sumo_drives_avs:
            obs = self._wait_for_an_agent(int(seed), bool((options or {}).get("allow_no_agents")))
        # reset's infos stay empty: TorchRL takes their keys for the info spec of every step
        return obs, {a: {} for a in self.agents}

    def _wait_for_an_agent(self, seed: int, allow_none: bool) -> dict[str, dict]:
        """Advance the simulation (nobody acts) until the first AV enters the network, for at
        most ``config.reset_wait`` seconds and never past the episode's last step; the
        observations of the agents that entered. If none did, ``NoAgentError`` unless
        ``allow_none`` (the episode then runs on all human)."""
        cfg = self.config
        end = cfg.episode_length - cfg.step_length
        limit = min(self.sim_time + cfg.reset_wait, end)
        obs: dict[str, dict] = {}
        while not self.agents and self.sim_time < limit - 1e-9:
            obs, *_ = self._step_once(*no_actions())
        if not self.agents and not allow_none:
            raise NoAgentError(checks.no_agent_message(seed, cfg, limit < end - 1e-9))
        return obs

    def _start_from(self, snap: TrafficSnapshot) -> dict[str, dict]:
        """Admit the AVs of ``snap`` and observe them, as at the start of an episode."""
        self._admit(snap)
        rows = self._table.live_rows(snap)
        truth, sensed = self._sense(snap, rows)
        self._remember(snap, rows, StepViews.of(snap, truth, rows.r))
        obs = self._observe(snap, rows, sensed)
        self._snap = snap
        return {a: obs.get(a, self._empty_obs) for a in self.agents}

    # ------------------------------------------------------------------ step
    def step(self, actions: dict[str, Any]):
        checks.check_step(self._phase, actions, self.config.episode_length)
        out = self._step_once(*stack_actions(actions, self.agents, self._act_space))
        return self._idle(*out) if self._idles() else out

    def step_batch(self, decision: Any, params: Any) -> BatchStep:
        """``step`` for batched policies: ``decision`` (A,) and ``params`` (A, 3, 2) of the A
        live agents in ``env.agents`` order. The same step without the PettingZoo per-agent
        dicts (no ``infos`` with reward terms, no last observation of an agent that ended);
        the next observations are ``observation_batch()``, the metrics are the same."""
        checks.check_phase(self._phase, self.config.episode_length)
        out = self._step_once(*stack_batch(decision, params, self.agents, self._act_space), False)
        if self._idles():  # run on until an AV enters or the episode ends, as step() does
            while not self.agents and self._phase == "running":
                out.entered.extend(self._step_once(*no_actions(), False).entered)
        return out

    def _step_once(self, decision: np.ndarray, params: np.ndarray, dicts: bool = True):
        """One simulation step: the agents act (their stacked actions), SUMO moves; the
        PettingZoo dicts, or without ``dicts`` a ``BatchStep``."""
        decision = self._allowed(decision)
        self._extras.command(self._table.slots_of, self.agents, decision, params)
        steer, accel = to_physical(decision, params, self.config.vehicle)
        cmd = self._control(steer, accel, decision)  # control
        snap = self._advance()  # SUMO step + density boundary
        rows = self._table.live_rows(snap)
        truth, sensed = self._sense(snap, rows)  # perception
        views = StepViews.of(snap, truth, rows.r)  # front and rear vehicles, once
        events = self._events(snap, rows, cmd)  # termination
        rewards, terms, changed = self._rewards(snap, rows, views, events, dicts)  # reward
        self._record(snap, rows, views, rewards, changed)  # metrics
        self._remember(snap, rows, views)
        obs = self._observe(snap, rows, sensed, dicts)  # observation
        self._step_views = (rows, views)  # joined if agents enter in _finish
        return self._finish(snap, obs, rewards, terms, events, dicts)

    def _idles(self) -> bool:
        """The last agent left mid-episode (one trip per agent, the env drives the AVs)."""
        return (not self.agents and self._phase == "running" and bool(self.possible_agents)
                and not self.sumo_drives_avs and not self.config.fixed_fleet)  # fmt: skip

    def _idle(self, obs: dict, rew: dict, term: dict, trunc: dict, infos: dict):
        """Run on with nobody acting until an AV enters (its entries join the step's dicts)
        or the episode ends (every info then carries ``"episode"``): ``while env.agents:``."""
        while not self.agents and self._phase == "running":
            for mine, theirs in zip((obs, rew, term, trunc, infos), self._step_once(*no_actions())):
                mine.update(theirs)
        if self._phase == "ended":
            self._summarise(infos)
        return obs, rew, term, trunc, infos

    def _summarise(self, infos: dict[str, dict]) -> None:
        """The episode's metrics into every info (``"episode"``: its copy's), where the env
        records them."""
        if self.metrics:
            summary = [self.episode_metrics(c) for c in range(self.config.copies)]
            for a, info in infos.items():
                info["episode"] = summary[self._vehicle_copy(a)]

    def _allowed(self, decision: np.ndarray) -> np.ndarray:
        """Decisions the masks of the last observations forbid, replaced (``allowed_decisions``)
        and remembered for this step's infos."""
        masks = self.observation_batch()["action_mask"]
        decision, replaced = allowed_decisions(decision, masks.reshape(-1, 3))
        self._replaced = set(compress(self.agents, replaced.tolist()))
        return decision

    # ------------------------------------------------------------------ stages
    def _control(self, steer: np.ndarray, accel: np.ndarray, decision: np.ndarray):
        """Bicycle model -> SUMO for every agent present in the simulation."""
        rows = self._table.live_rows(self._snap)
        acting = rows.pos  # agents in the simulation, in agent order
        self._table.decision.fill(FOLLOW)  # agents that did not act count as following
        self._table.decision[rows.slots] = decision[acting]
        return self._controller.step(
            self._backend, self._snap, rows.ids, steer[acting], accel[acting]
        )

    def _advance(self) -> TrafficSnapshot:
        """One SUMO step; the boundary replaces vehicles that left; flow metrics."""
        snap = self._backend.step()
        self._batches.clear()
        self._boundary.step(snap, self._backend)
        if self.metrics:
            self._rec.flow.update(snap)
        ids = self._perception.tls_ids
        self._tls = dict(zip(ids, self._backend.tls_states(ids)))
        return snap

    def _admit(self, snap: TrafficSnapshot, gone: Sequence[str] = ()) -> list[str]:
        """Start controlling AVs that (re-)entered the network; returns their ids. ``gone``:
        agents removed after ``snap`` was taken (a fixed fleet's may re-enter later)."""
        table = self._table
        avs = list(compress(snap.ids, snap.is_av.tolist()))
        fresh = set(avs).difference(self._controller.tracked, table.finished, table.released, gone)
        if not fresh:  # the usual step: set operations only, no per-vehicle Python loop
            return []
        new = [v for v in avs if v in fresh]  # in snapshot order
        if self.sumo_drives_avs:
            self._backend.release_control(new)
            table.released.update(new)
            return []
        self._controller.add_from_snapshot(snap, new, self._backend)
        for a in new:
            table.set_route(a, self._route_rows(self._backend.vehicle_route(a)))
        self._builder.drop(new)
        self._extras.drop(table.slots_of(new))
        if not self.config.fixed_fleet:
            table.agents += new
        return new

    def _sense(self, snap: TrafficSnapshot, rows: Rows) -> tuple[PerceptionFrame, PerceptionFrame]:
        r = rows.r
        nxt = self._table.next_edge(rows.slots, snap.route_index[r])
        tls = [self._tls[t] for t in self._perception.tls_ids]
        s = self.config.sensors
        gates = give_way_gates(self.hdmap, self._backend, snap, rows, nxt, tls, s.camera_range)
        via = fan_choices(self.hdmap, self._backend, snap, rows, nxt, s.lidar_range)
        return self._perception.sense(snap, r, nxt, tls, self._noise_rng, gates, via)

    def _events(self, snap: TrafficSnapshot, rows: Rows, cmd) -> dict[str, str]:
        """'arrived', a terminal reason, or '' for every agent that acted, judged on the routes
        SUMO has now (it may have changed some)."""
        follow_sumo_routes(self._table, self._backend, snap, rows, self._route_rows)
        return agent_events(self.hdmap, self._memory, self._table, snap, rows, cmd,
                            self._tls_prev, self.config.speed_tolerance)  # fmt: skip

    def _route_rows(self, edges: Sequence[str]) -> np.ndarray:
        """(R,) edge rows of a route given by edge ids."""
        return np.array([self.hdmap.edge_row.get(e, -1) for e in edges], np.int64)

    def _rewards(self, snap: TrafficSnapshot, rows: Rows, views: StepViews,
                 events: dict[str, str], dicts: bool = True):  # fmt: skip
        """Reward, named terms and completed lane changes (bool per agent number) of every
        agent that acted."""
        return agent_rewards(self.config, self.hdmap, self._memory, self._table, snap, rows,
                             views, events, self.scenario.ring, self._desired, dicts)  # fmt: skip

    def _record(self, snap, rows: Rows, views: StepViews, rewards: dict[str, float],
                changed: np.ndarray) -> None:  # fmt: skip
        """Per-AV metrics of this step (flow metrics are recorded in ``_advance``)."""
        if not self.metrics:
            return
        sample = av_step(snap, rows, views, self._table, self._memory, rewards, changed,
                         self._agent_copy[rows.slots])  # fmt: skip
        self._rec.av.step(sample, snap.time, SpeedView(snap))

    def _remember(self, snap: TrafficSnapshot, rows: Rows, views: StepViews) -> None:
        """Ground truth of this step that the next step's events and rewards compare against."""
        self._memory = step_memory(snap, rows, views, self._table)
        self._tls_prev = dict(self._tls)

    def _observe(self, snap, rows: Rows, sensed: PerceptionFrame,
                 dicts: bool = True) -> dict[str, dict]:  # fmt: skip
        """The observations of ``rows``' agents (per agent, or with ``dicts`` False none: the
        batch only)."""
        ids, t = rows.ids, self._table
        if not ids:
            return {}
        extra = self._extras.keys(
            self.hdmap, snap, rows.r, rows.slots, t.route_table, t.route_len, sensed
        )
        obs = self._builder.build(snap, ids, rows.r, sensed, t.route_table[rows.slots], extra,
                                  dicts)  # fmt: skip
        self._batches.add(ids, self._builder.last_batch)
        return obs

    def _finish(self, snap, obs, rewards, terms, events, dicts: bool = True):
        """Retire finished agents, admit new ones; the PettingZoo dicts of the agents that
        acted and entered, or without ``dicts`` their ``BatchStep``."""
        cfg, table = self.config, self._table
        done = sorted(a for a, e in events.items() if e)
        self._retire(done, events)
        truncate = snap.time >= cfg.episode_length - 1e-9
        agents = list(self.agents)
        ended = set() if cfg.fixed_fleet else set(done).intersection(agents)
        if dicts:
            out = api_dicts(agents, ended, truncate, obs, rewards, terms, events, self._replaced,
                            lambda a: self._batches.last_obs(a) or self._empty_obs,
                            self._copies(agents))  # fmt: skip
        else:
            out = batch_step(agents, ended, truncate, rewards, events, self._copies(agents))
        self._forget(done)
        if not cfg.fixed_fleet:
            table.finished.update(done)
            table.agents = [a for a in agents if a not in ended]
        new = [] if truncate else self._admit(snap, done)  # nobody enters at the time limit
        if new:
            new_obs = self._observe_new(snap, new, dicts)
            if dicts:
                add_entered(out, new, new_obs, cfg.fixed_fleet, self._copies(new))
            else:
                out.entered.extend(new)
        if truncate:
            self._phase = "ended"
            table.agents = []
            if dicts:
                self._summarise(out[4])
        self._snap = snap
        return out

    def _copies(self, agents: list[str]) -> np.ndarray:
        """(A,) int32 the copy each agent drives in."""
        return self._agent_copy[self._table.slots_of(agents)]

    def _forget(self, done: list[str]) -> None:
        """Free what finished agents hold (history slots; last observations, which are views
        of a whole step's arrays), so memory stays flat. A fixed fleet keeps a compact copy
        of each last observation: it is returned until the agent enters again."""
        self._builder.drop(done)
        self._extras.drop(self._table.slots_of(done))
        self._batches.forget(done, keep=self.config.fixed_fleet)

    def _retire(self, done: list[str], events: dict[str, str]) -> None:
        """End the trips of ``done`` agents; SUMO already removed arrived and collided ones."""
        for a in done:
            self._rec.av.end_trip(a, events[a])
            if events[a] not in ("arrived", "collision"):
                self._backend.remove(a)
        removed = [a for a in done if events[a] not in ("arrived", "collision")]
        self._boundary.replace(self._backend, removed)
        self._controller.remove(done)
        for a in done:  # not live until admitted again (the step's snapshot still shows it)
            self._table.end_trip(a)

    def _observe_new(self, snap: TrafficSnapshot, new: list[str],
                     dicts: bool = True) -> dict[str, dict]:  # fmt: skip
        """Observations of agents that entered this step (they act from the next step on)."""
        rows = self._table.live_rows(snap).subset(new, self._table.slot)
        truth, sensed = self._sense(snap, rows)
        new_obs = self._observe(snap, rows, sensed, dicts)
        self._remember_new(snap, rows, truth)
        return new_obs

    def _remember_new(self, snap: TrafficSnapshot, rows: Rows, truth: PerceptionFrame) -> None:
        """Add entering agents (``rows``, their ground truth ``truth``) to the memory.

        Ground truth is per agent (same snapshot, same route), so the other agents' views come
        from this step's instead of sensing and searching for everyone again; the noise
        generator still advances as that second full ``sense`` did, so later noise is
        unchanged.
        """
        table = self._table
        all_rows = table.live_rows(snap)
        self._perception.skip_noise(len(all_rows), self._noise_rng)
        step_rows, step_views = self._step_views
        n_step = len(step_rows.ids)
        at = table.by_slot(step_rows.slots, np.arange(n_step))
        at[rows.slots] = n_step + np.arange(len(rows.ids))  # entering: their new route wins
        entering = StepViews.of(snap, truth, rows.r)
        self._remember(snap, all_rows, step_views.joined(entering, at[all_rows.slots]))

    def observation_batch(self, agents: Sequence[str] | None = None) -> dict[str, np.ndarray]:
        """``{key: (A, ...)}`` the observations of ``agents`` (default: the live agents) as the
        last reset or step returned them, stacked in that order: for batched policies. Taken
        from the arrays the step built for all agents at once, so it saves stacking the
        per-agent dicts; equal to stacking them."""
        agents = list(self.agents if agents is None else agents)
        return self._batches.gather(agents, lambda a: self._batches.last_obs(a) or self._empty_obs)

    # ------------------------------------------------------------------ metrics, render, close
    def episode_metrics(self, copy: int = 0) -> dict[str, float | None]:
        """Every DESIGN §9 metric of the episode so far (keys of ``schema.METRICS``), of copy
        ``copy`` (``EnvConfig.copies``: each copy is its own episode)."""
        return self._rec.episode_metrics(copy)

    def flow_diagnostics(self, copy: int | None = None) -> dict[str, float | int | None]:
        """Flow figures of the episode beyond the metric catalogue (delay indices, free-flow
        time, vehicles seen, steps; with a fleet pool, its trips and waits), of one ``copy``
        or, None, of every vehicle."""
        return self._rec.flow_diagnostics(copy, self._boundary)

    def trajectories(self) -> dict[str, np.ndarray]:
        """With ``trace=True``: every vehicle's time ``t`` [s], position ``s`` [m] along the
        measurement segment and speed ``v`` [m/s] every ``TRACE_INTERVAL`` after warm-up."""
        return self._rec.trajectories()

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array" or self._snap is None:
            return None
        from mixed_traffic.env.render import Renderer

        self._renderer = self._renderer or Renderer(self.hdmap)
        rows = self._table.live_rows(self._snap)  # centred on the first agent, if any
        return self._renderer.draw(self._snap, rows.r[0] if rows else None, self._tls)

    def close(self) -> None:
        self._backend.close()
        shutil.rmtree(self._tmp, ignore_errors=True)
        self._phase = "closed"

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.close()

    def __setstate__(self, state: dict[str, Any]) -> None:
        """A copy (pickle, e.g. SuperSuit's ``concat_vec_envs``) gets its own scratch directory,
        so copies neither overwrite each other's route file nor delete it on close."""
        self.__dict__.update(state)
        self._tmp = scratch_dir()


def parallel_env(**kwargs: Any) -> MixedTrafficEnv:
    """The PettingZoo ParallelEnv; keywords are ``EnvConfig`` fields (or ``config=``)."""
    return MixedTrafficEnv(**kwargs)


def env(**kwargs: Any):
    """The AEC version of ``parallel_env`` (via ``parallel_to_aec``)."""
    return parallel_to_aec(parallel_env(**kwargs))
