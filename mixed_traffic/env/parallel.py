"""MixedTrafficEnv: a PettingZoo ParallelEnv in which the AVs of a SUMO simulation are agents.

MDP (DESIGN §3, §6-§9; paper §III-IV)
-------------------------------------
Agents
    ``possible_agents = av_0 … av_{N-1}``: every AV the episode's demand contains (fixed for a
    config). An AV becomes an agent when it enters the network and stops being one when it
    arrives (terminated, ``event="arrived"``), collides or commits another terminal event;
    ids are never reused within an episode. ``fixed_fleet=True``: all AVs are agents from
    reset until truncation; an AV that arrives or fails re-enters upstream under the same id
    (a failure still gives its penalty and ``event``), and an AV waiting to re-enter gets the
    empty observation (only ``follow`` allowed) and its actions are ignored.
Observation
    ``Dict(ego (z,5), lanes (3,z,4m), vehicles (3,z,12), lights (3,z,4), node_mask (3,3),
    action_mask (3,))``, see ``mixed_traffic.sensing.observation`` for features and scales. Sensors
    (LiDAR vehicles, camera lights, GNSS/IMU ego) apply the weather preset's noise and
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
    r3_comfort, r4_impact (``mixed_traffic.env.reward``).
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
``"human"`` (sumo-gui, needs a display); ``warmup`` [s] before flow metrics count.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from functools import cached_property
from itertools import compress, repeat
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv
from pettingzoo.utils.conversions import parallel_to_aec

from mixed_traffic.config import EnvConfig
from mixed_traffic.env import reward as rw
from mixed_traffic.env.action import action_space, stack_actions, to_physical
from mixed_traffic.env.control import BicycleController
from mixed_traffic.env.metrics import AVMetrics, AVStep, FlowRecorder
from mixed_traffic.schema import METRICS
from mixed_traffic.sensing.observation import ObservationBuilder, observation_space
from mixed_traffic.sensing.perception import (
    CURRENT,
    Neighbours,
    Perception,
    PerceptionFrame,
    bumper_gap,
    ttc,
)
from mixed_traffic.world.backend import SumoBackend
from mixed_traffic.world.boundary import PeriodicBoundary
from mixed_traffic.world.registry import (
    check_density,
    load_scenario,
    make_demand,
    sumo_args,
    write_demand,
)
from mixed_traffic.world.snapshot import TrafficSnapshot

FOLLOW = 1


@dataclass
class _AgentState:
    """Ground truth of the live agents kept from one step to the next, aligned with ``ids``."""

    ids: list[str] = field(default_factory=list)
    slots: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    """(A,) agent number of each id (``av_i`` -> i)."""
    accel: np.ndarray = field(default_factory=lambda: np.zeros(0))
    lane: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    edge: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    next_edge: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    front_gap: np.ndarray = field(default_factory=lambda: np.zeros(0))
    rear_ids: list[str] = field(default_factory=list)
    rear_speed: np.ndarray = field(default_factory=lambda: np.zeros(0))


class _Rows(dict):
    """Agent -> snapshot row of the live agents (in agent order), with the same as arrays.

    Built once per (snapshot, agent set) so the stages index arrays instead of looping over ids.
    """

    def __init__(self, items: dict[str, int], slot: dict[str, int], pos: list[int]) -> None:
        super().__init__(items)
        n = len(items)
        self.ids: list[str] = list(items)
        self.r = np.fromiter(items.values(), np.int64, n)
        """(A,) snapshot rows."""
        self.slots = np.fromiter(map(slot.__getitem__, self.ids), np.int64, n)
        """(A,) agent numbers."""
        self.pos = np.asarray(pos, np.int64)
        """(A,) position of each agent in ``env.agents`` (the order of stacked actions)."""

    def subset(self, ids: list[str], slot: dict[str, int]) -> _Rows:
        return _Rows({a: self[a] for a in ids}, slot, [])


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
        warmup: float = 0.0,
        **kwargs: Any,
    ) -> None:
        if config is not None and kwargs:
            raise ValueError(
                f"pass either config=EnvConfig(...) or keyword fields, not both: {sorted(kwargs)}"
            )
        self.config = cfg = config if config is not None else EnvConfig(**kwargs)
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(
                f"render_mode={render_mode!r} is not one of {self.metadata['render_modes']}"
            )
        if render_mode == "human":
            _check_gui()
        self.render_mode = render_mode
        self.scenario = load_scenario(cfg.scenario)
        check_density(self.scenario, cfg.density)
        self.hdmap = self.scenario.hdmap
        self.warmup = warmup
        demand = make_demand(self.scenario, cfg, np.random.default_rng(cfg.seed))
        self.possible_agents = sorted(demand.av_ids, key=lambda a: int(a[3:]))
        # agent number: index into the per-agent tables (route table, per-slot scratch arrays)
        self._slot = {a: i for i, a in enumerate(self.possible_agents)}
        self._obs_space = observation_space(cfg)
        self._act_space = action_space()
        self._perception = Perception(cfg.sensors, self.hdmap, cfg.weather)
        self._controller = BicycleController(cfg.vehicle, self.hdmap, cfg.step_length)
        self._builder = ObservationBuilder(cfg, self.hdmap)
        self._backend = SumoBackend("traci" if render_mode == "human" else cfg.backend, cfg.second_instance,
                                    gui=render_mode == "human")  # fmt: skip
        self._backend.set_lane_table(self.hdmap.lane_ids, self.hdmap.lane_edge)
        self._tmp = tempfile.mkdtemp(prefix="mixed_traffic_")
        self._episode_rng = np.random.default_rng(cfg.seed)
        self.agents: list[str] = []
        self._snap: TrafficSnapshot | None = None

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
        if seed is None:
            seed = int(self._episode_rng.integers(2**31 - 1))
        cfg = replace(self.config, seed=int(seed))
        demand_seed, sumo_seed, noise_seed = np.random.SeedSequence(int(seed)).generate_state(3)
        demand = make_demand(self.scenario, cfg, np.random.default_rng(demand_seed))
        route_file = Path(self._tmp) / "demand.rou.xml"
        write_demand(demand, cfg, route_file)
        self._backend.start(sumo_args(self.scenario, cfg, route_file, seed=int(sumo_seed) % 2**31))
        self._boundary = PeriodicBoundary.for_demand(
            self.scenario, demand, cfg.vehicle, cfg.step_length, cfg.fixed_fleet
        )
        self._noise_rng = np.random.default_rng(noise_seed)
        self._controller.reset()
        self._builder.reset()
        self._flow = FlowRecorder(
            self.hdmap, self.scenario.measurement, cfg.step_length, self.warmup
        )
        self._av = AVMetrics(cfg.step_length, cfg.reward.rear_speed_drop)
        self._routes: dict[str, np.ndarray] = {}
        # routes by agent number, -1 padded (filled on admission, so no per-step padding)
        n = len(self.possible_agents)
        self._route_table = np.full((n, 1), -1, dtype=np.int64)
        self._route_len = np.zeros(n, dtype=np.int64)
        self._rows_key: tuple = ()
        self._rows_cache: _Rows | None = None
        self._decision_by_slot = np.full(n, FOLLOW, dtype=np.int64)
        self._finished: set[str] = set()
        self._last_obs: dict[str, dict] = {}
        self._state = _AgentState()
        self.agents = list(self.possible_agents) if cfg.fixed_fleet else []
        snap = self._advance()
        self._backend.drop_pending(demand.placed_ids)
        return self._start_from(snap), {a: {} for a in self.agents}

    def _start_from(self, snap: TrafficSnapshot) -> dict[str, dict]:
        """Admit the AVs of ``snap`` and observe them, as at the start of an episode."""
        self._admit(snap)
        rows = self._live_rows(snap)
        truth, sensed = self._sense(snap, rows)
        self._remember(snap, rows, truth)
        obs = self._observe(snap, rows, sensed)
        self._snap = snap
        return {a: obs.get(a, self._empty_obs) for a in self.agents}

    # ------------------------------------------------------------------ step
    def step(self, actions: dict[str, Any]):
        decision, params = stack_actions(actions, self.agents, self._act_space)  # action
        steer, accel = to_physical(decision, params, self.config.vehicle)
        cmd = self._control(steer, accel, decision)  # control
        snap = self._advance()  # SUMO step + density boundary
        rows = self._live_rows(snap)
        truth, sensed = self._sense(snap, rows)  # perception
        events = self._events(snap, rows, cmd)  # termination
        rewards, terms, changed = self._rewards(snap, rows, truth, events)  # reward
        self._record(snap, rows, truth, rewards, changed)  # metrics
        self._remember(snap, rows, truth)
        obs = self._observe(snap, rows, sensed)  # observation
        self._step_truth = (rows, truth)  # reused if agents enter in _finish
        return self._finish(snap, obs, rewards, terms, events)

    # ------------------------------------------------------------------ stages
    def _control(self, steer: np.ndarray, accel: np.ndarray, decision: np.ndarray):
        """Bicycle model -> SUMO for every agent present in the simulation."""
        rows = self._live_rows(self._snap)
        acting = rows.pos  # agents in the simulation, in agent order
        self._decision_by_slot.fill(FOLLOW)  # agents that did not act count as following
        self._decision_by_slot[rows.slots] = decision[acting]
        return self._controller.step(
            self._backend, self._snap, rows.ids, steer[acting], accel[acting]
        )

    def _advance(self) -> TrafficSnapshot:
        """One SUMO step; the boundary replaces vehicles that left; flow metrics."""
        snap = self._backend.step()
        self._boundary.step(snap, self._backend)
        self._flow.update(snap)
        ids = self._perception.tls_ids
        self._tls = dict(zip(ids, self._backend.tls_states(ids)))
        return snap

    def _admit(self, snap: TrafficSnapshot) -> list[str]:
        """Start controlling AVs that (re-)entered the network; returns their ids."""
        avs = list(compress(snap.ids, snap.is_av.tolist()))
        fresh = set(avs).difference(self._controller.tracked, self._finished)
        if not fresh:  # the usual step: set operations only, no per-vehicle Python loop
            return []
        new = [v for v in avs if v in fresh]  # in snapshot order
        self._controller.add_from_snapshot(snap, new, self._backend)
        for a in new:
            edges = self._backend.vehicle_route(a)
            route = np.array([self.hdmap.edge_row.get(e, -1) for e in edges], dtype=np.int64)
            self._routes[a] = route
            self._set_route(self._slot[a], route)
        self._builder.drop(new)
        if not self.config.fixed_fleet:
            self.agents += new
        return new

    def _set_route(self, slot: int, route: np.ndarray) -> None:
        """Store an admitted agent's route in the table (widened when a route is longer)."""
        table = self._route_table
        if len(route) > table.shape[1]:
            wider = np.full((len(table), len(route)), -1, dtype=np.int64)
            wider[:, : table.shape[1]] = table
            self._route_table = table = wider
        table[slot] = -1
        table[slot, : len(route)] = route
        self._route_len[slot] = len(route)

    def _next_edge(self, slots: np.ndarray, route_index: np.ndarray) -> np.ndarray:
        """``next_route_edge`` from the route table: (A,) next edge row, -1 on the last edge."""
        k = np.asarray(route_index, np.int64) + 1
        ok = (k >= 0) & (k < self._route_len[slots])
        width = self._route_table.shape[1]
        return np.where(ok, self._route_table[slots, np.clip(k, 0, width - 1)], -1)

    def _live_rows(self, snap: TrafficSnapshot) -> _Rows:
        """Snapshot row of every admitted agent present in the simulation, in agent order.

        With ``fixed_fleet`` an AV that was still waiting to enter at reset is an agent before
        ``_admit`` has seen it: it only counts once admitted (its route is known). Cached until
        the snapshot, the agent list or the admitted set changes (several stages ask per step).
        """
        agents, routes = self.agents, self._routes
        # by content: _finish rebuilds the agent list every step, usually with the same agents
        key = (tuple(agents), len(routes))
        if self._rows_key and self._rows_key[0] is snap and self._rows_key[1:] == key:
            return self._rows_cache
        index = snap.index_of()
        pos = [i for i, a in enumerate(agents) if a in index and a in routes]
        rows = _Rows({agents[i]: index[agents[i]] for i in pos}, self._slot, pos)
        self._rows_key, self._rows_cache = (snap, *key), rows
        return rows

    def _sense(self, snap: TrafficSnapshot, rows: _Rows) -> tuple[PerceptionFrame, PerceptionFrame]:
        r = rows.r
        nxt = self._next_edge(rows.slots, snap.route_index[r])
        tls = [self._tls[t] for t in self._perception.tls_ids]
        return self._perception.sense(snap, r, nxt, tls, self._noise_rng)

    def _events(self, snap: TrafficSnapshot, rows: _Rows, cmd) -> dict[str, str]:
        """'arrived', a terminal reason, or '' for every agent that acted."""
        prev, hd = self._state, self.hdmap
        crashed = (
            rw.collided_mask(prev.ids, snap.collisions)
            if snap.collisions
            else repeat(False, len(prev.ids))
        )
        arrived = set(snap.arrived)
        events = {
            a: "collision" if c else "arrived" if a in arrived else ""
            for a, c in zip(prev.ids, crashed)
        }
        if not events:
            return events
        now = self._by_slot(rows.slots, rows.r)[prev.slots]  # row now, -1 if gone
        fine = np.fromiter(map(events.__getitem__, prev.ids), object, len(prev.ids)) == ""
        p = np.flatnonzero((now >= 0) & fine)
        if not len(p):
            return events
        ids = [prev.ids[i] for i in p.tolist()]
        r = now[p]
        # SUMO clamps lateral moves to the road: judge off-road by the commanded position
        lateral = self._aligned(cmd.ids, cmd.intended_lateral, prev.slots[p], snap.lateral[r])
        reasons = rw.terminal_events(
            collision=np.zeros(len(r), bool),
            off_road=rw.off_road_mask(hd, prev.lane[p], lateral),
            route_deviation=rw.route_deviation_mask(hd, snap.edge[r], snap.lane[r], snap.lane_pos[r],
                                                    self._route_table[prev.slots[p]], snap.route_index[r]),
            red_light=rw.red_light_mask(hd, prev.lane[p], snap.lane[r], prev.next_edge[p], self._tls_prev),
            speed_limit=rw.speed_limit_mask(snap.speed[r], hd.lane_speed[snap.lane[r]], self.config.speed_tolerance),
        )  # fmt: skip
        events.update(zip(ids, reasons.tolist()))
        return events

    def _by_slot(self, slots: np.ndarray, values: np.ndarray, fill: Any = -1) -> np.ndarray:
        """(n_agents,) table with ``values`` at ``slots`` and ``fill`` elsewhere (id lookups
        become array indexing)."""
        values = np.asarray(values)
        out = np.full(len(self.possible_agents), fill, dtype=values.dtype)
        out[slots] = values
        return out

    def _aligned(
        self, cmd_ids: list[str], values: np.ndarray, slots: np.ndarray, default: np.ndarray
    ) -> np.ndarray:
        """``values`` (ordered as ``cmd_ids``) at the agents ``slots``; ``default`` where absent."""
        cmd = np.fromiter(map(self._slot.__getitem__, cmd_ids), np.int64, len(cmd_ids))
        at = self._by_slot(cmd, np.arange(len(cmd)))[slots]
        vals = np.asarray(values, np.float64)
        out = np.array(default, dtype=np.float64, copy=True)
        out[at >= 0] = vals[at[at >= 0]]
        return out

    def _rewards(
        self,
        snap: TrafficSnapshot,
        rows: _Rows,
        truth: PerceptionFrame,
        events: dict[str, str],
    ):
        """Reward, named terms and completed lane changes (bool per agent number) of every
        agent that acted."""
        prev, cfg, hd = self._state, self.config, self.hdmap
        rewards: dict[str, float] = {}
        terms_out: dict[str, dict[str, float]] = {}
        failed = {a for a, e in events.items() if e not in ("", "arrived")}
        now = self._by_slot(rows.slots, rows.r)[prev.slots]  # row now, -1 if gone
        for i in np.flatnonzero(now < 0).tolist():
            # left the network this step: only the terminal penalty applies
            a = prev.ids[i]
            t = dict.fromkeys(rw.TERM_NAMES, 0.0)
            t["r1_terminal"] = cfg.reward.terminal_penalty if a in failed else 0.0
            terms_out[a], rewards[a] = t, cfg.reward.w_safety * t["r1_terminal"]
        p = np.flatnonzero(now >= 0)
        if not len(p):
            return rewards, terms_out, self._by_slot(p, np.zeros(0, bool), False)
        ids = [prev.ids[i] for i in p.tolist()]
        r = now[p]
        # truth was sensed in the order of rows
        k = self._by_slot(rows.slots, np.arange(len(rows.r)))[prev.slots[p]]
        front = _FrontView(snap, truth, k, r)
        rear_now = _speeds_of(snap, [prev.rear_ids[i] for i in p.tolist()])
        lane = snap.lane[r]
        changed = rw.lane_change_completed(prev.lane[p], lane, prev.edge[p], snap.edge[r])
        terms = rw.reward_terms(
            cfg.reward, cfg.step_length,
            front_distance=front.distance, closing_speed=front.closing, length=snap.length[r],
            front_length=front.length,
            centre_distance=rw.centreline_distance(hd, lane, snap.lane_pos[r], snap.x[r], snap.y[r]),
            lane_width=hd.lane_width[lane], terminal=np.fromiter(map(failed.__contains__, ids), bool, len(ids)),
            speed=snap.speed[r], speed_limit=hd.lane_speed[lane],
            lane_changed=changed, gap_new=front.gap, gap_old=prev.front_gap[p],
            lidar_range=cfg.sensors.lidar_range, accel=snap.accel[r], prev_accel=prev.accel[p],
            rear_speed_prev=prev.rear_speed[p], rear_speed_now=rear_now, rear_same=~np.isnan(rear_now),
        )  # fmt: skip
        total = rw.total_reward(terms, cfg.reward)
        names = list(terms)
        columns = [np.asarray(v, np.float64).tolist() for v in terms.values()]
        # one {term: value} dict per agent, built by C-level maps (hundreds of agents per step)
        terms_out.update(zip(ids, map(dict, map(zip, repeat(names), zip(*columns)))))
        rewards.update(zip(ids, np.asarray(total, np.float64).tolist()))
        return rewards, terms_out, self._by_slot(prev.slots[p], np.asarray(changed, bool), False)

    def _record(self, snap, rows: _Rows, truth: PerceptionFrame, rewards: dict[str, float],
                changed: np.ndarray) -> None:  # fmt: skip
        """Per-AV metrics of this step (flow metrics are recorded in ``_advance``)."""
        ids, r, n = rows.ids, rows.r, len(rows.ids)
        front = _FrontView(snap, truth, np.arange(len(r)), r)
        rear_ids, rear_speed = _rear_conventional(snap, truth)
        prev = self._state
        pi = self._by_slot(prev.slots, np.arange(len(prev.ids)))[rows.slots]  # -1: new agent
        prev_accel = np.where(pi >= 0, _take(prev.accel, pi), snap.accel[r])
        # the same conventional vehicle C behind the agent as at the previous step
        rear_now = np.array(rear_ids, dtype=object)
        rear_before = np.array([*prev.rear_ids, ""], dtype=object)[pi]  # pi = -1 -> ""
        same = (pi >= 0) & (rear_now != "") & (rear_before == rear_now)
        self._av.step(
            AVStep(ids=ids, speed=snap.speed[r], accel=snap.accel[r], prev_accel=prev_accel,
                   lateral=snap.lateral[r],
                   following=self._decision_by_slot[rows.slots] == FOLLOW,
                   lane_changed=changed[rows.slots],
                   ttc=np.where(front.exists, ttc(front.gap, front.closing), np.inf),
                   rear_ids=rear_ids, rear_speed=np.nan_to_num(rear_speed),
                   rear_prev_speed=np.where(same, _take(prev.rear_speed, pi), np.nan),
                   reward=np.fromiter(map(rewards.get, ids, repeat(0.0)), np.float64, n)),
            snap.time,
            _SpeedView(snap),
        )  # fmt: skip

    def _remember(self, snap: TrafficSnapshot, rows: _Rows, truth: PerceptionFrame) -> None:
        """Ground truth of this step that the next step's events and rewards compare against."""
        r = rows.r
        rear_ids, rear_speed = _rear_conventional(snap, truth)
        self._state = _AgentState(
            ids=rows.ids, slots=rows.slots, accel=snap.accel[r].copy(), lane=snap.lane[r].astype(np.int64),
            edge=snap.edge[r].astype(np.int64),
            next_edge=self._next_edge(rows.slots, snap.route_index[r]),
            front_gap=_FrontView(snap, truth, np.arange(len(r)), r).gap, rear_ids=rear_ids, rear_speed=rear_speed,
        )  # fmt: skip
        self._tls_prev = dict(self._tls)

    def _observe(self, snap, rows: _Rows, sensed: PerceptionFrame) -> dict[str, dict]:
        ids = rows.ids
        routes = list(map(self._routes.__getitem__, ids))
        obs = self._builder.build(snap, ids, rows.r, sensed, routes) if ids else {}
        self._last_obs.update(obs)
        return obs

    def _finish(self, snap, obs, rewards, terms, events):
        """Retire finished agents, admit new ones, and assemble the PettingZoo dicts."""
        cfg = self.config
        done = sorted(a for a, e in events.items() if e)
        for a in done:
            self._av.end_trip(a, events[a])
            if events[a] not in ("arrived", "collision"):
                self._backend.remove(a)  # SUMO already removed arrived and collided vehicles
        removed = [a for a in done if events[a] not in ("arrived", "collision")]
        self._boundary.replace(self._backend, removed)
        self._controller.remove(done)
        truncate = snap.time >= cfg.episode_length - 1e-9
        agents = list(self.agents)
        # per-agent dicts of the API, filled by C-level maps and patched where an event happened
        ended = [] if cfg.fixed_fleet else list(set(done).intersection(agents))
        terminated = dict.fromkeys(agents, False)
        terminated.update(dict.fromkeys(ended, True))
        truncated = dict.fromkeys(agents, truncate)
        truncated.update(dict.fromkeys(ended, False))
        infos = {a: {"reward_terms": t if t is not None else {}, "event": e}
                 for a, t, e in zip(agents, map(terms.get, agents), map(events.get, agents, repeat("")))}  # fmt: skip
        obs_out = dict(zip(agents, map(obs.get, agents)))
        for a in [a for a, o in obs_out.items() if o is None]:  # not observed this step
            obs_out[a] = self._last_obs.get(a, self._empty_obs)
        rew_out = dict(zip(agents, map(rewards.get, agents, repeat(0.0))))
        if not cfg.fixed_fleet:
            self._finished.update(done)
            self.agents = [a for a in agents if not terminated[a]]
        new = [] if truncate else self._admit(snap)  # nobody enters at the time limit
        if new:
            rows = self._live_rows(snap).subset(new, self._slot)
            truth, sensed = self._sense(snap, rows)
            new_obs = self._observe(snap, rows, sensed)
            self._remember_new(snap, rows, truth)
            for a in new:
                if a not in obs_out or cfg.fixed_fleet:
                    obs_out[a], rew_out[a] = new_obs[a], rew_out.get(a, 0.0)
                    terminated[a], truncated[a] = False, False
                    infos.setdefault(a, {"reward_terms": {}, "event": ""})["event"] = "entered"
        if truncate:
            self.agents = []
            summary = self.episode_metrics()
            for info in infos.values():
                info["episode"] = summary
        self._snap = snap
        return obs_out, rew_out, terminated, truncated, infos

    def _remember_new(self, snap: TrafficSnapshot, rows: _Rows, truth: PerceptionFrame) -> None:
        """Add entering agents (``rows``, their ground truth ``truth``) to the per-agent memory
        (they act from the next step on).

        Ground truth is per agent (same snapshot, same route), so the other agents' rows come
        from this step's perception instead of sensing everyone again; the noise generator
        still advances as that second full ``sense`` did, so later noise is unchanged.
        """
        all_rows = self._live_rows(snap)
        self._perception.skip_noise(len(all_rows), self._noise_rng)
        step_rows, step_truth = self._step_truth
        n_step = len(step_rows.ids)
        at = self._by_slot(step_rows.slots, np.arange(n_step))
        at[rows.slots] = n_step + np.arange(len(rows.ids))  # entering: their new route wins
        self._remember(snap, all_rows, _gather(step_truth, truth, at[all_rows.slots]))

    @cached_property
    def _empty_obs(self) -> dict[str, np.ndarray]:
        obs = {k: np.zeros(s.shape, s.dtype) for k, s in self._obs_space.spaces.items()}
        obs["action_mask"][FOLLOW] = 1
        return obs

    # ------------------------------------------------------------------ metrics, render, close
    def episode_metrics(self) -> dict[str, float | None]:
        """Every DESIGN §9 metric of the episode so far (keys of ``schema.METRICS``)."""
        out: dict[str, Any] = dict.fromkeys(METRICS)
        out.update(self._flow.summary())
        out.update(self._av.summary())
        di = self._flow.delay_index(sorted(self._av.rear_vehicles))
        di = di[np.isfinite(di)] if len(di) else di
        out["avg_di_c"] = float(np.mean(di)) if len(di) else None
        return out

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array" or self._snap is None:
            return None
        from mixed_traffic.env.render import Renderer

        if not hasattr(self, "_renderer"):
            self._renderer = Renderer(self.hdmap)
        snap = self._snap
        centre = None
        rows = self._live_rows(snap)
        if rows:
            i = next(iter(rows.values()))
            centre = np.array([snap.x[i], snap.y[i]])
        return self._renderer.draw(snap, centre, self._tls)

    def close(self) -> None:
        self._backend.close()
        shutil.rmtree(self._tmp, ignore_errors=True)

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.close()

    def __setstate__(self, state: dict[str, Any]) -> None:
        """A copy (pickle, e.g. SuperSuit's ``concat_vec_envs``) gets its own scratch directory,
        so copies neither overwrite each other's route file nor delete it on close."""
        self.__dict__.update(state)
        self._tmp = tempfile.mkdtemp(prefix="mixed_traffic_")


