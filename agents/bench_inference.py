"""AvgIT benchmark: µs per decision for one batched actor + critic + selection forward.

``python -m agents.bench_inference [--agents 128] [--threads 1]`` prints the figure.
Observations are prebuilt (random, DESIGN §6 shapes) numpy arrays; the timed call includes the
numpy → torch view, the fused forward and the masked argmax, i.e. :meth:`Policy.act` without
exploration. Time is the calling thread's CPU time (robust to other processes sharing the
machine), best of several repeats.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from agents.learners.rbpdqn import Policy
from agents.nets.lca import LCAConfig
from agents.nets.networks import Actor, Critic


def random_obs(n: int, cfg: LCAConfig, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Plausible random observations (A = n) with random node/action masks."""
    obs = {
        k: rng.uniform(-1, 1, size=(n, *s)).astype(np.float32) for k, s in cfg.obs_shapes().items()
    }
    obs["node_mask"] = (rng.random((n, 3, 3)) < 0.8).astype(np.float32)
    am = (rng.random((n, 3)) < 0.7).astype(np.float32)
    am[:, 1] = 1.0
    obs["action_mask"] = am
    return obs


def avg_inference_us(
    n_agents: int = 128,
    z: int = 5,
    m: int = 10,
    threads: int = 1,
    repeats: int = 7,
    iters: int = 50,
    safety: bool = False,
) -> float:
    """µs per decision (per agent) of a batched forward for ``n_agents`` agents; with
    ``safety`` the safety module's filter (``agents.rules.safety``) is timed after it."""
    from agents.rules.safety import SafetyModule

    prev = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        torch.manual_seed(0)
        cfg = LCAConfig(z=z, m=m)
        policy = Policy(Actor(cfg).eval(), Critic(cfg).eval())
        obs = random_obs(n_agents, cfg, np.random.default_rng(0))
        module = SafetyModule() if safety else None

        def act() -> None:
            decision, params = policy.act(obs, explore=False)
            if module is not None:
                module.filter(obs, decision, params)

        for _ in range(10):  # warm-up: buffers, allocator, caches
            act()
        best = float("inf")
        for _ in range(repeats):
            t0 = time.thread_time()
            for _ in range(iters):
                act()
            best = min(best, (time.thread_time() - t0) / iters)
        return best / n_agents * 1e6
    finally:
        torch.set_num_threads(prev)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--agents", type=int, default=128)
    ap.add_argument("--z", type=int, default=5)
    ap.add_argument("--m", type=int, default=10)
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args()
    us = avg_inference_us(a.agents, a.z, a.m, a.threads)
    print(f"AvgIT: {us:.2f} us per decision ({a.agents} agents batched, {a.threads} thread(s))")


if __name__ == "__main__":
    main()
