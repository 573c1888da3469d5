"""Encoders of the paper's sensor-fusion baselines over the raster of :mod:`agents.nets.raster`
and LiDAR point tokens: DRL-MF (Fu et al. 2022: image and point-cloud features, no map or
pose) and TransFuser (Prakash et al. 2021: camera and LiDAR branches fused by a transformer).

A point token is one detected vehicle slot (3 lanes × front/rear) with its z frames of
(distance, lateral position relative to the ego, relative speed, relative heading, length,
width) in the observation's units; absent slots are masked. Neither encoder sees the lane
waypoints; DRL-MF's ego input is its speed alone (no pose), TransFuser's the ego's frame
features, which it measures (speed, as TransFuser's measured velocity input, and pose).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from agents.nets.raster import CHANNELS, LANE_WIDTH, RasterCNN, rasterize

POINT_DIM = 6
"""Features per vehicle slot and frame."""
_LAT = 2.0


def point_tokens(obs: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
    """→ (tokens (B, 6, z·POINT_DIM), present (B, 6) bool), lateral positions relative to the
    ego [/ 2 m]."""
    ego, veh = obs["ego"], obs["vehicles"]
    b, z = ego.shape[:2]
    v = veh.view(b, 3, z, 2, 6)
    centre = (LANE_WIDTH / _LAT) * torch.tensor([1.0, 0.0, -1.0], device=veh.device)
    lat = centre[None, :, None, None] + v[..., 5] - ego[:, None, :, None, 4]
    feats = torch.stack((v[..., 0], lat, v[..., 1], v[..., 2], v[..., 3], v[..., 4]), dim=-1)
    present = (v[..., 4] > 0).any(2)  # (B, 3, 2): seen in some frame
    feats = feats * (v[..., 4:5] > 0)
    tokens = feats.permute(0, 1, 3, 2, 4).reshape(b, 6, z * POINT_DIM)
    return tokens, present.reshape(b, 6)


class MultiFeatureEncoder(nn.Module):
    """DRL-MF: CNN over the map-less raster ⊕ PointNet (shared MLP, max-pool) over point
    tokens ⊕ ego speed history → linear → E_s (B, D)."""

    def __init__(self, z: int, d: int, lidar_range: float, camera_range: float) -> None:
        super().__init__()
        self.ranges = (lidar_range, camera_range)
        self.cnn = RasterCNN(z * CHANNELS, d)
        self.image = nn.Linear(d * RasterCNN.cells(), d)
        self.points = nn.Sequential(nn.Linear(z * POINT_DIM, d), nn.ReLU(), nn.Linear(d, d))
        self.speed = nn.Linear(z, d)
        self.out = nn.Sequential(nn.ReLU(), nn.Linear(3 * d, d), nn.ReLU())

    def forward(self, obs: dict[str, Tensor]) -> Tensor:
        img = self.image(self.cnn(rasterize(obs, *self.ranges, with_map=False)).flatten(1))
        tokens, present = point_tokens(obs)
        pts = self.points(tokens).masked_fill(~present[..., None], -1e9).amax(1)
        pts = torch.where(present.any(1, keepdim=True), pts, torch.zeros_like(pts))
        return self.out(torch.cat((img, pts, self.speed(obs["ego"][..., 0])), dim=1))


class TransFuserEncoder(nn.Module):
    """TransFuser: camera tokens (the raster CNN's cells, with map and lights) and LiDAR point
    tokens, plus an ego token, through one transformer layer with learned token-type
    embeddings; the ego token's output → E_s (B, D)."""

    def __init__(self, z: int, d: int, lidar_range: float, camera_range: float) -> None:
        super().__init__()
        self.ranges = (lidar_range, camera_range)
        self.cnn = RasterCNN(z * CHANNELS, d)
        self.points = nn.Linear(z * POINT_DIM, d)
        self.ego = nn.Linear(z * 5, d)
        self.pos = nn.Parameter(torch.zeros(1, RasterCNN.cells(), d))
        self.kind = nn.Parameter(torch.zeros(3, d))  # ego, camera, lidar
        self.layer = nn.TransformerEncoderLayer(d, nhead=4, dim_feedforward=2 * d,
                                                batch_first=True, dropout=0.0)  # fmt: skip
        self.out = nn.Sequential(nn.Linear(d, d), nn.ReLU())

    def forward(self, obs: dict[str, Tensor]) -> Tensor:
        b = obs["ego"].shape[0]
        cam = self.cnn(rasterize(obs, *self.ranges)).flatten(2).transpose(1, 2)  # (B, N, D)
        tokens, present = point_tokens(obs)
        seq = torch.cat((self.ego(obs["ego"].flatten(1))[:, None] + self.kind[0],
                         cam + self.pos + self.kind[1], self.points(tokens) + self.kind[2]),
                        dim=1)  # fmt: skip
        pad = torch.cat((present.new_zeros(b, 1 + cam.shape[1]), ~present), dim=1)
        return self.out(self.layer(seq, src_key_padding_mask=pad)[:, 0])
