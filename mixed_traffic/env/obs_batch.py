"""The observations of one step as batches: what a batched policy wants, without stacking the
per-agent dicts of the PettingZoo API again (``MixedTrafficEnv.observation_batch``)."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np

Arrays = Mapping[str, np.ndarray]


class StepBatches:
    """The arrays ``ObservationBuilder.build`` made since the last SUMO step, one part per
    call (the step's agents, then agents that entered), each ``{key: (A_part, ...)}``."""

    def __init__(self) -> None:
        self.parts: list[tuple[list[str], Arrays]] = []

    def clear(self) -> None:
        """A new SUMO step: the parts are stale."""
        self.parts = []

    def add(self, ids: Sequence[str], arrays: Arrays) -> None:
        self.parts.append((list(ids), arrays))

    def gather(self, agents: list[str], single: Callable[[str], Arrays]) -> dict[str, np.ndarray]:
        """``{key: (A, ...)}`` of ``agents`` in that order. The usual step is one part in the
        agents' order (returned as it is); a later part wins for an agent in two; an agent in
        none (a fixed fleet's agent waiting to enter) makes the batch from ``single(agent)``."""
        if len(self.parts) == 1 and self.parts[0][0] == agents:
            return dict(self.parts[0][1])
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
