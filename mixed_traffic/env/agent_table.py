"""Agent ids, slots and routes, and their alignment with the rows of a snapshot.

Every agent has a fixed *slot*: its index in ``possible_agents`` (``av_i`` -> i). Per-agent
tables (routes, decisions, the memory of the previous step) are arrays indexed by slot, so the
stages of a step line agents up by array indexing instead of looping over ids. ``Rows`` is the
view of the live agents at one snapshot: their ids, snapshot rows, slots and positions in
``agents`` (the order of stacked actions).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mixed_traffic.world.snapshot import TrafficSnapshot

FOLLOW = 1


class Rows(dict):
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
        """(A,) position of each agent in ``agents`` (the order of stacked actions)."""

    def subset(self, ids: list[str], slot: dict[str, int]) -> Rows:
        return Rows({a: self[a] for a in ids}, slot, [])


@dataclass
class StepMemory:
    """Ground truth of the live agents kept from one step to the next, aligned with ``ids``."""

    ids: list[str] = field(default_factory=list)
    slots: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    """(A,) agent number of each id (``av_i`` -> i)."""
    accel: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """(A,) acceleration [m/s²]."""
    lane: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    """(A,) lane row."""
    edge: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    """(A,) edge row (-1 inside a junction)."""
    next_edge: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    """(A,) next edge row of the route (-1 on the last edge)."""
    front_gap: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """(A,) bumper gap to the front vehicle [m] (+inf if none)."""
    rear_ids: list[str] = field(default_factory=list)
    """The conventional vehicle C behind each agent ('' if none)."""
    rear_speed: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """(A,) speed of C [m/s] (nan if none)."""


class AgentTable:
    """The agents of one env: the live list, the slots, the routes, and who has finished.

    Args:
        possible_agents: every agent id the config can produce, ``av_0 … av_{N-1}``.
    """

    def __init__(self, possible_agents: list[str]) -> None:
        self.possible_agents = possible_agents
        self.slot = {a: i for i, a in enumerate(possible_agents)}
        """Agent id -> slot (index into the per-agent tables)."""
        n = len(possible_agents)
        self.agents: list[str] = []
        """Live agents, in admission order (PettingZoo's ``env.agents``)."""
        self.finished: set[str] = set()
        """Agents whose trip ended (never re-admitted within the episode)."""
        self.released: set[str] = set()
        """AVs handed back to SUMO instead of becoming agents (``sumo_drives_avs``)."""
        self.routes: dict[str, np.ndarray] = {}
        """Admitted agent -> (R,) edge rows of its route."""
        self.route_table = np.full((n, 1), -1, dtype=np.int64)
        """(n, W) routes by slot, -1 padded (filled on admission: no per-step padding)."""
        self.route_len = np.zeros(n, dtype=np.int64)
        """(n,) route lengths by slot."""
        self.decision = np.full(n, FOLLOW, dtype=np.int64)
        """(n,) decision of the last step by slot (follow for agents that did not act)."""
        self._rows_key: tuple = ()
        self._rows: Rows | None = None
        self._admissions = 0
        """Changes of the admitted set (the ``live_rows`` cache key)."""

    def reset(self, agents: list[str]) -> None:
        """Start an episode with ``agents`` live (all of them with a fixed fleet, else none)."""
        self.agents = agents
        self.finished, self.released, self.routes = set(), set(), {}
        self.route_table = np.full((len(self.possible_agents), 1), -1, dtype=np.int64)
        self.route_len[:] = 0
        self.decision[:] = FOLLOW
        self._rows_key, self._rows = (), None

    def __len__(self) -> int:
        return len(self.possible_agents)

    def set_route(self, agent: str, route: np.ndarray) -> None:
        """Store an admitted agent's route (the table widens when a route is longer)."""
        self.routes[agent] = route
        self._admissions += 1
        slot, table = self.slot[agent], self.route_table
        if len(route) > table.shape[1]:
            wider = np.full((len(table), len(route)), -1, dtype=np.int64)
            wider[:, : table.shape[1]] = table
            self.route_table = table = wider
        table[slot] = -1
        table[slot, : len(route)] = route
        self.route_len[slot] = len(route)

    def end_trip(self, agent: str) -> None:
        """``agent`` is no longer on the road: not live until admitted again."""
        if self.routes.pop(agent, None) is not None:
            self._admissions += 1

    def next_edge(self, slots: np.ndarray, route_index: np.ndarray) -> np.ndarray:
        """(A,) next edge row of each agent's route after ``route_index`` (A,), -1 on the last."""
        k = np.asarray(route_index, np.int64) + 1
        ok = (k >= 0) & (k < self.route_len[slots])
        width = self.route_table.shape[1]
        return np.where(ok, self.route_table[slots, np.clip(k, 0, width - 1)], -1)

    def live_rows(self, snap: TrafficSnapshot) -> Rows:
        """Snapshot row of every admitted agent present in the simulation, in agent order.

        With a fixed fleet an AV still waiting to enter at reset is an agent before it was
        admitted: it only counts once admitted (its route is known). Cached until the snapshot,
        the agent list or the admitted set changes (several stages ask per step).
        """
        agents, routes = self.agents, self.routes
        # by content: the env rebuilds the agent list every step, usually with the same agents
        key = (tuple(agents), self._admissions)
        if self._rows_key and self._rows_key[0] is snap and self._rows_key[1:] == key:
            return self._rows
        index = snap.index_of()
        pos = [i for i, a in enumerate(agents) if a in index and a in routes]
        rows = Rows({agents[i]: index[agents[i]] for i in pos}, self.slot, pos)
        self._rows_key, self._rows = (snap, *key), rows
        return rows

    def slots_of(self, ids: list[str]) -> np.ndarray:
        """(n,) slots of the agents ``ids``."""
        return np.fromiter(map(self.slot.__getitem__, ids), np.int64, len(ids))

    def by_slot(self, slots: np.ndarray, values: np.ndarray, fill: Any = -1) -> np.ndarray:
        """(n,) table with ``values`` at ``slots`` and ``fill`` elsewhere (id lookups become
        array indexing)."""
        values = np.asarray(values)
        out = np.full(len(self.possible_agents), fill, dtype=values.dtype)
        out[slots] = values
        return out

    def aligned(
        self, ids: list[str], values: np.ndarray, slots: np.ndarray, default: np.ndarray
    ) -> np.ndarray:
        """``values`` (ordered as ``ids``) at the agents ``slots``; ``default`` where absent."""
        at_slot = np.fromiter(map(self.slot.__getitem__, ids), np.int64, len(ids))
        at = self.by_slot(at_slot, np.arange(len(ids)))[slots]
        vals = np.asarray(values, np.float64)
        out = np.array(default, dtype=np.float64, copy=True)
        out[at >= 0] = vals[at[at >= 0]]
        return out
