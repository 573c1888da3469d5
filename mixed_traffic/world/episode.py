"""What SUMO runs in one episode: the copies of the scenario (``EnvConfig.copies``), their ring
lengths, the demand with its route file, the boundary and the reference speed of each copy.

``Worlds`` is built once per env: it checks that the scenario can be copied and sizes the
agents on the longest ring. ``Worlds.episode`` makes an ``Episode`` at every reset. One copy
draws everything as an env without copies always did. Several copies of a ring whose length
is drawn per reset take one of ``RING_POOL`` joined networks, each with its own draw of
lengths, so that no reset waits for netconvert once a machine has built them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from mixed_traffic.config import EnvConfig
from mixed_traffic.world.boundary import PeriodicBoundary
from mixed_traffic.world.copies import (
    Batch,
    Boundaries,
    batch_boundary,
    batch_demand,
    check_copies,
    check_memory,
    make_batch,
)
from mixed_traffic.world.demand import Demand, av_count, reference_speed, write_demand
from mixed_traffic.world.fleet_pool import FleetPool
from mixed_traffic.world.ring import draw_ring_length, episode_ring, scaled_ring
from mixed_traffic.world.scenario import Scenario

RING_POOL = 8
"""Joined networks of drawn ring lengths per (length range, copies): each reset of a batch of
rings takes one of them."""


@dataclass(frozen=True)
class Episode:
    """The world of one episode."""

    batch: Batch
    demand: Demand
    """What the route file holds (every copy's vehicles)."""
    parts: tuple[Demand, ...]
    """Each copy's demand."""
    ring_lengths: tuple[float | None, ...]
    """Each copy's ring centre-line length [m] (None: no ring)."""
    desired: np.ndarray
    """(C,) r8's reference speed of each copy [m/s] (0: the lane limits)."""

    @property
    def scenario(self) -> Scenario:
        """What SUMO loads: copy 0's view of the joined network (the scenario itself for one
        copy)."""
        return self.batch.views[0]


def check_batch(bundled: Scenario, config: EnvConfig) -> None:
    """ValueError unless ``config.copies`` copies of ``bundled`` can run: a family whose
    copies stay apart, and memory for their vehicles (``config`` with the scenario's defaults
    filled in). Before any network is joined."""
    check_copies(bundled, config.copies)
    if config.copies > 1:
        longest, _ = episode_ring(bundled, config.ring_length, None)
        everyone = replace(config, penetration=1.0, fixed_fleet=False)
        check_memory(config.copies, av_count(longest, everyone))


class Worlds:
    """The copies an env runs, sized once; an ``Episode`` per reset.

    Args:
        bundled: the scenario as loaded (a ring at its bundled length).
        config: the env's config, the scenario's defaults filled in.
    """

    def __init__(self, bundled: Scenario, config: EnvConfig) -> None:
        check_batch(bundled, config)
        self.bundled, self.config = bundled, config
        longest, length = episode_ring(bundled, config.ring_length, None)
        self.sizing = make_batch((longest,) * config.copies)
        """The batch at the longest ring: it sizes the agents."""
        self.longest_length = length
        self.per_copy = av_count(longest, config)
        """AVs a copy can have [count]: copy i's are ``av_{i·per_copy}`` on."""

    @property
    def copies(self) -> int:
        return self.config.copies

    @property
    def agent_copy(self) -> np.ndarray:
        """(P,) int32 the copy of each possible agent (copy-major)."""
        return np.repeat(np.arange(self.copies, dtype=np.int32), self.per_copy)

    def episode(
        self, config: EnvConfig, demand_seed: int, ring_rng: np.random.Generator
    ) -> Episode:
        """The world of an episode of ``config`` (its seed set) from the reset's seeds."""
        rings = self._rings(ring_rng)
        batch = make_batch(tuple(s for s, _ in rings))
        demand, parts = batch_demand(batch, config, demand_seed, self.per_copy)
        desired = np.array([reference_speed(v, config, length, d)
                            for v, (_, length), d in zip(batch.views, rings, parts)])  # fmt: skip
        return Episode(batch, demand, parts, tuple(length for _, length in rings), desired)

    def _rings(self, rng: np.random.Generator) -> list[tuple[Scenario, float | None]]:
        """Each copy's scenario and ring length: one copy's as without copies; copies of a
        drawn length from one of the pool's draws, else all the same."""
        spec = self.config.ring_length
        if self.copies == 1 or not (self.bundled.ring and len(spec) == 2):
            return [episode_ring(self.bundled, spec, rng)] * self.copies
        draw = np.random.default_rng([int(rng.integers(RING_POOL)), *(round(x * 10) for x in spec)])
        lengths = [draw_ring_length(spec, draw) for _ in range(self.copies)]
        return [(scaled_ring(self.bundled, length), length) for length in lengths]

    def start(self, episode: Episode, config: EnvConfig, route_file: Path, avs_as_humans: bool,
              fleet: list[str] | None) -> PeriodicBoundary | FleetPool | Boundaries:  # fmt: skip
        """Write the episode's route file; the boundary that brings vehicles in."""
        sc = episode.scenario
        write_demand(episode.demand, config, route_file, avs_as_humans, sc.vtypes, sc.vclass,
                     sc.verbatim)  # fmt: skip
        return batch_boundary(episode.batch, episode.parts, config.human, config.step_length,
                              fleet, self.per_copy)  # fmt: skip
