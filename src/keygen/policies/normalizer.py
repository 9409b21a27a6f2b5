"""The normaliser: fitted on the dataset, stored in the policy's state dict (so in its checkpoint).

- Actions and proprioception (10 = position 3, 6D rotation 6, gripper 1): position and gripper map
  to [-1, 1] by the dataset's min / max; the 6D columns are unit vectors already in [-1, 1] and
  pass unchanged (rescaling them per dimension would distort their geometry).
- Clouds and keypoints: a FIXED affine map from the perception workspace box (centre, half the
  largest side), not a dataset statistic, so a policy sees the same geometry whatever the data and
  unseen object positions do not fall outside a fitted range.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from keygen.errors import InvalidParameterError
from keygen.perception.fusion import FusionConfig

ROT6D = slice(3, 9)
# Dimensions whose range is smaller than this keep their centre and a unit half-range of this size
# (a constant gripper would otherwise divide by zero).
MIN_HALF_RANGE = 1e-3


def workspace_frame(config: FusionConfig | None = None) -> tuple[np.ndarray, float]:
    """Centre (3,) and scale (metres per unit) of the perception workspace box."""
    config = config or FusionConfig()
    lo, hi = np.asarray(config.workspace_lo, float), np.asarray(config.workspace_hi, float)
    return (lo + hi) / 2, float(np.max(hi - lo) / 2)


def _range_stats(values: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    values = np.asarray(values, dtype=np.float64).reshape(-1, values.shape[-1])
    if values.shape[-1] != 10 or len(values) == 0:
        raise InvalidParameterError(f"{name} must be (S, 10) with S >= 1, got {values.shape}")
    if not np.all(np.isfinite(values)):
        raise InvalidParameterError(f"{name} holds NaN or inf; fix the dataset before fitting a normaliser")
    lo, hi = values.min(axis=0), values.max(axis=0)
    centre, half = (lo + hi) / 2, np.maximum((hi - lo) / 2, MIN_HALF_RANGE)
    centre[ROT6D], half[ROT6D] = 0.0, 1.0
    return centre, half


class Normalizer(nn.Module):
    """Affine maps of actions, proprioception and 3D points; all statistics are buffers."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("action_centre", torch.zeros(10))
        self.register_buffer("action_half", torch.ones(10))
        self.register_buffer("proprio_centre", torch.zeros(10))
        self.register_buffer("proprio_half", torch.ones(10))
        centre, scale = workspace_frame()
        self.register_buffer("point_centre", torch.tensor(centre, dtype=torch.float32))
        self.register_buffer("point_scale", torch.tensor(scale, dtype=torch.float32))
        self.register_buffer("fitted", torch.tensor(False))

    @torch.no_grad()
    def fit(self, actions: np.ndarray, proprio: np.ndarray) -> Normalizer:
        """Fit the action and proprioception ranges on every step of the training data."""
        for prefix, values in (("action", actions), ("proprio", proprio)):
            centre, half = _range_stats(values, prefix)
            getattr(self, f"{prefix}_centre").copy_(torch.as_tensor(centre, dtype=torch.float32))
            getattr(self, f"{prefix}_half").copy_(torch.as_tensor(half, dtype=torch.float32))
        self.fitted.fill_(True)
        return self

    def _check(self) -> None:
        if not bool(self.fitted):
            raise InvalidParameterError(
                "the normaliser was never fitted; call fit() on the dataset or load a trained checkpoint"
            )

    def normalize_action(self, x: torch.Tensor) -> torch.Tensor:  # (..., 10)
        self._check()
        return (x - self.action_centre) / self.action_half

    def unnormalize_action(self, x: torch.Tensor) -> torch.Tensor:  # (..., 10)
        self._check()
        return x * self.action_half + self.action_centre

    def normalize_proprio(self, x: torch.Tensor) -> torch.Tensor:  # (..., 10)
        self._check()
        return (x - self.proprio_centre) / self.proprio_half

    def normalize_points(self, x: torch.Tensor) -> torch.Tensor:  # (..., 3)
        return (x - self.point_centre) / self.point_scale

    def normalize_offsets(self, x: torch.Tensor) -> torch.Tensor:  # (..., 3) differences of points
        return x / self.point_scale
