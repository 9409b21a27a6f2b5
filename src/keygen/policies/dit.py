"""The DiT noise-prediction network (Peebles & Xie 2023) over an action trajectory.

The T noisy action tokens self-attend, cross-attend to the conditioning tokens (cloud, keypoints,
proprioception) and pass an MLP; every block is modulated by adaLN-Zero from the diffusion-step
embedding plus the proprioception vector. Cross-attention rather than in-context tokens keeps the
per-step cost at T tokens (the conditioning keys / values are computed once per query), which is what
fits a query of 10 DDIM steps in ~25 ms on one CPU core. Output: the predicted noise, (B, T, 10).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from keygen.policies.config import ACTION_DIM, PolicyConfig


def timestep_embedding(t: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
    """Sinusoidal embedding of diffusion steps: (B,) -> (B, dim)."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    args = t.float()[:, None] * freqs[None]  # (B, half)
    return torch.cat([torch.cos(args), torch.sin(args)], dim=-1)


class TimestepEmbedder(nn.Module):
    def __init__(self, width: int):
        super().__init__()
        self.width = width
        self.mlp = nn.Sequential(nn.Linear(width, width), nn.SiLU(), nn.Linear(width, width))

    def forward(self, t: torch.Tensor) -> torch.Tensor:  # (B,) -> (B, W)
        return self.mlp(timestep_embedding(t, self.width))


