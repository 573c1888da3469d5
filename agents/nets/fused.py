"""Fused actor + critic inference path (no autograd), numerically equal to the reference modules.

Why: at B = 128 agents the reference path spends most of its time in per-op overhead, fresh
large allocations (page faults on every step) and a slow CPU ``tanh``. This path:

- runs the GRUs of both networks together: the six (lane, vehicle, light) × (actor, critic)
  GRUs share N = 3B rows and run as one ``baddbmm`` per time step (the two ego GRUs as another);
- re-parameterises each GRU so a step is ``baddbmm → sigmoid → addcmul → sigmoid → lerp``:
  tanh(a) = 2σ(2a) − 1 and h = 2h̃ − 1 are folded into derived weights (see
  :func:`_derive_gru`), so the hidden update is a single ``lerp`` on h̃;
- writes every intermediate into preallocated buffers (``out=``) that grow with the largest
  batch seen, so a fleet whose size changes every step does not allocate every step.

Only the default LCA (history, lane-wise, star) is fused; :class:`FusedActorCritic` refuses
other configs and callers fall back to the reference modules. Derived weights are snapshots:
call :meth:`FusedActorCritic.refresh` after the source networks change.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from agents.nets.lca import LCA, N_LANES, N_NODE_TYPES, HistoryGRU
from agents.nets.networks import ACTION_DIM, N_DECISIONS, N_PARAMS, Actor, Critic, gate_input

_GROWTH = 1.25
"""Buffers grow to this factor times the largest row count seen, so a fleet whose size drifts
step by step reuses one allocation (a fresh buffer per size cost 3 ms a step at 2,000 AVs)."""


class _Arena:
    """Named buffers with a leading group axis and a row capacity; :meth:`take` returns views
    of the first n rows, allocating again only when n exceeds the capacity."""

    def __init__(self, shapes: dict[str, tuple[int, ...]],
                 fill: Callable[[dict[str, Tensor]], None] | None = None) -> None:  # fmt: skip
        self.shapes, self.fill, self.cap = shapes, fill, 0
        self._full: dict[str, Tensor] = {}

    def take(self, n: int) -> dict[str, Tensor]:
        if n > self.cap:
            self.cap = max(n, int(self.cap * _GROWTH))
            self._full = {
                k: torch.empty(g, self.cap, *rest) for k, (g, *rest) in self.shapes.items()
            }
            if self.fill is not None:
                self.fill(self._full)
        return {k: v[:, :n] for k, v in self._full.items()}


def _derive_gru(gru: HistoryGRU) -> dict[str, Tensor]:
    """Derived weights of one GRU for the h̃ = (h + 1)/2, tanh(a) = 2σ(2a) − 1 formulation.

    With these, one step is: ``out = [P_rz, c] + h̃·whᵀ`` (pre-activations of r, z and
    2·(W_hn·h + b_hn)), ``a = P_n + r ⊙ out_n`` (= 2× the tanh argument), ``s = σ(a)``,
    ``h̃ ← s + u·(h̃ − s)``. Keys (transposed weights ready for ``addmm``):

    - ``wx_rz`` (F, 2D), ``bx_rz`` (2D): P_rz = x·wx_rz + bx_rz (both biases, minus W_hh·1);
    - ``wx_n`` (F, D), ``bx_n`` (D): P_n = 2·(W_in·x + b_in);
    - ``c`` (D): constant of the recurrent n block, 2·(b_hn − W_hn·1);
    - ``wh`` (D, 3D): recurrent weights on h̃; ``k0`` (3D): h̃₀·wh with h̃₀ = 0.5 (h₀ = 0).
    """
    d = gru.d
    w_ih, w_hh, b_ih, b_hh = gru.w_ih, gru.w_hh, gru.b_ih, gru.b_hh
    row_sum = w_hh.sum(dim=1)  # W_hh·1, from h = 2h̃ − 1
    wh = torch.cat((2.0 * w_hh[: 2 * d], 4.0 * w_hh[2 * d :]))
    return {
        "wx_rz": w_ih[: 2 * d].t().contiguous(),
        "bx_rz": b_ih[: 2 * d] + b_hh[: 2 * d] - row_sum[: 2 * d],
        "wx_n": (2.0 * w_ih[2 * d :]).t().contiguous(),
        "bx_n": 2.0 * b_ih[2 * d :],
        "c": 2.0 * (b_hh[2 * d :] - row_sum[2 * d :]),
        "wh": wh.t().contiguous(),
        "k0": 0.5 * wh.sum(dim=1),
    }


class _GroupGRU:
    """G GRUs with equal row count N run in lock-step; buffers preallocated per (N, z)."""

    def __init__(self, grus: list[HistoryGRU]) -> None:
        self.w = [_derive_gru(g) for g in grus]
        self.d = grus[0].d
        self.wh = torch.stack([w["wh"] for w in self.w])  # (G, D, 3D)
        self.k0 = torch.stack([w["k0"] for w in self.w])[:, None, :]  # (G, 1, 3D)
        self.half = torch.full((1, 1, 1), 0.5)
        self._arenas: dict[int, _Arena] = {}  # per history length z

    def _fill_constant(self, bufs: dict[str, Tensor]) -> None:
        """The recurrent n block's constant, written once per allocation."""
        for i, w in enumerate(self.w):
            bufs["p"][i, :, :, 2 * self.d :] = w["c"]

    def _buffers(self, n: int, z: int) -> dict[str, Tensor]:
        if z not in self._arenas:
            g, d = len(self.w), self.d
            shapes = {"p": (g, z, 3 * d), "pn": (g, z, d), "out": (g, 3 * d),
                      "rz": (g, 2 * d), "a": (g, d), "h": (g, d)}  # fmt: skip
            self._arenas[z] = _Arena(shapes, self._fill_constant)
        return self._arenas[z].take(n)

    def __call__(self, xs: list[Tensor]) -> Tensor:
        """xs: G inputs (N, z, F_g) → final hidden h (G, N, D) (a buffer, valid until next call)."""
        n, z = xs[0].shape[0], xs[0].shape[1]
        d = self.d
        buf = self._buffers(n, z)
        p, pn, out, rz, a, h = buf["p"], buf["pn"], buf["out"], buf["rz"], buf["a"], buf["h"]
        for g, x in enumerate(xs):
            w, x2 = self.w[g], x.reshape(n * z, -1)
            # Strided out= (leading dimension 3D) is written in place by BLAS, no copy.
            torch.addmm(w["bx_rz"], x2, w["wx_rz"], out=p[g].view(n * z, 3 * d)[:, : 2 * d])
            torch.addmm(w["bx_n"], x2, w["wx_n"], out=pn[g].view(n * z, d))
        for t in range(z):
            pt = p[:, :, t]  # (G, N, 3D) strided view, no copy
            if t == 0:
                torch.add(pt, self.k0, out=out)  # h₀ = 0: no matmul needed
            else:
                torch.baddbmm(pt, h, self.wh, out=out)
            torch.sigmoid(out[..., : 2 * d], out=rz)
            torch.addcmul(pn[:, :, t], rz[..., :d], out[..., 2 * d :], out=a)
            torch.sigmoid(a, out=a)  # s = (n + 1) / 2
            torch.lerp(a, self.half if t == 0 else h, rz[..., d:], out=h)  # h̃ ← s + u·(h̃ − s)
        return h.mul_(2.0).sub_(1.0)  # back to h = 2h̃ − 1


