"""Actor, critic and masked decision selection (paper §IV-D, DESIGN §10).

Decisions: 0 = left change, 1 = follow, 2 = right change. Params per decision:
(steering, accel_brake) in [-1, 1].
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from agents.nets.fusion import MultiFeatureEncoder, TransFuserEncoder
from agents.nets.lca import LCA, N_LANES, LCAConfig, fast_tanh
from agents.nets.raster import BevEncoder

N_DECISIONS = 3
"""Parameterized-action decisions (left change, follow, right change)."""
N_PARAMS = 2
"""Continuous parameters per decision (steering, accel_brake)."""
ACTION_DIM = N_DECISIONS * N_PARAMS
FOLLOW = 1
"""Fallback decision when a row has every decision masked (should not happen per DESIGN §6:
following the current lane is always physically possible; the env stops the car at the end)."""

assert N_DECISIONS == N_LANES  # one decision per target lane (left, current, right)


def make_encoder(cfg: LCAConfig) -> nn.Module:
    """The state encoder ``cfg.encoder`` names: obs dict (B, ...) → E_s (B, D)."""
    if cfg.encoder == "lca":
        return LCA(cfg)
    cls = {"bev": BevEncoder, "mf": MultiFeatureEncoder, "transfuser": TransFuserEncoder}
    return cls[cfg.encoder](cfg.z, cfg.d, cfg.lidar_range, cfg.camera_range)


class _ZeroOutput:
    head: nn.Sequential

    def zero_output(self) -> None:
        """Zero the last layer: the output is 0 for every input (a residual's start)."""
        with torch.no_grad():
            self.head[-1].weight.zero_()
            self.head[-1].bias.zero_()


LEAD_SPREAD = "lead_spread"
"""Optional observation key (B,) that only the hold gate reads: the standard deviation of the
leader's speed about its mean over ``LearnerConfig.hold_tau``, divided by that mean (at least
1 m/s) [-]; large in stop-and-go waves, small behind a steady leader. The driver tracks it
(``agents.driver.Lead``); absent, it is 0."""


def gate_input(hid: Tensor, obs: dict[str, Tensor]) -> Tensor:
    """(B, d + 1): the hidden features (B, d) and ``obs[LEAD_SPREAD]`` (0 where absent)."""
    spread = obs.get(LEAD_SPREAD)
    spread = hid.new_zeros(len(hid)) if spread is None else spread.to(hid.dtype)
    return torch.cat([hid, spread[:, None]], dim=1)


class Actor(_ZeroOutput, nn.Module):
    """Encoder → MLP → tanh. obs dict (B, ...) → params (B, 3, 2) in [-1, 1]; with ``scores``
    (P-DDPG) (B, 3, 3): each decision's parameters and then its score.

    ``gate``: a hold gate, one linear score (B,) of the MLP's hidden features and of the
    observation's optional ``LEAD_SPREAD`` (:func:`gate_input`), zero at the start; where it
    is > 0 the driver holds speed (``LearnerConfig.hold_gate``). Gradient training leaves it
    alone (it is not in the optimiser); the fleet search sets it."""

    def __init__(self, cfg: LCAConfig, scores: bool = False, gate: bool = False) -> None:
        super().__init__()
        d = cfg.d
        self.lca = make_encoder(cfg)
        self.scores = scores
        self.width = N_PARAMS + scores
        self.head = nn.Sequential(
            nn.Linear(d, d), nn.ReLU(), nn.Linear(d, N_DECISIONS * self.width)
        )  # W9
        self.gate = nn.Linear(d + 1, 1) if gate else None
        if self.gate is not None:
            nn.init.zeros_(self.gate.weight)
            nn.init.zeros_(self.gate.bias)

    def forward(self, obs: dict[str, Tensor]) -> Tensor:
        return self.with_hold(obs)[0]

    def with_hold(self, obs: dict[str, Tensor]) -> tuple[Tensor, Tensor | None]:
        """(the forward's output, the hold gate's score (B,) or None without a gate) from one
        pass of the encoder and the MLP; hold where the score is > 0."""
        hid = self.head[1](self.head[0](self.lca(obs)))
        out = fast_tanh(self.head[2](hid)).view(-1, N_DECISIONS, self.width)
        return out, None if self.gate is None else self.gate(gate_input(hid, obs)).squeeze(-1)

    def hold_score(self, obs: dict[str, Tensor]) -> Tensor | None:
        """(B,) the hold gate's score (hold where > 0), or None without a gate."""
        return self.with_hold(obs)[1]

    def gradient_parameters(self) -> list[nn.Parameter]:
        """Every parameter but the gate's (the gate is searched, not trained by gradient)."""
        gate = set() if self.gate is None else set(self.gate.parameters())
        return [p for p in self.parameters() if p not in gate]


class Critic(_ZeroOutput, nn.Module):
    """Own LCA + ReLU(W10·A) → MLP → Q for all three decisions.

    obs dict (B, ...), params (B, 3, 2) → Q (B, 3) where Q[:, p] = Q(s, p, params[:, p]).
    ``multi_pass`` (MP-DQN, Bester et al. 2019): Q[:, p] sees only decision p's parameters
    (the other rows are zeroed in its pass). In the paper's single pass every Q[:, p] depends
    on all six numbers, so the actor's update of one row is pushed by the other decisions' Q
    (P-DQN's "false gradient").
    """

    def __init__(self, cfg: LCAConfig, multi_pass: bool = False, joint: bool = False) -> None:
        """``joint`` (P-DDPG): one Q (B, 1) of the whole action (B, 3, 3), parameters and
        decision scores together."""
        super().__init__()
        d = cfg.d
        self.lca = make_encoder(cfg)
        width = ACTION_DIM + N_DECISIONS * joint
        self.act_embed = nn.Linear(width, d)  # W10
        self.head = nn.Sequential(
            nn.Linear(2 * d, d), nn.ReLU(), nn.Linear(d, 1 if joint else N_DECISIONS)
        )  # W11
        self.multi_pass = multi_pass
        self.width = width

    def forward(self, obs: dict[str, Tensor], params: Tensor) -> Tensor:
        e_s = self.lca(obs)
        if not self.multi_pass:
            e_a = torch.relu(self.act_embed(params.reshape(-1, self.width)))
            return self.head(torch.cat((e_s, e_a), dim=-1))
        # pass p embeds W10's columns of row p only: (B, 3, D)
        w = self.act_embed.weight.view(-1, N_DECISIONS, N_PARAMS)
        e_a = torch.relu(torch.einsum("bpk,dpk->bpd", params, w) + self.act_embed.bias)
        x = torch.cat((e_s.unsqueeze(1).expand_as(e_a), e_a), dim=-1)
        hid = self.head[1](self.head[0](x))  # (B, 3, D)
        out = self.head[2]
        return torch.einsum("bpd,pd->bp", hid, out.weight) + out.bias  # pass p's Q of p


def masked_q(q: Tensor, action_mask: Tensor) -> Tensor:
    """q (B, 3), action_mask (B, 3) (bool or 0/1) → q with masked entries set to -inf."""
    return q.masked_fill(
        action_mask <= 0 if action_mask.dtype != torch.bool else ~action_mask, -torch.inf
    )


def select(q: Tensor, action_mask: Tensor) -> Tensor:
    """Argmax over unmasked Q. q (B, 3), action_mask (B, 3) → decision (B,) int64.

    A row with every decision masked falls back to ``FOLLOW`` (1) instead of returning an
    arbitrary index of an all -inf row.
    """
    qm = masked_q(q, action_mask)
    dec = qm.argmax(dim=-1)
    any_ok = torch.isfinite(qm).any(dim=-1)
    return torch.where(any_ok, dec, torch.full_like(dec, FOLLOW))
