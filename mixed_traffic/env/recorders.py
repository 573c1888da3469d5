"""An episode's metric recorders behind one object: the flow recorder (every vehicle of each
copy, ``flow_metrics``) and the per-AV metrics (``av_metrics``), and the summaries the env
returns from them (``episode_metrics``, ``flow_diagnostics``, ``trajectories``)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from mixed_traffic.config import EnvConfig
from mixed_traffic.env.av_metrics import AVMetrics
from mixed_traffic.env.flow_metrics import FlowRecorder
from mixed_traffic.schema import METRICS
from mixed_traffic.world.fleet_pool import FleetPool
from mixed_traffic.world.hdmap import HDMap


class Recorders:
    """The recorders of the current episode; ``enabled`` False (a training env): the flow is
    not recorded and the summaries raise."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.flow: FlowRecorder | None = None
        self.av: AVMetrics | None = None

    def start(self, hdmap: HDMap, segments: Sequence[Sequence[str]], cfg: EnvConfig,
              warmup: float, trace_every: int, copy_of: Callable[[str], int]) -> None:  # fmt: skip
        """Fresh recorders for an episode: ``segments`` each copy's measurement edges,
        ``warmup`` [s], ``trace_every`` steps between traced samples (0: no trace)."""
        self.flow = FlowRecorder(hdmap, segments, cfg.step_length, warmup, trace_every,
                                 cfg.av_window, copy_of)  # fmt: skip
        self.av = AVMetrics(cfg.step_length, cfg.reward.rear_speed_drop, cfg.copies, copy_of)

    def checked(self, what: str) -> FlowRecorder:
        """The flow recorder; ``RuntimeError`` naming ``what`` without one."""
        if not self.enabled:
            raise RuntimeError(f"{what}(): this env was made with metrics=False and records none")
        if self.flow is None:
            raise RuntimeError(f"{what}() before reset(): call reset() to start an episode first")
        return self.flow

    def episode_metrics(self, copy: int) -> dict[str, float | None]:
        """Every metric of ``schema.METRICS`` of copy ``copy`` so far."""
        flow, av = self.checked("episode_metrics"), self.av
        out: dict[str, Any] = dict.fromkeys(METRICS)
        out.update(flow.summary(copy))
        out.update(av.summary(copy))
        out["avg_di_c"] = flow.mean_delay_index(sorted(av.rear_vehicles(copy)))
        return out

    def flow_diagnostics(self, copy: int | None, boundary: Any) -> dict[str, float | int | None]:
        """The flow recorder's diagnostics of ``copy`` (None: every vehicle), and a fleet
        pool's trips and waits."""
        out = self.checked("flow_diagnostics").diagnostics(copy)
        if isinstance(boundary, FleetPool):
            out.update(boundary.summary())
        return out

    def trajectories(self) -> dict[str, np.ndarray]:
        """The traced trajectories (``FlowRecorder``'s space-time field)."""
        return self.checked("trajectories").field.traces()
