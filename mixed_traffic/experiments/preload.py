"""Imported by the sweep's fork server before it forks cells: the runner, and the compiled
kernels loaded once (``mixed_traffic.compiled``), so that no cell pays their first call."""

from agents.rules import acc_lc
from mixed_traffic import compiled
from mixed_traffic.env import control_kernel, metrics_kernel, step_kernel, traffic_terms_kernel
from mixed_traffic.experiments import runner  # noqa: F401  (the import is the preload)
from mixed_traffic.sensing import (
    blockers_kernel,
    neighbours_kernel,
    observation_kernel,
    sensing_kernel,
)

if compiled.enabled():
    neighbours_kernel.warm()
    blockers_kernel.warm()
    traffic_terms_kernel.warm()
    metrics_kernel.warm()
    step_kernel.warm()
    control_kernel.warm()
    acc_lc.warm()
    observation_kernel.warm()
    sensing_kernel.warm()