def _modulate(x: torch.Tensor, shift: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    return x * (1 + scale[:, None]) + shift[:, None]


class DiTBlock(nn.Module):
    """adaLN-Zero block over the action tokens: self-attention, cross-attention to the conditioning
    tokens, MLP. Cross-attention keys / values depend only on the observation, so a query computes
    them once for all its denoising steps (:meth:`DiTNoiseNet.context`)."""

    def __init__(self, width: int, heads: int, mlp_ratio: float):
        super().__init__()
        self.heads = heads
        self.norm1 = nn.LayerNorm(width, elementwise_affine=False, eps=1e-6)
        self.qkv = nn.Linear(width, 3 * width)
        self.out = nn.Linear(width, width)
        self.norm_x = nn.LayerNorm(width, eps=1e-6)
        self.cross_q = nn.Linear(width, width)
        self.cross_kv = nn.Linear(width, 2 * width)
        self.cross_out = nn.Linear(width, width)
        self.norm2 = nn.LayerNorm(width, elementwise_affine=False, eps=1e-6)
        hidden = int(width * mlp_ratio)
        self.mlp = nn.Sequential(
            nn.Linear(width, hidden), nn.GELU(approximate="tanh"), nn.Linear(hidden, width)
        )
        self.ada = nn.Sequential(nn.SiLU(), nn.Linear(width, 6 * width))
        # adaLN-Zero: every block starts as the identity, which stabilises early training.
        nn.init.zeros_(self.ada[1].weight)
        nn.init.zeros_(self.ada[1].bias)
        nn.init.zeros_(self.cross_out.weight)
        nn.init.zeros_(self.cross_out.bias)

    def _heads(self, x: torch.Tensor) -> torch.Tensor:  # (B, L, W) -> (B, heads, L, W / heads)
        b, n, w = x.shape
        return x.reshape(b, n, self.heads, w // self.heads).transpose(1, 2)

    def context(self, tokens: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        k, v = self.cross_kv(tokens).chunk(2, dim=-1)  # each (B, C, W)
        return self._heads(k), self._heads(v)

    def modulations(self, c: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """adaLN shift / scale / gate (x2) from the condition: (..., W) -> 6 x (..., W)."""
        return self.ada(c).chunk(6, dim=-1)

    def forward(
        self, x: torch.Tensor, mods: tuple[torch.Tensor, ...], kv: tuple[torch.Tensor, torch.Tensor]
    ) -> torch.Tensor:
        # x (B, T, W) action tokens, mods 6 x (B, W) from modulations(), kv per-head cross keys / values
        shift1, scale1, gate1, shift2, scale2, gate2 = mods
        b, n, w = x.shape
        h = _modulate(self.norm1(x), shift1, scale1)
        q, k, v = self.qkv(h).reshape(b, n, 3, self.heads, w // self.heads).permute(2, 0, 3, 1, 4)
        attn = F.scaled_dot_product_attention(q, k, v)  # (B, heads, T, W / heads)
        x = x + gate1[:, None] * self.out(attn.transpose(1, 2).reshape(b, n, w))
        cross = F.scaled_dot_product_attention(self._heads(self.cross_q(self.norm_x(x))), *kv)
        x = x + self.cross_out(cross.transpose(1, 2).reshape(b, n, w))
        return x + gate2[:, None] * self.mlp(_modulate(self.norm2(x), shift2, scale2))


class DiTContext:
    """The observation's part of every denoising step: adaLN vector and cross-attention keys / values."""

    def __init__(self, global_c: torch.Tensor, kv: list[tuple[torch.Tensor, torch.Tensor]]):
        self.global_c, self.kv = global_c, kv
        # timestep -> every block's adaLN modulations, filled by DiTNoiseNet.precompute
        self.modulations: dict[int, list[tuple[torch.Tensor, ...]]] = {}


class DiTNoiseNet(nn.Module):
    """eps_theta(a_noisy, cond tokens, c, n) -> predicted noise, (B, T, 10)."""

    def __init__(self, config: PolicyConfig):
        super().__init__()
        w = config.width
        self.action_in = nn.Linear(ACTION_DIM, w)
        self.action_pos = nn.Parameter(torch.randn(config.horizon, w) * 0.02)
        self.t_embed = TimestepEmbedder(w)
        self.blocks = nn.ModuleList(DiTBlock(w, config.heads, config.mlp_ratio) for _ in range(config.depth))
        self.final_norm = nn.LayerNorm(w, elementwise_affine=False, eps=1e-6)
        self.final_ada = nn.Sequential(nn.SiLU(), nn.Linear(w, 2 * w))
        self.action_out = nn.Linear(w, ACTION_DIM)
        for layer in (self.final_ada[1], self.action_out):
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)

    def context(self, cond: tuple[torch.Tensor, torch.Tensor]) -> DiTContext:
        tokens, global_c = cond  # (B, C, W), (B, W)
        return DiTContext(global_c, [block.context(tokens) for block in self.blocks])

    def _modulations(self, c: torch.Tensor) -> list[tuple[torch.Tensor, ...]]:
        # (..., W) -> per block 6 x (..., W), then the final layer's (shift, scale)
        return [block.modulations(c) for block in self.blocks] + [self.final_ada(c).chunk(2, dim=-1)]

    def precompute(self, ctx: DiTContext, timesteps: torch.Tensor) -> None:
        """Cache the adaLN modulations of the sampler's timesteps (S,): they depend only on the step
        and the observation, so a query computes them in a few batched products instead of per step."""
        t_emb = self.t_embed(timesteps)  # (S, W)
        c = t_emb[:, None] + ctx.global_c[None]  # (S, B, W)
        mods = self._modulations(c)
        for i, t in enumerate(timesteps.tolist()):
            ctx.modulations[int(t)] = [tuple(m[i] for m in layer) for layer in mods]

    def forward(
        self,
        noisy: torch.Tensor,
        timestep: torch.Tensor,
        cond: tuple[torch.Tensor, torch.Tensor] | DiTContext,
    ) -> torch.Tensor:
        ctx = cond if isinstance(cond, DiTContext) else self.context(cond)
        mods = ctx.modulations.get(int(timestep)) if timestep.dim() == 0 else None
        if mods is None:
            t = timestep.expand(noisy.shape[0]) if timestep.dim() == 0 else timestep
            mods = self._modulations(self.t_embed(t) + ctx.global_c)  # from c: (B, W)
        x = self.action_in(noisy) + self.action_pos  # (B, T, W)
        for block, layer_mods, kv in zip(self.blocks, mods, ctx.kv, strict=False):
            x = block(x, layer_mods, kv)
        shift, scale = mods[-1]
        return self.action_out(_modulate(self.final_norm(x), shift, scale))  # (B, T, 10)
