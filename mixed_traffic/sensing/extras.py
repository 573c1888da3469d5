"""The opt-in observation keys, built beside the observation builder: ``downstream`` (the V2X
feed, ``EnvConfig.v2x``) and ``memory`` (slow summaries, ``SensorConfig.memory``)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mixed_traffic.config import EnvConfig
from mixed_traffic.sensing.frame import PerceptionFrame
from mixed_traffic.sensing.memory import SlowMemory
from mixed_traffic.sensing.v2x import DownstreamFeed
from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.snapshot import TrafficSnapshot


class ExtraKeys:
    """Both opt-in keys of every agent slot; each is ``{}`` while its option is off."""

    def __init__(self, config: EnvConfig, n_agents: int, ring: bool) -> None:
        self.feed = DownstreamFeed(config, n_agents, ring)
        self.memory = SlowMemory(config, n_agents)

    def reset(self, rng: np.random.Generator) -> None:
        """A new episode (``rng`` draws the feed's noise)."""
        self.feed.reset(rng)
        self.memory.reset()

    def drop(self, slots: np.ndarray) -> None:
        """Forget what ``slots`` received and remembered."""
        self.feed.drop(slots)
        self.memory.drop(slots)

    def command(self, slots_of: Callable[[list[str]], np.ndarray], agents: list[str],
                decision: np.ndarray, params: np.ndarray) -> None:  # fmt: skip
        """The command ``agents`` execute this step (``SlowMemory.command``); ``slots_of``
        looks up their slots, only where the memory is on."""
        if self.memory.on:
            self.memory.command(slots_of(agents), decision, params)

    def keys(self, hd: HDMap, snap: TrafficSnapshot, rows: np.ndarray, slots: np.ndarray,
             route_table: np.ndarray, route_len: np.ndarray,
             sensed: PerceptionFrame) -> dict[str, np.ndarray]:  # fmt: skip
        """``{key: (A, ...)}`` of the agents at snapshot ``rows`` (A,) and ``slots`` (A,)."""
        return {**self.feed.keys(hd, snap, rows, slots, route_table, route_len),
                **self.memory.keys(slots, sensed.ego, sensed.vehicles)}  # fmt: skip
