"""The conditional 1-D temporal UNet of Diffusion Policy / DP3, with FiLM conditioning.

Each residual block convolves over time and is modulated per channel (scale and bias) by the
global condition: the diffusion-step embedding concatenated with the observation feature. The
horizon is halved once per level but the last, and restored on the way up with skip connections.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from keygen.policies.config import ACTION_DIM, PolicyConfig
from keygen.policies.dit import timestep_embedding


class Conv1d(nn.Conv1d):
    """nn.Conv1d (same weights and state dict) computed as unfold + one matrix product.

    PyTorch's CPU convolution falls back to a slow im2col path for short sequences with many
    channels (the UNet's deep levels: 256 channels x 4 steps); one GEMM is ~4x faster there.
    Stride 1, odd kernel, 'same' zero padding only; other convolutions use nn.Conv1d directly.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # (B, Cin, T) -> (B, Cout, T)
        k = self.kernel_size[0]
        b, c, t = x.shape
        cols = F.pad(x, (k // 2, k // 2)).unfold(2, k, 1)  # (B, Cin, T, k)
        cols = cols.permute(0, 2, 1, 3).reshape(b, t, c * k)  # (B, T, Cin * k)
        out = cols @ self.weight.reshape(self.out_channels, c * k).T  # (B, T, Cout)
        if self.bias is not None:
            out = out + self.bias
        return out.transpose(1, 2)


class Conv1dBlock(nn.Module):
    def __init__(self, cin: int, cout: int, kernel: int, groups: int):
        super().__init__()
        self.block = nn.Sequential(
            Conv1d(cin, cout, kernel, padding=kernel // 2), nn.GroupNorm(groups, cout), nn.Mish()
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # (B, Cin, T) -> (B, Cout, T)
        return self.block(x)


class FiLMResBlock(nn.Module):
    def __init__(self, cin: int, cout: int, cond_dim: int, kernel: int, groups: int):
        super().__init__()
        self.conv1 = Conv1dBlock(cin, cout, kernel, groups)
        self.conv2 = Conv1dBlock(cout, cout, kernel, groups)
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * cout))
        self.skip = nn.Conv1d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:  # (B, Cin, T), (B, D)
        scale, bias = self.film(cond).unsqueeze(-1).chunk(2, dim=1)  # each (B, Cout, 1)
        h = self.conv1(x) * scale + bias
        return self.conv2(h) + self.skip(x)


class ConditionalUnet1D(nn.Module):
    """eps_theta(a_noisy (B, T, 10), n, global cond (B, G)) -> predicted noise (B, T, 10)."""

    def __init__(self, config: PolicyConfig, global_cond_dim: int, step_dim: int = 128):
        super().__init__()
        k, g = config.unet_kernel, config.unet_groups
        self.step_dim = step_dim
        self.step_mlp = nn.Sequential(
            nn.Linear(step_dim, 4 * step_dim), nn.Mish(), nn.Linear(4 * step_dim, step_dim)
        )
        cond_dim = step_dim + global_cond_dim
        dims = [ACTION_DIM, *config.unet_channels]
        pairs = list(zip(dims[:-1], dims[1:], strict=True))
        self.down = nn.ModuleList()
        for i, (cin, cout) in enumerate(pairs):
            last = i == len(pairs) - 1
            self.down.append(
                nn.ModuleList(
                    [
                        FiLMResBlock(cin, cout, cond_dim, k, g),
                        FiLMResBlock(cout, cout, cond_dim, k, g),
                        nn.Identity() if last else nn.Conv1d(cout, cout, 3, stride=2, padding=1),
                    ]
                )
            )
        mid = dims[-1]
        self.mid = nn.ModuleList(
            [FiLMResBlock(mid, mid, cond_dim, k, g), FiLMResBlock(mid, mid, cond_dim, k, g)]
        )
        self.up = nn.ModuleList()
        for cin, cout in reversed(pairs[1:]):
            self.up.append(
                nn.ModuleList(
                    [
                        FiLMResBlock(2 * cout, cin, cond_dim, k, g),
                        FiLMResBlock(cin, cin, cond_dim, k, g),
                        nn.ConvTranspose1d(cin, cin, 4, stride=2, padding=1),
                    ]
                )
            )
        start = config.unet_channels[0]
        self.final = nn.Sequential(Conv1dBlock(start, start, k, g), nn.Conv1d(start, ACTION_DIM, 1))

    def forward(self, noisy: torch.Tensor, timestep: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        t = timestep.expand(noisy.shape[0]) if timestep.dim() == 0 else timestep
        c = torch.cat([self.step_mlp(timestep_embedding(t, self.step_dim)), cond], dim=-1)  # (B, D)
        x = noisy.transpose(1, 2)  # (B, 10, T)
        skips = []
        for res1, res2, down in self.down:
            x = res2(res1(x, c), c)
            skips.append(x)
            x = down(x)
        for res in self.mid:
            x = res(x, c)
        for res1, res2, up in self.up:
            # The skip of the deepest level was never downsampled; pop pairs it with its input.
            x = torch.cat([x, skips.pop()], dim=1)
            x = up(res2(res1(x, c), c))
        return self.final(x).transpose(1, 2)  # (B, T, 10)
