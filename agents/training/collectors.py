"""The learner's side of the worker transports (see :mod:`agents.training.trainer` for the
topology): :func:`make_collector` picks one per backend; each has ``synchronous``,
``restarts``, ``publish(vec)`` (broadcast weights), ``poll(timeout) -> chunks`` and ``close()``.

- :class:`InProcessCollector`: ``workers == 1``, the worker runs in the learner process;
- :class:`ProcessCollector`: spawned processes, one pipe each, weights via shared memory;
- :class:`RayCollector`: Ray core actors.

A worker that dies is restarted with a fresh incarnation (fresh env seeds) until one slot has
been restarted ``max_restarts`` times.
"""

from __future__ import annotations

import multiprocessing as mp
from dataclasses import replace
from multiprocessing.connection import wait as mp_wait
from typing import Any

import numpy as np

from agents.collection.workers import Chunk, RolloutWorker, SharedWeights, WorkerSpec, process_main
from agents.training.config import TrainConfig


def make_collector(cfg: TrainConfig, specs: list[WorkerSpec], vec: np.ndarray, log: Any) -> Any:
    """The collector of ``cfg.backend`` / ``cfg.workers`` for ``specs``, with the weight
    vector ``vec`` published; ``log`` reports worker restarts."""
    if cfg.backend == "ray":
        return RayCollector(specs, cfg.local_buffer, vec, cfg.address,
                            cfg.max_worker_restarts, log)  # fmt: skip
    if cfg.workers == 1:
        col = InProcessCollector(specs, cfg.local_buffer)
        col.publish(vec)
        return col
    return ProcessCollector(specs, cfg.local_buffer, vec, cfg.max_worker_restarts, log)


class InProcessCollector:
    """``workers == 1``: the worker lives in the learner process (synchronous, deterministic)."""

    synchronous = True

    def __init__(self, specs: list[WorkerSpec], n: int) -> None:
        self.worker = RolloutWorker(specs[0])
        self.n = n
        self.restarts = 0

    def publish(self, vec: np.ndarray) -> None:
        """Load the weight vector into the worker's policy."""
        self.worker.set_weights(vec)

    def poll(self, timeout: float) -> list[Chunk]:
        """One chunk of at least ``n`` transitions, collected now (``timeout`` unused)."""
        return [self.worker.collect(self.n)]

    def close(self) -> None:
        """Close the worker's env."""
        self.worker.close()


def _next_incarnation(collector: Any, wid: int, why: str) -> None:
    """Count a restart of worker ``wid`` (giving up after ``max_restarts``) and give its spec
    a new incarnation (fresh env seeds)."""
    collector.slot_restarts[wid] += 1
    collector.restarts += 1
    if collector.slot_restarts[wid] > collector.max_restarts:
        raise RuntimeError(f"worker {wid} restarted {collector.max_restarts} times; last: {why}")
    spec = collector.specs[wid]
    collector.specs[wid] = replace(spec, incarnation=spec.incarnation + 1)


class ProcessCollector:
    """Spawned worker processes, one pipe each; weights through :class:`SharedWeights`."""

    synchronous = False

    def __init__(self, specs: list[WorkerSpec], n: int, vec: np.ndarray, max_restarts: int,
                 log: Any) -> None:  # fmt: skip
        self.ctx = mp.get_context("spawn")
        self.n, self.max_restarts, self.log = n, max_restarts, log
        self.weights = SharedWeights(self.ctx, len(vec))
        self.weights.publish(vec)
        self.stop = self.ctx.Event()
        self.specs = {s.worker_id: s for s in specs}
        self.procs: dict[int, Any] = {}
        self.conns: dict[int, Any] = {}
        self.restarts = 0
        self.slot_restarts = dict.fromkeys(self.specs, 0)
        for wid in self.specs:
            self._spawn(wid)

    def _spawn(self, wid: int) -> None:
        """Start worker ``wid``'s process with a fresh pipe."""
        reader, writer = self.ctx.Pipe(duplex=False)
        p = self.ctx.Process(
            target=process_main, args=(self.specs[wid], writer, self.weights, self.stop, self.n),
            name=f"mt-worker-{wid}", daemon=True,
        )  # fmt: skip
        p.start()
        writer.close()  # only the child holds the write end: its death → EOF here
        self.procs[wid], self.conns[wid] = p, reader

    def _restart(self, wid: int, why: str) -> None:
        """Reap worker ``wid``'s process and start its next incarnation."""
        self.conns.pop(wid).close()
        p = self.procs.pop(wid)
        p.join(timeout=5)
        if p.is_alive():
            p.kill()
            p.join(timeout=5)
        _next_incarnation(self, wid, why)
        self.log(f"worker {wid} died (exit code {p.exitcode}): {why.strip()[-2000:]}; restarting")
        self._spawn(wid)

    def publish(self, vec: np.ndarray) -> None:
        """Write the weight vector into shared memory (workers pick it up between chunks)."""
        self.weights.publish(vec)

    def poll(self, timeout: float) -> list[Chunk]:
        """Chunks that arrived within ``timeout`` seconds; restarts workers that died."""
        out: list[Chunk] = []
        by_conn = {c: wid for wid, c in self.conns.items()}
        for conn in mp_wait(list(by_conn), timeout=timeout):
            wid = by_conn[conn]
            try:
                kind, payload = conn.recv()
            except (EOFError, OSError):
                self._restart(wid, "connection closed (process died)")
                continue
            if kind == "chunk":
                out.append(payload)
            else:
                self._restart(wid, payload)
        for wid, p in list(self.procs.items()):
            if not p.is_alive() and not self.conns[wid].poll():
                self._restart(wid, "process not alive")
        return out

    def close(self) -> None:
        """Stop the workers and reap their processes."""
        self.stop.set()
        for c in self.conns.values():
            c.close()  # a worker blocked in send gets BrokenPipeError and exits
        for p in self.procs.values():
            p.join(timeout=10)
            if p.is_alive():
                p.kill()
                p.join(timeout=5)


