"""The observations of one step as batches: what a batched policy wants, without stacking the
per-agent dicts of the PettingZoo API again (``MixedTrafficEnv.observation_batch``)."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from itertools import chain, repeat

import numpy as np

Arrays = Mapping[str, np.ndarray]


class StepBatches:
    """The arrays ``ObservationBuilder.build`` made since the last SUMO step, one part per
    call (the step's agents, then agents that entered), each ``{key: (A_part, ...)}``; and
    where each agent's last observation is (``last``: its part's arrays and row)."""

    def __init__(self) -> None:
        self.parts: list[tuple[list[str], Arrays]] = []
        self.last: dict[str, tuple[Arrays, int]] = {}
        self._gathered: tuple[list[str], dict[str, np.ndarray]] | None = None

    def reset(self) -> None:
        """A new episode: no observation yet."""
        self.parts, self.last, self._gathered = [], {}, None

    def clear(self) -> None:
        """A new SUMO step: the parts are stale (the last observations stay)."""
        self.parts, self._gathered = [], None

    def add(self, ids: Sequence[str], arrays: Arrays) -> None:
        self.parts.append((list(ids), arrays))
        self._gathered = None
        self.last.update(zip(ids, zip(repeat(arrays), range(len(ids)))))

    def last_obs(self, agent: str) -> dict[str, np.ndarray] | None:
        """The last observation of ``agent`` as a per-agent dict (views), None if none."""
        at = self.last.get(agent)
        return None if at is None else {k: v[at[1]] for k, v in at[0].items()}

    def forget(self, agents: Sequence[str], keep: bool) -> None:
        """Drop the last observations of ``agents`` (whole steps' arrays are then freed), or
        with ``keep`` replace each by a compact copy (a fixed fleet returns it until the agent
        enters again)."""
        self._gathered = None
        for a in agents:
            at = self.last.pop(a, None)
            if at is not None and keep:
                self.last[a] = ({k: v[at[1] : at[1] + 1].copy() for k, v in at[0].items()}, 0)

    def gather(self, agents: list[str], single: Callable[[str], Arrays]) -> dict[str, np.ndarray]:
        """``{key: (A, ...)}`` of ``agents`` in that order (the arrays are shared: do not
        write into them). The usual step is one part in the agents' order (returned as it
        is), or that and the agents that entered (joined); a later part wins for an agent in
        two; an agent in none (a fixed fleet's agent waiting to enter) makes the batch from
        ``single(agent)``. The last gather is kept until the parts change."""
        if self._gathered is None or self._gathered[0] != agents:
            self._gathered = (list(agents), self._gather(agents, single))
        return dict(self._gathered[1])

    def _gather(self, agents: list[str], single: Callable[[str], Arrays]) -> dict[str, np.ndarray]:
        if len(self.parts) == 1 and self.parts[0][0] == agents:
            return dict(self.parts[0][1])
        if self.parts and list(chain.from_iterable(ids for ids, _ in self.parts)) == agents:
            return {k: np.concatenate([arrays[k] for _, arrays in self.parts])
                    for k in self.parts[0][1]}  # fmt: skip
        offset, where = 0, {}
        for ids, _ in self.parts:
            where.update(zip(ids, range(offset, offset + len(ids))))
            offset += len(ids)
        if not agents:
            return {k: np.zeros((0, *v.shape), v.dtype) for k, v in single("").items()}
        if not all(a in where for a in agents):
            return {k: np.stack([single(a)[k] for a in agents]) for k in single("")}
        idx = np.fromiter(map(where.__getitem__, agents), np.int64, len(agents))
        keys = self.parts[0][1].keys()
        return {k: np.concatenate([arrays[k] for _, arrays in self.parts])[idx] for k in keys}
