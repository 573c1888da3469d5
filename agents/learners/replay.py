"""Numpy structure-of-arrays replay buffer for dict observations (ring, preallocated).

One array per observation key for ``obs`` and ``next_obs`` (``next_obs`` keeps its
``action_mask``, needed to mask the TD target), plus decision, params, reward, done, and the
expert label of the transition: the demonstrator's decision and params for the same
observation (``labelled`` = 1; for demonstrator-driven rows they equal the taken action) or, on
unlabelled rows, a copy of the taken action; and the transition's ``discount`` (γ per decision,
less for a decision interval cut short; NaN = the learner's γ).
"""

from __future__ import annotations

import numpy as np
import torch

from agents.nets.lca import LCAConfig

LABEL_KEYS = ("labelled", "label_decision", "label_params")


class ReplayBuffer:
    """Ring buffer of capacity transitions; ``add_batch`` writes many agents at once."""

    def __init__(self, capacity: int, lca: LCAConfig) -> None:
        if capacity <= 0:
            raise ValueError("capacity must be positive")
        self.capacity = capacity
        self.shapes = lca.obs_shapes()
        self.obs = {k: np.zeros((capacity, *s), np.float32) for k, s in self.shapes.items()}
        self.next_obs = {k: np.zeros((capacity, *s), np.float32) for k, s in self.shapes.items()}
        self.decision = np.zeros(capacity, np.int64)
        self.params = np.zeros((capacity, 3, 2), np.float32)
        self.reward = np.zeros(capacity, np.float32)
        self.done = np.zeros(capacity, np.float32)
        self.labelled = np.zeros(capacity, np.float32)
        """1 where the demonstrator (ACC-LC) labelled the observation (DQfD margin loss)."""
        self.label_decision = np.zeros(capacity, np.int64)
        self.label_params = np.zeros((capacity, 3, 2), np.float32)
        """Behaviour-cloning targets: the demonstrator's action, else the taken one."""
        self.discount = np.full(capacity, np.nan, np.float32)
        """Discount of the bootstrap term [-] (NaN: the learner's γ)."""
        self.pos = 0
        """Next write index."""
        self.size = 0

    def __len__(self) -> int:
        return self.size

    def add_batch(
        self,
        obs: dict[str, np.ndarray],
        decision: np.ndarray,
        params: np.ndarray,
        reward: np.ndarray,
        next_obs: dict[str, np.ndarray],
        done: np.ndarray,
        labelled: np.ndarray | None = None,
        label_decision: np.ndarray | None = None,
        label_params: np.ndarray | None = None,
        discount: np.ndarray | None = None,
    ) -> None:
        """Append n transitions (arrays with leading dim n); the oldest are overwritten.
        Without labels the rows are unlabelled and their targets are the taken action."""
        n = len(decision)
        if n == 0:
            return
        labelled = np.zeros(n, np.float32) if labelled is None else np.asarray(labelled)
        label_decision = decision if label_decision is None else label_decision
        label_params = params if label_params is None else label_params
        discount = np.full(n, np.nan, np.float32) if discount is None else np.asarray(discount)
        if n > self.capacity:  # only the newest `capacity` survive anyway
            sl = slice(n - self.capacity, n)
            obs = {k: v[sl] for k, v in obs.items()}
            next_obs = {k: v[sl] for k, v in next_obs.items()}
            decision, params, reward, done = decision[sl], params[sl], reward[sl], done[sl]
            labelled, label_decision, label_params = (
                labelled[sl],
                label_decision[sl],
                label_params[sl],
            )
            discount = discount[sl]
            n = self.capacity
        idx = (self.pos + np.arange(n)) % self.capacity
        for k in self.shapes:
            self.obs[k][idx] = obs[k]
            self.next_obs[k][idx] = next_obs[k]
        self.decision[idx] = decision
        self.params[idx] = np.reshape(params, (n, 3, 2))
        self.reward[idx] = reward
        self.done[idx] = done
        self.labelled[idx] = labelled
        self.label_decision[idx] = label_decision
        self.label_params[idx] = np.reshape(label_params, (n, 3, 2))
        self.discount[idx] = discount
        self.pos = int((self.pos + n) % self.capacity)
        self.size = min(self.size + n, self.capacity)

    def sample(self, batch: int, rng: np.random.Generator) -> dict:
        """Uniform sample with replacement → batch dict of torch tensors (see agents.learners.rbpdqn)."""
        if self.size == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        idx = rng.integers(0, self.size, size=batch)
        t = torch.from_numpy
        return {
            "obs": {k: t(v[idx]) for k, v in self.obs.items()},
            "next_obs": {k: t(v[idx]) for k, v in self.next_obs.items()},
            "decision": t(self.decision[idx]),
            "params": t(self.params[idx]),
            "reward": t(self.reward[idx]),
            "done": t(self.done[idx]),
            "discount": t(self.discount[idx]),
            **{k: t(getattr(self, k)[idx]) for k in LABEL_KEYS},
        }

    def state_dict(self) -> dict:
        """Only the filled part, as torch tensors + ints so it round-trips through
        ``torch.save`` / ``torch.load(weights_only=True)``; restore with :meth:`load_state_dict`."""
        n = self.size

        def t(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(a[:n].copy())

        return {
            "capacity": self.capacity,
            "pos": self.pos,
            "size": n,
            "obs": {k: t(v) for k, v in self.obs.items()},
            "next_obs": {k: t(v) for k, v in self.next_obs.items()},
            "decision": t(self.decision),
            "params": t(self.params),
            "reward": t(self.reward),
            "done": t(self.done),
            "discount": t(self.discount),
            **{k: t(getattr(self, k)) for k in LABEL_KEYS},
        }

    def load_state_dict(self, sd: dict) -> None:
        if sd["capacity"] != self.capacity:
            raise ValueError(f"replay capacity {sd['capacity']} != {self.capacity}")
        n = int(sd["size"])
        for k in self.shapes:
            got = tuple(sd["obs"][k].shape[1:])
            if got != self.obs[k].shape[1:]:
                raise ValueError(f"replay obs '{k}' shape {got} != {self.obs[k].shape[1:]}")
            self.obs[k][:n] = np.asarray(sd["obs"][k])
            self.next_obs[k][:n] = np.asarray(sd["next_obs"][k])
        for name in ("decision", "params", "reward", "done", *LABEL_KEYS):
            getattr(self, name)[:n] = np.asarray(sd[name])
        if "discount" in sd:  # replays saved before per-row discounts use the learner's γ
            self.discount[:n] = np.asarray(sd["discount"])
        self.pos, self.size = int(sd["pos"]), n
