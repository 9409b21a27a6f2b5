"""Observation encoders: point clouds (PointNet, DP3), keypoints and proprioception.

Inputs arrive normalised (``keygen.policies.normalizer``) with an observation-history axis H:
clouds (B, F, P, 3) (the latest F <= H frames), keypoints (B, H, M, 3), proprio (B, H, 10). No batch
norm anywhere, so an encoding does not depend on the other samples of a batch nor on train / eval mode.
"""

from __future__ import annotations

import torch
from torch import nn

from keygen.policies.config import PROPRIO_DIM, PolicyConfig
from keygen.policies.robot_base import BASE_DIM
from keygen.policies.target_token import TARGET_DIM


def max_pool_points(features: torch.Tensor) -> torch.Tensor:
    """Max over the point axis (..., P, C) -> (..., C).

    ``max(dim).values`` rather than ``amax``: the same values, and the same gradient wherever the
    maximum is unique, but its backward scatters through the stored argmax where ``amax``'s
    rebuilds an equality mask over every point: a KeyGen training step (batch 64, one CPU thread)
    took 0.226 s of CPU instead of 0.254 s in an A/B within one process.
    """
    return features.max(dim=-2).values


class PointNetEncoder(nn.Module):
    """KeyGen's z_pc: shared per-point MLP (Linear + GELU), max pool over points, linear projection."""

    def __init__(self, dims: tuple[int, ...], out_dim: int):
        super().__init__()
        layers: list[nn.Module] = []
        prev = 3
        for d in dims:
            layers += [nn.Linear(prev, d), nn.GELU()]
            prev = d
        self.point_mlp = nn.Sequential(*layers)
        self.proj = nn.Linear(prev, out_dim)
        self.out_dim = out_dim

    def forward(self, cloud: torch.Tensor) -> torch.Tensor:  # (..., P, 3) -> (..., out_dim)
        return self.proj(max_pool_points(self.point_mlp(cloud)))


class DP3Encoder(nn.Module):
    """DP3's point encoder (Ze et al. 2024): per-point Linear + LayerNorm + ReLU, max pool, projection
    with LayerNorm to a compact feature (64 in DP3)."""

    def __init__(self, dims: tuple[int, ...], out_dim: int):
        super().__init__()
        layers: list[nn.Module] = []
        prev = 3
        for d in dims:
            layers += [nn.Linear(prev, d), nn.LayerNorm(d), nn.ReLU()]
            prev = d
        self.point_mlp = nn.Sequential(*layers)
        self.proj = nn.Sequential(nn.Linear(prev, out_dim), nn.LayerNorm(out_dim))
        self.out_dim = out_dim

    def forward(self, cloud: torch.Tensor) -> torch.Tensor:  # (..., P, 3) -> (..., out_dim)
        return self.proj(max_pool_points(self.point_mlp(cloud)))


class KeypointEncoder(nn.Module):
    """z_kp: one token per (object slot, keypoint index).

    A token's content is its keypoint's positions over the observation history (H * 3 numbers,
    so motion is visible); an index embedding and an object-slot embedding say which keypoint of
    which object it is (keypoints are semantically ordered by the extractor).
    """

    def __init__(self, obs_horizon: int, num_keypoints: int, num_objects: int, width: int):
        super().__init__()
        self.num_keypoints, self.num_objects = num_keypoints, num_objects
        self.mlp = nn.Sequential(nn.Linear(3 * obs_horizon, width), nn.GELU(), nn.Linear(width, width))
        self.index_embed = nn.Parameter(torch.randn(num_keypoints, width) * 0.02)
        self.slot_embed = nn.Parameter(torch.randn(num_objects, width) * 0.02)

    def forward(self, keypoints: torch.Tensor) -> torch.Tensor:  # (B, H, M, 3) -> (B, M, width)
        b, h, m, _ = keypoints.shape
        per_token = keypoints.permute(0, 2, 1, 3).reshape(b, m, h * 3)  # (B, M, H*3)
        # Token order is object-major: slot s, keypoint k at s * K + k (features.py builds it so).
        embed = (self.slot_embed[:, None, :] + self.index_embed[None, :, :]).reshape(m, -1)  # (M, W)
        return self.mlp(per_token) + embed


