"""What a step returns: the PettingZoo API's per-agent dicts (``step``) or a ``BatchStep``
(``step_batch``), from the step's per-agent results."""

from __future__ import annotations

from collections.abc import Callable
from itertools import repeat
from typing import NamedTuple

import numpy as np

Dicts = tuple[dict, dict, dict, dict, dict]
"""(observations, rewards, terminations, truncations, infos), each keyed by agent."""


class BatchStep(NamedTuple):
    """One ``step_batch``: rows follow ``agents``, the A agents that acted."""

    agents: list[str]
    """(A,) the agents that acted, in the order of their actions."""
    rewards: np.ndarray
    """(A,) float64 rewards (``step``'s)."""
    terminated: np.ndarray
    """(A,) bool: the agent's trip ended (``events`` says why)."""
    truncated: np.ndarray
    """(A,) bool: the episode reached its time limit."""
    events: list[str]
    """(A,) 'arrived', a terminal reason, or ''."""
    entered: list[str]
    """Agents that entered the network this step (they act from the next step on)."""
    copy: np.ndarray
    """(A,) int32 the copy of the scenario each agent drives in (``EnvConfig.copies``)."""


def batch_step(agents: list[str], ended: set[str], truncate: bool, rewards: dict[str, float],
               events: dict[str, str], copy: np.ndarray) -> BatchStep:  # fmt: skip
    """The ``BatchStep`` of ``agents`` (``ended``: whose trips ended; ``truncate``: the time
    limit was reached; ``copy`` (A,): their copies)."""
    n = len(agents)
    return BatchStep(
        agents, np.fromiter(map(rewards.get, agents, repeat(0.0)), np.float64, n),
        np.fromiter(map(ended.__contains__, agents), bool, n),
        np.fromiter((truncate and a not in ended for a in agents), bool, n),
        list(map(events.get, agents, repeat(""))), [], copy,
    )  # fmt: skip


def api_dicts(agents: list[str], ended: set[str], truncate: bool, obs: dict, rewards: dict,
              terms: dict, events: dict, replaced: set[str], last_obs: Callable[[str], dict],
              copy: np.ndarray) -> Dicts:  # fmt: skip
    """The PettingZoo dicts of the agents that acted, filled by C-level maps and patched where
    an event happened (``replaced``: agents whose decision the mask forbade; ``last_obs``: the
    observation of an agent not observed this step; ``copy`` (A,): their copies)."""
    terminated = dict.fromkeys(agents, False)
    terminated.update(dict.fromkeys(ended, True))
    truncated = dict.fromkeys(agents, truncate)
    truncated.update(dict.fromkeys(ended, False))
    infos = {a: {"reward_terms": t if t is not None else {}, "event": e, "copy": c}
             for a, t, e, c in zip(agents, map(terms.get, agents),
                                   map(events.get, agents, repeat("")), copy.tolist())}  # fmt: skip
    for a in replaced.intersection(infos):
        infos[a]["decision_replaced"] = True
    obs_out = dict(zip(agents, map(obs.get, agents)))
    for a in [a for a, o in obs_out.items() if o is None]:  # not observed this step
        obs_out[a] = last_obs(a)
    rew_out = dict(zip(agents, map(rewards.get, agents, repeat(0.0))))
    return obs_out, rew_out, terminated, truncated, infos


def add_entered(out: Dicts, new: list[str], new_obs: dict[str, dict], fixed_fleet: bool,
                copy: np.ndarray) -> None:  # fmt: skip
    """Add the agents that entered (``new``, their observations, ``copy`` (A,) their copies) to
    a step's dicts."""
    obs_out, rew_out, terminated, truncated, infos = out
    for a, c in zip(new, copy.tolist()):
        if a not in obs_out or fixed_fleet:
            obs_out[a], rew_out[a] = new_obs[a], rew_out.get(a, 0.0)
            terminated[a], truncated[a] = False, False
            info = infos.setdefault(a, {"reward_terms": {}, "event": "", "copy": c})
            info["event"] = "entered"