class _FrontView:
    """Ground-truth front vehicle in the current lane for agents at truth rows ``k``, snapshot rows ``r``."""

    def __init__(
        self, snap: TrafficSnapshot, truth: PerceptionFrame, k: np.ndarray, r: np.ndarray
    ) -> None:
        nb = truth.neighbours
        row = nb.front[k, CURRENT]
        self.exists = row >= 0
        self.distance = nb.front_dist[k, CURRENT]
        # from the ground-truth features: a vehicle across the path is measured in its frame
        feats = truth.vehicles[k, CURRENT, 0]
        self.length = np.where(self.exists, feats[:, 3], 0.0)
        self.closing = np.where(self.exists, -feats[:, 1], snap.speed[r])
        self.gap = bumper_gap(self.distance, snap.length[r], self.length)


def _gather(a: PerceptionFrame, b: PerceptionFrame, idx: np.ndarray) -> PerceptionFrame:
    """Rows ``idx`` of the frames ``a`` and ``b`` stacked (a's agents first)."""
    if (idx < 0).any():
        raise RuntimeError("an agent's ground truth is missing")  # would be a bug in _finish

    def cat(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.concatenate([x, y])[idx]

    na, nb = a.neighbours, b.neighbours
    return PerceptionFrame(
        Neighbours(cat(na.lane, nb.lane), cat(na.vehicle, nb.vehicle), cat(na.distance, nb.distance)),
        cat(a.vehicles, b.vehicles), cat(a.ego, b.ego), cat(a.light_state, b.light_state),
        cat(a.light_dist, b.light_dist),
    )  # fmt: skip


def _rear_conventional(
    snap: TrafficSnapshot, truth: PerceptionFrame
) -> tuple[list[str], np.ndarray]:
    """C, the conventional vehicle behind each agent in its lane ('' if none or an AV), and its speed."""
    rear = truth.neighbours.rear[:, CURRENT]
    ok = (rear >= 0) & ~snap.is_av[np.maximum(rear, 0)]
    ids = [""] * len(rear)
    for k in np.flatnonzero(ok).tolist():
        ids[k] = snap.ids[rear[k]]
    return ids, np.where(ok, snap.speed[np.maximum(rear, 0)], np.nan)


def _speeds_of(snap: TrafficSnapshot, ids: list[str]) -> np.ndarray:
    """Speed of each vehicle id now, nan if it is not in the network (or '')."""
    k = np.fromiter(map(snap.index_of().get, ids, repeat(-1)), np.int64, len(ids))
    return np.where(k >= 0, snap.speed[np.maximum(k, 0)], np.nan) if len(k) else np.zeros(0)


class _SpeedView(Mapping):
    """Vehicle id -> speed now [m/s], read from the snapshot on demand (no per-step dict)."""

    def __init__(self, snap: TrafficSnapshot) -> None:
        self._index, self._speed = snap.index_of(), snap.speed

    def __getitem__(self, vid: str) -> float:
        return float(self._speed[self._index[vid]])

    def __contains__(self, vid: object) -> bool:
        return vid in self._index

    def __iter__(self):
        return iter(self._index)

    def __len__(self) -> int:
        return len(self._index)


def _take(values: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """values[idx] with idx = -1 giving nan (also for an empty ``values``)."""
    out = np.full(len(idx), np.nan)
    ok = idx >= 0
    out[ok] = values[idx[ok]]
    return out


def _check_gui() -> None:
    from mixed_traffic.world.backend import binary

    if not os.environ.get("DISPLAY"):
        raise ValueError("render_mode='human' needs sumo-gui and a display (DISPLAY is not set); "
                         "use render_mode='rgb_array' for headless rendering")  # fmt: skip
    binary("sumo-gui")


def parallel_env(**kwargs: Any) -> MixedTrafficEnv:
    """The PettingZoo ParallelEnv; keywords are ``EnvConfig`` fields (or ``config=``)."""
    return MixedTrafficEnv(**kwargs)


def env(**kwargs: Any):
    """The AEC version of ``parallel_env`` (via ``parallel_to_aec``)."""
    return parallel_to_aec(parallel_env(**kwargs))
