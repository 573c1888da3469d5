"""Lane-wise Cross Attention (LCA) state encoder (paper §IV-C, DESIGN §10).

Input is one batch of per-agent observations (DESIGN §6) as a dict of tensors with a leading
batch dimension B:

- ``ego``       (B, z, 5)
- ``lanes``     (B, 3, z, 4m)
- ``vehicles``  (B, 3, z, 12)
- ``lights``    (B, 3, z, 4)
- ``node_mask`` (B, 3, 3)  [lane exists, vehicle(s) detected, light detected] per lane

z and m are read from the shapes (through :class:`LCAConfig`), never hard-coded here.

Pipeline: one GRU per node type embeds the z-step history of every node (hidden state of the
last step, D values); per lane k a star graph with the ego as the only query attends over that
lane's (lane, vehicle, light) nodes, honouring ``node_mask``; a fusion MLP maps
concat(E_left, E_cur, E_right, h_ego) to the state embedding E_s (B, D). The paper fuses the
three lane vectors only; ``LCAConfig.ego_fusion`` explains the added ego embedding.

Ablation flags (paper §V-A): ``history=False`` (NoHIS: a per-frame MLP on the last step instead
of the GRU), ``lane_wise=False`` (NoLANE: one ego attention over all nine nodes),
``star=False`` (NoSTAR: full self-attention over ego + nine nodes before the read-out).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn

N_LANES = 3
"""Lanes per observation (left, current, right); fixed by the observation space."""
N_NODE_TYPES = 3
"""Non-ego node types per lane (lane waypoints, vehicles, light); fixed by the space."""
EGO_DIM = 5
VEH_DIM = 12
LIGHT_DIM = 4
ENCODERS = ("lca", "bev", "mf", "transfuser")
_NEG = -1e9
"""Finite 'minus infinity' for masked attention logits: a fully masked row stays finite."""


@dataclass(frozen=True)
class LCAConfig:
    """Hyper-parameters of the encoder; stored in checkpoints to rebuild the model."""

    z: int = 5
    """History steps per observation (DESIGN §6)."""
    m: int = 10
    """Waypoints per lane; lane features are 4·m wide."""
    d: int = 32
    """Embedding width D (paper: D1 = D2 = D3 = D4 = D)."""
    history: bool = True
    """False → NoHIS ablation (MLP on the last frame instead of a GRU)."""
    lane_wise: bool = True
    """False → NoLANE ablation (one attention over all nodes, no lane-wise fusion)."""
    star: bool = True
    """False → NoSTAR ablation (complete graph: self-attention over ego and all nodes)."""
    ego_fusion: bool = True
    """True → the ego embedding joins the fusion, E_s = W8(E_k-1 ⊕ E_k ⊕ E_k+1 ⊕ h_A). The
    paper's eq. (W8 over the lane vectors only) leaves the agent's own speed, heading and offset
    in E_s only through the attention weights. False → the paper's form (and every checkpoint
    written before this field, see :meth:`from_dict`)."""
    encoder: str = "lca"
    """State encoder (``agents.nets.networks.make_encoder``): lca (this module) | bev (NoVEC:
    raster + CNN) | mf (DRL-MF: map-less raster + point cloud) | transfuser (raster and point
    tokens through a transformer)."""
    lidar_range: float = 90.0
    """LiDAR range the observation's distances are scaled by [m] (rasters draw in metres)."""
    camera_range: float = 60.0
    """Camera range the observation's light distances are scaled by [m]."""
    extra: int = 0
    """X: width of the observation's ``extra`` vector (the env's opt-in keys ``memory`` and
    ``downstream``, flattened: ``agents.rules.obs_batch``), which joins the fusion beside the
    lane vectors and the ego embedding [features]; 0 = none (lca only)."""

    def __post_init__(self) -> None:
        if self.encoder not in ENCODERS:
            raise ValueError(f"LCAConfig.encoder={self.encoder!r}: choose from {ENCODERS}")
        if self.extra and self.encoder != "lca":
            raise ValueError(f"LCAConfig.extra={self.extra}: only the lca encoder reads it")

    @property
    def lane_dim(self) -> int:
        return 4 * self.m

    def to_dict(self) -> dict[str, int | bool | float | str]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, int | bool | float | str]) -> LCAConfig:
        """Inverse of :meth:`to_dict`; configs stored before ``ego_fusion`` existed are the
        paper's form."""
        return cls(**{"ego_fusion": False, **data})

    @classmethod
    def from_obs_shapes(cls, shapes: dict[str, tuple[int, ...]], **kw: int | bool) -> LCAConfig:
        """Infer z and m from per-agent (unbatched) shapes, e.g. a gymnasium ``Dict`` space."""
        z, lane_dim = shapes["lanes"][-2], shapes["lanes"][-1]
        if lane_dim % 4:
            raise ValueError(f"lanes feature width {lane_dim} is not a multiple of 4 (4·m)")
        return cls(z=int(z), m=int(lane_dim) // 4, **kw)

    def obs_shapes(self) -> dict[str, tuple[int, ...]]:
        """Per-agent observation shapes this encoder expects (no batch dimension)."""
        return {
            "ego": (self.z, EGO_DIM),
            "lanes": (N_LANES, self.z, self.lane_dim),
            "vehicles": (N_LANES, self.z, VEH_DIM),
            "lights": (N_LANES, self.z, LIGHT_DIM),
            "node_mask": (N_LANES, N_NODE_TYPES),
            "action_mask": (N_LANES,),
            **({"extra": (self.extra,)} if self.extra else {}),
        }


def fast_tanh(x: Tensor) -> Tensor:
    """tanh(x) = 2·σ(2x) − 1. Same values, but this build's CPU ``tanh`` kernel measured ~8×
    slower than ``sigmoid`` on (384, 32) tensors, and tanh sits on the GRU's critical path."""
    return torch.sigmoid(2.0 * x) * 2.0 - 1.0


class HistoryGRU(nn.Module):
    """GRU over a short history returning the last hidden state.

    Same parameters and maths as ``nn.GRU`` (gate order r, z, n), written out because for
    z ≈ 5 steps and tiny widths the explicit loop is faster on CPU than ``nn.GRU``'s generic
    path: all input projections are one matmul, and step 0 skips the recurrent matmul
    (h₀ = 0 per the paper, so W_hh·h₀ is just the bias).
    """

    def __init__(self, in_dim: int, d: int) -> None:
        super().__init__()
        self.d = d
        self.w_ih = nn.Parameter(torch.empty(3 * d, in_dim))
        self.w_hh = nn.Parameter(torch.empty(3 * d, d))
        self.b_ih = nn.Parameter(torch.empty(3 * d))
        self.b_hh = nn.Parameter(torch.empty(3 * d))
        bound = 1.0 / math.sqrt(d)  # nn.GRU's default init
        for p in self.parameters():
            nn.init.uniform_(p, -bound, bound)

    def forward(self, x: Tensor) -> Tensor:
        """x (N, z, F) → h_z (N, D)."""
        # unbind/split instead of slicing: their backward is a stack/cat, whereas each slice's
        # backward allocates and zero-fills a full-size gradient.
        sizes = (2 * self.d, self.d)
        steps = torch.nn.functional.linear(x, self.w_ih, self.b_ih).unbind(1)  # z × (N, 3D)
        b_rz, b_n = self.b_hh.split(sizes)
        # Step 0 with h = 0: gh = b_hh.
        g_rz, g_n = steps[0].split(sizes, dim=1)
        r, u = torch.sigmoid(g_rz + b_rz).chunk(2, dim=1)
        n = fast_tanh(g_n + r * b_n)
        h = n - u * n  # (1 - u)·n + u·0
        for g in steps[1:]:
            g_rz, g_n = g.split(sizes, dim=1)
            gh_rz, gh_n = torch.addmm(self.b_hh, h, self.w_hh.t()).split(sizes, dim=1)
            r, u = torch.sigmoid(g_rz + gh_rz).chunk(2, dim=1)
            n = fast_tanh(g_n + r * gh_n)
            h = n + u * (h - n)  # (1 - u)·n + u·h
        return h


class LastFrameMLP(nn.Module):
    """NoHIS ablation: embed only the newest frame. x (N, z, F) → (N, D)."""

    def __init__(self, in_dim: int, d: int) -> None:
        super().__init__()
        self.lin = nn.Linear(in_dim, d)

    def forward(self, x: Tensor) -> Tensor:
        return fast_tanh(self.lin(x[:, -1]))


def _embedder(in_dim: int, d: int, history: bool) -> nn.Module:
    return HistoryGRU(in_dim, d) if history else LastFrameMLP(in_dim, d)


class LCA(nn.Module):
    """Lane-wise cross attention encoder: observation dict → E_s (B, D)."""

    def __init__(self, cfg: LCAConfig) -> None:
        super().__init__()
        self.cfg = cfg
        d = cfg.d
        self.ego_rnn = _embedder(EGO_DIM, d, cfg.history)  # W1
        self.lane_rnn = _embedder(cfg.lane_dim, d, cfg.history)  # W2
        self.veh_rnn = _embedder(VEH_DIM, d, cfg.history)  # W3
        self.light_rnn = _embedder(LIGHT_DIM, d, cfg.history)  # W4
        self.w_q = nn.Linear(d, d, bias=False)  # W5
        # W6 and W7 packed in one matmul: keys and values come from the same nodes.
        self.w_kv = nn.Linear(d, 2 * d, bias=False)
        self.scale = 1.0 / math.sqrt(d)
        if not cfg.star:
            # Complete graph: one self-attention layer over [ego, 9 nodes] (NoSTAR).
            self.sa_qkv = nn.Linear(d, 3 * d, bias=False)
        fuse_in = (N_LANES * d if cfg.lane_wise else d) + (d if cfg.ego_fusion else 0) + cfg.extra
        self.fuse = nn.Sequential(nn.Linear(fuse_in, d), nn.ReLU())  # W8

    def embed_nodes(self, obs: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        """GRU embeddings. → ego (B, D), nodes (B, 3 lanes, 3 types, D)."""
        b = obs["ego"].shape[0]
        z = obs["ego"].shape[1]
        # Lanes are folded into the batch dim so each node type is one GRU call.
        h_ego = self.ego_rnn(obs["ego"])
        h_lane = self.lane_rnn(obs["lanes"].reshape(b * N_LANES, z, -1))
        h_veh = self.veh_rnn(obs["vehicles"].reshape(b * N_LANES, z, -1))
        h_light = self.light_rnn(obs["lights"].reshape(b * N_LANES, z, -1))
        nodes = torch.stack((h_lane, h_veh, h_light), dim=1)  # (3B, 3, D)
        return h_ego, nodes.view(b, N_LANES, N_NODE_TYPES, -1)

    def forward(self, obs: dict[str, Tensor]) -> Tensor:
        """obs dict (see module doc) → E_s (B, D)."""
        h_ego, nodes = self.embed_nodes(obs)
        mask = obs["node_mask"] > 0.5  # (B, 3, 3)
        if not self.cfg.star:
            h_ego, nodes = self._complete_graph(h_ego, nodes, mask)
        if self.cfg.lane_wise:
            e = self._lane_attention(h_ego, nodes, mask).flatten(1)  # (B, 3D)
        else:
            b, d = h_ego.shape
            e = self._lane_attention(h_ego, nodes.reshape(b, 1, -1, d), mask.reshape(b, 1, -1))
            e = e[:, 0]
        parts = (e, *((h_ego,) if self.cfg.ego_fusion else ()),
                 *((obs["extra"],) if self.cfg.extra else ()))  # fmt: skip
        return self.fuse(torch.cat(parts, dim=1))

    def _lane_attention(self, h_ego: Tensor, nodes: Tensor, mask: Tensor) -> Tensor:
        """Star-graph cross attention per lane.

        h_ego (B, D), nodes (B, L, K, D), mask (B, L, K) bool → E (B, L, D). A lane with every
        node masked yields a zero vector (not NaN): its logits are finite and its output is
        multiplied by 0, which also tells the fusion MLP "nothing there".
        """
        d = h_ego.shape[-1]
        q = self.w_q(h_ego)  # (B, D)
        k, v = self.w_kv(nodes).split(d, dim=-1)  # (B, L, K, D) each
        logits = torch.einsum("bd,blkd->blk", q, k) * self.scale
        logits = logits.masked_fill(~mask, _NEG)
        att = torch.softmax(logits, dim=-1) * mask.any(-1, keepdim=True)
        return torch.einsum("blk,blkd->bld", att, v)

    def _complete_graph(self, h_ego: Tensor, nodes: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
        """NoSTAR: one residual self-attention layer over [ego, all nodes] (masked keys).

        h_ego (B, D), nodes (B, 3, 3, D) → same shapes. The ego key is always valid, so every
        softmax row has at least one finite logit.
        """
        b, d = h_ego.shape
        tok = torch.cat((h_ego[:, None], nodes.reshape(b, -1, d)), dim=1)  # (B, 10, D)
        q, k, v = self.sa_qkv(tok).split(d, dim=-1)
        key_ok = torch.cat((mask.new_ones(b, 1), mask.reshape(b, -1)), dim=1)  # (B, 10)
        logits = torch.einsum("bqd,bkd->bqk", q, k) * self.scale
        logits = logits.masked_fill(~key_ok[:, None, :], _NEG)
        tok = tok + torch.einsum("bqk,bkd->bqd", torch.softmax(logits, dim=-1), v)
        return tok[:, 0], tok[:, 1:].reshape(nodes.shape)
