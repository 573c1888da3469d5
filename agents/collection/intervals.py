"""Decision-level transitions from per-step env output (the decision interval of ``agents.driver``).

An agent's transition opens when it decides (observation, decision, u, label) and closes

- at its next decision: ``next_obs`` is that step's observation, ``done`` = 0;
- when its trip ends: the env's last observation, ``done`` = 1, except an arrival with
  ``bootstrap_arrival`` (reaching the end of the route is not a failure; its value is that
  of driving on, estimated from the last observation);
- at truncation: the last observation, ``done`` = 0 (the episode's time limit is not part of
  the task).

Its reward is ``scale``·Σ_i γ_s^i r_i over the n steps it spans, and its ``discount`` γ_s^n,
with γ_s the discount per simulation step. With one step per decision this is the usual
one-step transition.

With ``n_step`` > 1 a closed transition waits for its successors and leaves as the n-step
transition of its decision: rewards r_0 + d_0·r_1 + d_0·d_1·r_2 + ..., discount Π d_k and the
``next_obs`` of the n-th decision (Sutton & Barto §7.1; Rainbow, R2D2). A trip's or episode's
end flushes the waiting ones with what is left (shorter returns, smaller products of d).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agents.rules.obs_batch import EXTRA, OBS_KEYS

Rows = dict[str, np.ndarray | dict[str, np.ndarray]]
"""Closed transitions: ``obs``/``next_obs`` dicts of (n, ...) arrays, ``decision``, ``params``
(the held u), ``reward``, ``done``, ``discount``, ``labelled``, ``label_decision``,
``label_params``."""


@dataclass
class _Open:
    obs: dict[str, np.ndarray]
    decision: int
    u: np.ndarray
    labelled: float
    label_decision: int
    label_params: np.ndarray
    reward: float = 0.0
    steps: int = 0


class Intervals:
    """The open transition of every agent of one episode, and those waiting for n-step."""

    def __init__(self, gamma_step: float, scale: float, bootstrap_arrival: bool,
                 n_step: int = 1) -> None:  # fmt: skip
        """``gamma_step`` discount per simulation step [-], ``scale`` reward scale [-],
        ``n_step`` decisions per stored transition [-]."""
        if n_step < 1:
            raise ValueError(f"n_step={n_step} must be >= 1")
        self.gamma_step, self.scale, self.n_step = gamma_step, scale, n_step
        self.bootstrap_arrival = bootstrap_arrival
        self._open: dict[str, _Open] = {}
        self._waiting: dict[str, list[_Open]] = {}

    def decide(
        self,
        agents: list[str],
        obs: dict[str, np.ndarray],
        idx: np.ndarray,
        decision: np.ndarray,
        u: np.ndarray,
        label: tuple[np.ndarray, ...],
    ) -> Rows:
        """The agents at ``idx`` decided on the stacked ``obs``: close their open transitions
        (next_obs = this observation) and open new ones. ``label`` = (labelled (A,),
        label_decision (A,), label_params (A, 3, 2)). → the closed transitions."""
        names = [agents[i] for i in idx.tolist()]
        closed = self._close(names, obs, idx, np.zeros(len(idx), bool), ended=False)
        labelled, ldec, lpar = label
        keys = _keys(obs)
        for a, i in zip(names, idx.tolist()):
            rows = {k: obs[k][i] for k in keys}
            self._open[a] = _Open(rows, int(decision[i]), u[i], float(labelled[i]),
                                  int(ldec[i]), lpar[i])  # fmt: skip
        return closed

    def reward(self, agents: list[str], rewards: np.ndarray) -> None:
        """Add one simulation step's rewards (A,) of ``agents`` to their open transitions."""
        for a, r in zip(agents, rewards.tolist()):
            t = self._open.get(a)
            if t is not None:
                t.reward += self.scale * self.gamma_step**t.steps * r
                t.steps += 1

    def end(self, agents: list[str], obs: dict[str, np.ndarray], terminal: np.ndarray,
            arrived: np.ndarray) -> Rows:  # fmt: skip
        """Close the transitions of ``agents`` whose trip or episode ended; ``obs`` their last
        stacked observations, ``terminal`` (A,) terminated (not truncated), ``arrived`` (A,)
        the termination was an arrival."""
        done = terminal & ~(arrived & self.bootstrap_arrival)
        return self._close(agents, obs, np.arange(len(agents)), done, ended=True)

    def _close(self, names: list[str], obs: dict[str, np.ndarray], idx: np.ndarray,
               done: np.ndarray, ended: bool) -> Rows:  # fmt: skip
        """Close the open transitions of ``names`` (``obs[idx]`` their next observations) and
        emit those that have their n decisions, all of an agent's if its trip ``ended``."""
        items, rows, returns = [], [], []
        for j, a in enumerate(names):
            if a not in self._open:
                continue
            queue = self._waiting.setdefault(a, [])
            queue.append(self._open.pop(a))
            starts = range(len(queue)) if ended else range(len(queue) >= self.n_step)
            for k in starts:
                items.append(queue[k])
                rows.append(j)
                returns.append(self._n_step(queue[k:]))
            if ended:
                del self._waiting[a]
            elif len(queue) >= self.n_step:
                queue.pop(0)
        rows, keys = np.array(rows, np.int64), _keys(obs)
        return {
            "obs": {k: _stack([t.obs[k] for t in items], obs[k]) for k in keys},
            "next_obs": {k: obs[k][idx[rows]] for k in keys},
            "decision": np.array([t.decision for t in items], np.int64),
            "params": _stack([t.u for t in items], np.zeros((0, 3, 2), np.float32)),
            "reward": np.array([r for r, _ in returns], np.float32),
            "done": done[rows].astype(np.float32),
            "discount": np.array([d for _, d in returns], np.float32),
            "labelled": np.array([t.labelled for t in items], np.float32),
            "label_decision": np.array([t.label_decision for t in items], np.int64),
            "label_params": _stack([t.label_params for t in items], np.zeros((0, 3, 2))),
        }

    def _n_step(self, chain: list[_Open]) -> tuple[float, float]:
        """(reward, discount) of the transition that starts ``chain`` and ends at its last."""
        reward, discount = 0.0, 1.0
        for t in chain:
            reward += discount * t.reward
            discount *= self.gamma_step**t.steps
        return reward, discount


def _keys(obs: dict[str, np.ndarray]) -> tuple[str, ...]:
    """The keys a transition keeps: the batch's, with its ``EXTRA`` vector where it has one."""
    return (*OBS_KEYS, EXTRA) if EXTRA in obs else OBS_KEYS


def _stack(rows: list[np.ndarray], like: np.ndarray) -> np.ndarray:
    """``np.stack(rows)``, or an empty array shaped like ``like``'s rows."""
    if rows:
        return np.stack(rows)
    return np.zeros((0, *like.shape[1:]), like.dtype)