class RayCollector:
    """Ray core actors as workers; the learner (driver) holds the replay."""

    synchronous = False

    def __init__(self, specs: list[WorkerSpec], n: int, vec: np.ndarray, address: str,
                 max_restarts: int, log: Any) -> None:  # fmt: skip
        import ray

        self.ray = ray
        self.owns_ray = not ray.is_initialized()
        if self.owns_ray:
            if address:
                ray.init(address=address)
            else:
                ray.init(num_cpus=len(specs) + 1, include_dashboard=False,
                         log_to_driver=False)  # fmt: skip
        self.remote_cls = ray.remote(num_cpus=1, max_restarts=0)(RolloutWorker)
        self.n, self.max_restarts, self.log = n, max_restarts, log
        self.specs = {s.worker_id: s for s in specs}
        self.actors: dict[int, Any] = {}
        self.pending: dict[Any, int] = {}
        self.sent_version: dict[int, int] = {}
        self.version = 0
        self.weights_ref = ray.put(vec)
        self.restarts = 0
        self.slot_restarts = dict.fromkeys(self.specs, 0)
        for wid in self.specs:
            self.actors[wid] = self.remote_cls.remote(self.specs[wid])
            self._submit(wid)

    def _submit(self, wid: int) -> None:
        """Ask worker ``wid`` for its next chunk (with the weights if they changed since)."""
        w = self.weights_ref if self.sent_version.get(wid) != self.version else None
        self.sent_version[wid] = self.version
        self.pending[self.actors[wid].collect_with.remote(self.n, w)] = wid

    def publish(self, vec: np.ndarray) -> None:
        """Put the weight vector in the object store; each worker gets it with its next task."""
        self.version += 1
        self.weights_ref = self.ray.put(vec)

    def poll(self, timeout: float) -> list[Chunk]:
        """At most one chunk that arrived within ``timeout`` seconds; restarts failed actors."""
        out: list[Chunk] = []
        ready, _ = self.ray.wait(list(self.pending), num_returns=1, timeout=timeout)
        for ref in ready:
            wid = self.pending.pop(ref)
            try:
                out.append(self.ray.get(ref))
            except Exception as exc:  # RayActorError (died) or a task error
                self._restart(wid, f"{type(exc).__name__}: {str(exc).splitlines()[0]}")
            self._submit(wid)
        return out

    def _restart(self, wid: int, why: str) -> None:
        """Kill worker ``wid``'s actor and start its next incarnation."""
        self.ray.kill(self.actors[wid], no_restart=True)
        _next_incarnation(self, wid, why)
        self.log(f"ray worker {wid} failed ({why.strip()[-2000:]}); restarting")
        self.actors[wid] = self.remote_cls.remote(self.specs[wid])
        self.sent_version.pop(wid, None)

    def close(self) -> None:
        """Kill the actors (and shut Ray down if this collector started it)."""
        for a in self.actors.values():
            self.ray.kill(a, no_restart=True)
        self.pending.clear()
        if self.owns_ray:
            self.ray.shutdown()