class ProprioEncoder(nn.Module):
    """c: the proprioceptive history (H, 10) flattened through a small MLP."""

    def __init__(self, obs_horizon: int, out_dim: int):
        super().__init__()
        self.mlp = nn.Sequential(
            nn.Linear(PROPRIO_DIM * obs_horizon, out_dim), nn.GELU(), nn.Linear(out_dim, out_dim)
        )

    def forward(self, proprio: torch.Tensor) -> torch.Tensor:  # (B, H, 10) -> (B, out_dim)
        return self.mlp(proprio.flatten(1))


def make_cloud_encoder(config: PolicyConfig) -> nn.Module:
    cls = DP3Encoder if config.encoder == "dp3" else PointNetEncoder
    return cls(config.pc_dims, config.pc_out)


class TokenObsEncoder(nn.Module):
    """Observation -> conditioning tokens for the DiT: F cloud tokens (one per cloud frame, with a
    frame embedding), K * objects keypoint tokens, optionally a target token, and the
    proprioception vector (a token and the adaLN conditioning)."""

    def __init__(self, config: PolicyConfig):
        super().__init__()
        w = config.width
        self.cloud = make_cloud_encoder(config)
        self.cloud_proj = nn.Linear(config.pc_out, w)
        self.frame_embed = nn.Parameter(torch.randn(config.cloud_frames, w) * 0.02)
        self.proprio = ProprioEncoder(config.obs_horizon, w)
        self.keypoints = (
            KeypointEncoder(config.obs_horizon, config.num_keypoints, config.num_objects, w)
            if config.num_keypoint_tokens
            else None
        )
        self.type_embed = nn.Parameter(torch.randn(3, w) * 0.02)  # cloud, keypoint, proprio tokens
        # Target token (keygen.policies.target_token): its own MLP and type embedding, kept apart from
        # type_embed so checkpoints without it keep their parameter shapes.
        self.target = (
            nn.Sequential(nn.Linear(TARGET_DIM, w), nn.GELU(), nn.Linear(w, w))
            if config.target_token
            else None
        )
        self.target_embed = nn.Parameter(torch.randn(w) * 0.02) if config.target_token else None
        # Robot base in the yaw frame (keygen.policies.robot_base), folded into c like the origin below.
        self.base = (
            nn.Sequential(nn.Linear(BASE_DIM, w), nn.GELU(), nn.Linear(w, w)) if config.robot_base else None
        )
        # Object frame: where the frame sits in the world (normalised), folded into c (the proprio
        # token and every block's adaLN), so world-fixed goals stay reachable.
        self.origin = (
            nn.Sequential(nn.Linear(3, w), nn.GELU(), nn.Linear(w, w)) if config.frame == "object" else None
        )

    def forward(self, inputs: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        z_pc = self.cloud_proj(self.cloud(inputs["cloud"])) + self.frame_embed  # (B, F, W)
        c = self.proprio(inputs["proprio"])  # (B, W)
        if self.origin is not None:
            c = c + self.origin(inputs["origin"])
        if self.base is not None:
            c = c + self.base(inputs["base"])
        tokens = [z_pc + self.type_embed[0]]
        if self.keypoints is not None:
            tokens.append(self.keypoints(inputs["keypoints"]) + self.type_embed[1])  # (B, M, W)
        if self.target is not None:
            tokens.append((self.target(inputs["target"]) + self.target_embed)[:, None])  # (B, 1, W)
        tokens.append((c + self.type_embed[2])[:, None])  # (B, 1, W)
        return torch.cat(tokens, dim=1), c  # (B, C, W), (B, W)


class GlobalObsEncoder(nn.Module):
    """Observation -> one global conditioning vector for the UNet (DP3): per frame the cloud feature
    and a proprioception feature per history step, all concatenated."""

    def __init__(self, config: PolicyConfig, proprio_dim: int = 64):
        super().__init__()
        self.cloud = make_cloud_encoder(config)
        self.proprio = nn.Sequential(
            nn.Linear(PROPRIO_DIM, proprio_dim), nn.ReLU(), nn.Linear(proprio_dim, proprio_dim)
        )
        self.out_dim = config.cloud_frames * config.pc_out + config.obs_horizon * proprio_dim

    def forward(self, inputs: dict[str, torch.Tensor]) -> torch.Tensor:
        z_pc = self.cloud(inputs["cloud"]).flatten(1)  # (B, F * pc_out)
        return torch.cat([z_pc, self.proprio(inputs["proprio"]).flatten(1)], dim=-1)  # (B, out_dim)
