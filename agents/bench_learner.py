"""Learner benchmark: RBP-DQN updates/s, new path vs the pre-issue-22 reference, side by side.

``python -m mixed_traffic.bench --section learner`` (or ``python -m agents.bench_learner``)
prints, per batch size and torch thread count: updates/s and samples/s (batch × updates/s) of
:meth:`agents.learners.rbpdqn.RBPDQN.update` and of the reference learner (the code before
issue 22: module-by-module forward with the slicing GRU, per-parameter Adam, clipping and soft
updates), their ratio, and the transitions/s training could take in at ``TrainConfig``'s
``update_ratio``.

Both learners start from the same weights and see the same pre-sampled batches (random
observations, DESIGN §6 shapes; replay sampling is not timed). They run in alternating blocks
of about ``block_s`` seconds in one process and the figures are medians over the blocks (the
ratio: median of the per-pair ratios), so load from other processes on a small machine hits
both alike. Wall-clock time (worker threads count).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
import types
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import Tensor, nn

from agents.bench_inference import random_obs
from agents.learners.rbpdqn import RBPDQN, LearnerConfig
from agents.learners.replay import ReplayBuffer
from agents.nets.lca import HistoryGRU, LCAConfig, fast_tanh
from agents.training.config import TrainConfig


class _ReferenceGRU(HistoryGRU):
    """HistoryGRU.forward before issue 22 (slices: each one's backward zero-fills a gradient)."""

    def forward(self, x: Tensor) -> Tensor:
        d = self.d
        gi = torch.nn.functional.linear(x, self.w_ih, self.b_ih)  # (N, z, 3D)
        g = gi[:, 0]
        rz = torch.sigmoid(g[:, : 2 * d] + self.b_hh[: 2 * d])
        r, u = rz[:, :d], rz[:, d:]
        n = fast_tanh(g[:, 2 * d :] + r * self.b_hh[2 * d :])
        h = n - u * n
        for t in range(1, x.shape[1]):
            g = gi[:, t]
            gh = torch.addmm(self.b_hh, h, self.w_hh.t())
            rz = torch.sigmoid(g[:, : 2 * d] + gh[:, : 2 * d])
            r, u = rz[:, :d], rz[:, d:]
            n = fast_tanh(g[:, 2 * d :] + r * gh[:, 2 * d :])
            h = n + u * (h - n)
        return h


def _reference_update(self: RBPDQN, batch: dict) -> dict[str, float]:
    """RBPDQN.update before issue 22 (module forward, per-parameter optimiser loops)."""
    c_loss = self.critic_loss(batch)
    self.critic_opt.zero_grad(set_to_none=True)
    c_loss.backward()
    c_norm = nn.utils.clip_grad_norm_(self.critic.parameters(), self.cfg.grad_clip)
    self.critic_opt.step()
    self.critic.requires_grad_(False)
    try:
        a_loss = self.actor_loss(batch)
        self.actor_opt.zero_grad(set_to_none=True)
        a_loss.backward()
        a_norm = nn.utils.clip_grad_norm_(self.actor.parameters(), self.cfg.grad_clip)
        self.actor_opt.step()
    finally:
        self.critic.requires_grad_(True)
    with torch.no_grad():
        for targ, src in ((self.critic_targ, self.critic), (self.actor_targ, self.actor)):
            for t, s in zip(targ.parameters(), src.parameters(), strict=True):
                t.lerp_(s, self.cfg.tau)
    self.steps += 1
    return {"critic_loss": float(c_loss.detach()), "actor_loss": float(a_loss.detach()),
            "critic_grad_norm": float(c_norm), "actor_grad_norm": float(a_norm)}  # fmt: skip


def reference_learner(lca: LCAConfig, cfg: LearnerConfig, seed: int = 0) -> RBPDQN:
    """A learner running the pre-issue-22 update on the same initial weights as
    ``RBPDQN(lca, cfg, seed)``."""
    ref = RBPDQN(lca, cfg, seed=seed)
    for net in (ref.actor, ref.critic, ref.actor_targ, ref.critic_targ):
        for m in net.modules():
            if type(m) is HistoryGRU:
                m.__class__ = _ReferenceGRU
    ref.actor_opt = torch.optim.Adam(ref.actor.parameters(), lr=cfg.lr)
    ref.critic_opt = torch.optim.Adam(ref.critic.parameters(), lr=cfg.lr)
    ref.update = types.MethodType(_reference_update, ref)  # type: ignore[method-assign]
    return ref


def random_batches(lca: LCAConfig, b: int, n: int, seed: int = 0) -> list[dict]:
    """``n`` replay samples of size ``b`` from a buffer of random transitions with labels."""
    rng = np.random.default_rng(seed)
    size = max(4 * b, 1024)
    buf = ReplayBuffer(size, lca)
    act = lambda: rng.uniform(-1, 1, (size, 3, 2)).astype(np.float32)  # noqa: E731
    buf.add_batch(
        random_obs(size, lca, rng), rng.integers(0, 3, size), act(),
        rng.normal(size=size).astype(np.float32), random_obs(size, lca, rng),
        (rng.random(size) < 0.05).astype(np.float32), (rng.random(size) < 0.5).astype(np.float32),
        rng.integers(0, 3, size), act(),
    )  # fmt: skip
    return [buf.sample(b, rng) for _ in range(n)]


@dataclass
class LearnerResult:
    batch: int
    threads: int
    updates_s: float
    """Median over blocks, new path [1/s]."""
    ref_updates_s: float
    """Median over blocks, reference learner [1/s]."""
    ratio: float
    """Median over adjacent block pairs of new / reference updates/s [-]."""
    blocks: int
    compile: bool = False
    """The new learner ran with ``compile=True``."""
    warmup_s: float = 0.0
    """Wall time of the new learner's first update (includes compiling with ``compile``) [s]."""

    @property
    def samples_s(self) -> float:
        return self.batch * self.updates_s

    @property
    def ref_samples_s(self) -> float:
        return self.batch * self.ref_updates_s


def _block(learner: RBPDQN, batches: list[dict], start: int, seconds: float) -> float:
    """Run updates for about ``seconds`` → updates/s."""
    n, t0 = 0, time.perf_counter()
    while True:
        learner.update(batches[(start + n) % len(batches)])
        n += 1
        dt = time.perf_counter() - t0
        if dt >= seconds:
            return n / dt


def bench_learner(
    batch: int, threads: int, blocks: int = 6, block_s: float = 0.5, compile: bool = False
) -> LearnerResult:
    """Alternate blocks of new and reference updates (order swapped every pair)."""
    prev = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        lca = LCAConfig()
        cfg = LearnerConfig(batch_size=batch)
        new, ref = RBPDQN(lca, cfg, compile=compile), reference_learner(lca, cfg)
        batches = random_batches(lca, batch, 8)
        t0 = time.perf_counter()
        new.update(batches[-1])
        warmup = time.perf_counter() - t0
        for learner in (new, ref):  # warm-up: workspaces, allocator, caches
            _block(learner, batches, 0, min(block_s, 0.2))
        rates: dict[str, list[float]] = {"new": [], "ref": []}
        for i in range(blocks):
            order = ("new", "ref") if i % 2 == 0 else ("ref", "new")
            for name in order:
                rates[name].append(_block(new if name == "new" else ref, batches, i, block_s))
        pairs = [n / r for n, r in zip(rates["new"], rates["ref"])]
        return LearnerResult(batch, threads, statistics.median(rates["new"]),
                             statistics.median(rates["ref"]), statistics.median(pairs), blocks,
                             compile, warmup)  # fmt: skip
    finally:
        torch.set_num_threads(prev)


_HEAD = (f"{'batch':>5} {'thr':>3} {'upd/s':>7} {'samples/s':>9} {'ref upd/s':>9} "
         f"{'ref smp/s':>9} {'x ref':>6} {'transitions/s':>13}")  # fmt: skip


def _row(r: LearnerResult, update_ratio: float) -> str:
    return (f"{r.batch:>5} {r.threads:>3} {r.updates_s:>7.1f} {r.samples_s:>9.0f} "
            f"{r.ref_updates_s:>9.1f} {r.ref_samples_s:>9.0f} {r.ratio:>6.2f} "
            f"{r.updates_s / update_ratio:>13.0f}")  # fmt: skip


def run(batches: list[int], threads: list[int], blocks: int, block_s: float,
        json_path: str = "", compile: bool = False) -> list[LearnerResult]:  # fmt: skip
    """Measure every (batch, threads) pair, print the table, optionally write JSON."""
    ratio = TrainConfig.__dataclass_fields__["update_ratio"].default
    mode = "compile=True" if compile else "eager"
    print(f"learner: RBPDQN.update ({mode}) vs the pre-issue-22 reference, same weights and "
          f"batches, alternating ~{block_s:g} s blocks x {blocks} each (medians); "
          f"transitions/s = upd/s / update_ratio ({ratio:g}, TrainConfig)")  # fmt: skip
    print(_HEAD)
    print("-" * len(_HEAD))
    results = []
    for b in batches:
        for th in threads:
            results.append(bench_learner(b, th, blocks, block_s, compile))
            print(_row(results[-1], ratio), flush=True)
    if compile:
        print("first update incl. compiling [s]: "
              + ", ".join(f"B={r.batch}/{r.threads}t {r.warmup_s:.1f}" for r in results))  # fmt: skip
    if json_path:
        rows = [{**asdict(r), "samples_s": r.samples_s, "ref_samples_s": r.ref_samples_s,
                 "transitions_s": r.updates_s / ratio} for r in results]  # fmt: skip
        with open(json_path, "w") as f:
            json.dump(rows, f, indent=1)
    return results


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, nargs="+", default=[128, 1024])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--blocks", type=int, default=6)
    ap.add_argument("--block-seconds", type=float, default=0.5)
    ap.add_argument("--json", default="", help="also write the results to this JSON file")
    ap.add_argument("--compile", action="store_true", help="time RBPDQN(compile=True)")
    a = ap.parse_args()
    run(a.batch, a.threads, a.blocks, a.block_seconds, a.json, a.compile)


if __name__ == "__main__":
    main()