def _stack_t(ws: list[Tensor]) -> Tensor:
    """Stack transposed weights: list of (O, I) → (G, I, O)."""
    return torch.stack([w.t() for w in ws]).contiguous()


class FusedActorCritic:
    """Inference-only fused forward of an (actor, critic) pair.

    ``__call__(obs) -> (params (B, 3, 2), q (B, 3), hold (B,) | None)`` with
    q = critic(obs, actor(obs)) and hold = actor.hold_score(obs).
    """

    def __init__(self, actor: Actor, critic: Critic) -> None:
        for lca in (actor.lca, critic.lca):
            c = lca.cfg
            if not (c.history and c.lane_wise and c.star):
                raise ValueError("FusedActorCritic supports only the default LCA configuration")
        self.actor, self.critic = actor, critic
        self.refresh()

    @torch.no_grad()
    def refresh(self) -> None:
        """Re-derive all fused weights from the current actor and critic parameters."""
        la, lc = self.actor.lca, self.critic.lca
        self.d = la.cfg.d
        self._abuf = _Arena({"q": (2, self.d), "es": (2, self.d)})
        self._pbuf = _Arena({"prod": (2 * N_NODE_TYPES, N_LANES, self.d)})
        self.nodes_gru = _GroupGRU(
            [la.lane_rnn, la.veh_rnn, la.light_rnn, lc.lane_rnn, lc.veh_rnn, lc.light_rnn]
        )
        self.ego_gru = _GroupGRU([la.ego_rnn, lc.ego_rnn])
        lcas: list[LCA] = [la, lc]
        d = self.d
        # logits = (W_q·h_e)ᵀ(W_k·h_n)·scale = (h_eᵀ·M)·h_n with M = W_qᵀ·W_k·scale: one small
        # matmul per agent instead of a key projection of every node.
        w_k = [m.w_kv.weight[:d] for m in lcas]
        w_v = [m.w_kv.weight[d:] for m in lcas]
        self.m_qk = torch.stack([m.w_q.weight.t() @ wk * m.scale for m, wk in zip(lcas, w_k)])
        # Σ_t att·(W_v·h_t) = W_v·(Σ_t att·h_t): W_v moves past the weighted sum and is folded
        # into the fusion layer, W8' = W8·blockdiag(W_v, W_v, W_v).
        wf = []
        for m, wv in zip(lcas, w_v):
            w8 = m.fuse[0].weight  # (D, 3D), (D, 4D) with ego fusion
            wf.append(torch.cat([w8[:, i * d : (i + 1) * d] @ wv for i in range(N_LANES)], dim=1))
        self.wf_t = _stack_t(wf)  # (2, 3D, D)
        # ego fusion: the fusion layer's next D input columns take h_ego directly, the last X
        # the observation's extra vector
        ego = [N_LANES * d + (d if m.cfg.ego_fusion else 0) for m in lcas]
        self.we_t = _stack_t([m.fuse[0].weight[:, N_LANES * d : e] for m, e in zip(lcas, ego)])
        self.wx_t = _stack_t([m.fuse[0].weight[:, e:] for m, e in zip(lcas, ego)])  # (2, X, D)
        self.bf = torch.stack([m.fuse[0].bias for m in lcas])[:, None, :]
        self.actor_head = [t.detach().clone() for t in self.actor.head.parameters()]
        gate = self.actor.gate
        self.gate = None if gate is None else [t.detach().clone() for t in gate.parameters()]
        self.critic_w10 = [t.detach().clone() for t in self.critic.act_embed.parameters()]
        self.critic_head = [t.detach().clone() for t in self.critic.head.parameters()]

    @torch.inference_mode()
    def __call__(
        self, obs: dict[str, Tensor], noise: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        """obs (B, ...) → (params (B, 3, 2), q (B, 3), hold score (B,) or None).

        ``noise`` (B, 3, 2), if given, is added to the actor output and clipped to [-1, 1]
        before the critic, so q scores the executed (noisy) params.
        """
        b, z = obs["ego"].shape[0], obs["ego"].shape[1]
        d = self.d
        lanes = obs["lanes"].reshape(b * N_LANES, z, -1)
        veh = obs["vehicles"].reshape(b * N_LANES, z, -1)
        light = obs["lights"].reshape(b * N_LANES, z, -1)
        ego = obs["ego"]
        h_nodes = self.nodes_gru([lanes, veh, light, lanes, veh, light])  # (6, 3B, D)
        h_ego = self.ego_gru([ego, ego])  # (2, B, D)
        # Rows of h_nodes per net are ordered (type, b, lane); attention runs in that layout
        # (elementwise products + sums) so nothing is permuted or copied.
        buf = self._abuf.take(b)
        q = torch.bmm(h_ego, self.m_qk, out=buf["q"])  # (2, B, D)
        nodes = h_nodes.view(2, N_NODE_TYPES, b, N_LANES, d)
        prod_buf = self._pbuf.take(b)["prod"].view(2, N_NODE_TYPES, b, N_LANES, d)
        prod = torch.mul(nodes, q.view(2, 1, b, 1, d), out=prod_buf)
        logits = prod.sum(-1)  # (2, T, B, L)
        mask = (obs["node_mask"] > 0.5).permute(2, 0, 1)  # (T, B, L)
        logits = logits.masked_fill_(~mask, -1e9)
        att = torch.softmax(logits, dim=1).mul_(mask.any(0))  # all-masked lane → 0
        wsum = torch.mul(nodes, att.unsqueeze(-1), out=prod_buf).sum(1)  # (2, B, L, D)
        e = wsum.view(2, b, N_LANES * d)
        e_s = torch.baddbmm(self.bf, e, self.wf_t, out=buf["es"])  # (2, B, D)
        if self.we_t.shape[1]:
            e_s.baddbmm_(h_ego, self.we_t)
        if self.wx_t.shape[1]:
            e_s.baddbmm_(obs["extra"].unsqueeze(0).expand(2, -1, -1), self.wx_t)
        torch.relu_(e_s)
        w1, b1, w2, b2 = self.actor_head
        hid = torch.relu(torch.addmm(b1, e_s[0], w1.t()))
        params = torch.sigmoid(2.0 * torch.addmm(b2, hid, w2.t())) * 2.0 - 1.0  # tanh
        if noise is not None:
            params = (params + noise.view(b, -1)).clamp_(-1.0, 1.0)
        assert params.shape[1] == ACTION_DIM
        params = params.view(b, N_DECISIONS, N_PARAMS)
        hold = None
        if self.gate is not None:
            hold = torch.addmm(self.gate[1], gate_input(hid, obs), self.gate[0].t())[:, 0]
        return params, self._critic_head(e_s[1], params), hold

    def _critic_head(self, e_s: Tensor, params: Tensor) -> Tensor:
        """Q (B, 3) from the critic's state embedding (B, D) and params (B, 3, 2)."""
        w10, b10 = self.critic_w10
        c1, cb1, c2, cb2 = self.critic_head
        b = len(params)
        if not self.critic.multi_pass:
            e_a = torch.relu(torch.addmm(b10, params.view(b, ACTION_DIM), w10.t()))
            hid = torch.relu(torch.addmm(cb1, torch.cat((e_s, e_a), dim=1), c1.t()))
            return torch.addmm(cb2, hid, c2.t())
        w = w10.view(-1, N_DECISIONS, N_PARAMS)
        e_a = torch.relu(torch.einsum("bpk,dpk->bpd", params, w) + b10)
        hid = torch.relu(torch.cat((e_s.unsqueeze(1).expand_as(e_a), e_a), dim=-1) @ c1.t() + cb1)
        return torch.einsum("bpd,pd->bp", hid, c2) + cb2
