"""Bench section ``soak``: memory over one long episode (issue 25: flat memory).

One episode of ``--soak-length`` simulated seconds (default 600 s) on ``straight`` at
``--soak-density`` (default 180 veh/km) with 100 % AVs that hold lane and speed. The resident
set size (RSS, from /proc) is sampled every ``SAMPLE_EVERY`` simulated seconds; the growth is the
last sample minus the first one taken after ``SETTLE`` s, when the buffers have their working
size. Target: ≤ 50 MB.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass

from tqdm import tqdm

from mixed_traffic.experiments.bench_env import bench_actions, make_bench_env

TARGET_GROWTH_MB = 50.0
SETTLE = 60.0
"""Simulated seconds before the baseline sample [s]."""
SAMPLE_EVERY = 30.0
"""Simulated seconds between RSS samples [s]."""


@dataclass
class SoakResult:
    length: float
    """Simulated episode length [s]."""
    density: float
    """Density [veh/km]."""
    baseline_mb: float
    """RSS after SETTLE simulated seconds [MB]."""
    final_mb: float
    """RSS at the end of the episode [MB]."""
    peak_mb: float
    """Largest RSS sample [MB]."""

    @property
    def growth_mb(self) -> float:
        return self.final_mb - self.baseline_mb


def rss_mb() -> float:
    """This process's resident set size now [MB] (Linux /proc)."""
    with open("/proc/self/statm") as f:
        pages = int(f.read().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def soak(length: float, density: float, seed: int = 0, progress: bool = True) -> SoakResult:
    """Run the soak episode and sample its memory."""
    env = make_bench_env(1.0, density, length, seed)
    obs, _ = env.reset(seed=seed)
    space, rng = env.action_space(env.agents[0]), None
    samples: list[tuple[float, float]] = []
    bar = tqdm(total=int(length), desc="soak", unit="sim s", disable=not progress)
    t, next_sample = 0.0, SETTLE
    while env.agents:
        obs, *_ = env.step(bench_actions(env, obs, space, rng, "keep"))
        t = env.sim_time
        bar.update(int(t) - bar.n)
        if t >= next_sample - 1e-9:
            samples.append((t, rss_mb()))
            next_sample += SAMPLE_EVERY
    bar.close()
    env.close()
    samples.append((t, rss_mb()))
    return SoakResult(length, density, samples[0][1], samples[-1][1], max(m for _, m in samples))


def section_soak(args: argparse.Namespace) -> SoakResult:
    r = soak(args.soak_length, args.soak_density)
    verdict = "ok" if r.growth_mb <= TARGET_GROWTH_MB else "OVER TARGET"
    print(f"soak: {r.length:.0f} s at {r.density:g} veh/km, 100 % AVs: RSS {r.baseline_mb:.0f} MB "
          f"after {SETTLE:.0f} s -> {r.final_mb:.0f} MB at the end (peak {r.peak_mb:.0f} MB), "
          f"growth {r.growth_mb:+.1f} MB (target <= {TARGET_GROWTH_MB:.0f} MB: {verdict})")  # fmt: skip
    return r
