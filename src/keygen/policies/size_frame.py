"""Size-normalised frame: run a policy trained on one instance as if an unseen one had its size.

A policy trained on demonstrations of a single instance learns where that instance's parts are in
absolute terms; on a wider or narrower unseen instance it reaches for where the training instance's
part would be (measured on stacking: the gripper closed 4.6-7.8 cm from the rim of the two widest
test bowls, about where the training bowl's rim is). The keypoints measure the object's size, so at
test time the observation can be scaled to the training size and the predicted trajectory scaled
back (paper, Sec. IV: keypoints as *relative* anchors that allow proportional adaptation)::

    s = spread(keypoints of the manipulated object) / spread on the training data
    c = (keypoint centroid x, y; lowest point of the object's cloud z)   the object's footprint
    policy input  p -> c + (p - c) / s     (cloud, keypoints, proprioception positions)
    policy output a -> c + (a - c) * s     (action positions; rotations and gripper untouched)

Scaling about a point on the table keeps the table where it is. The frame is fixed at the episode's
first query (the object still at rest) and kept for the whole episode, so the policy acts in one
consistent, scaled copy of the scene. Beyond the paper; off unless asked for
(``keygen eval --size-normalize``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from keygen.errors import InvalidParameterError
from keygen.policies.data import KEYPOINT_CACHE


def _spreads(kp: np.ndarray) -> np.ndarray:
    """(...,) root-mean-square distance of (..., K, 3) keypoints from their centroid."""
    return np.sqrt(((kp - kp.mean(-2, keepdims=True)) ** 2).sum(-1).mean(-1))


def keypoint_spread(keypoints: np.ndarray) -> float:
    """Root-mean-square distance (m) of (K, 3) keypoints from their centroid."""
    kp = np.asarray(keypoints)
    if kp.ndim != 2 or kp.shape[1] != 3 or len(kp) < 2:
        raise InvalidParameterError(f"keypoints must be (K >= 2, 3), got {kp.shape}")
    return float(_spreads(kp))


def reference_spread(run_dir: str | Path, num_keypoints: int) -> float:
    """Median spread of the manipulated object's keypoints (the first ``num_keypoints`` tokens) over
    every step of the run's training data, read from the run's keypoint cache."""
    path = Path(run_dir) / KEYPOINT_CACHE
    if not path.is_file():
        raise InvalidParameterError(
            f"{path} is missing: the size frame needs the keypoints of the run's training data, which "
            f"`keygen train` caches there (rerun the run's train command to rebuild it)"
        )
    with np.load(path) as cache:
        kp = np.asarray(cache["keypoints"])[:, :num_keypoints]  # (S, K, 3)
    if len(kp) == 0:
        raise InvalidParameterError(f"{path} holds no keypoints")
    return float(np.median(_spreads(kp)))


@dataclass(frozen=True)
class SizeFrame:
    """Uniform scaling by ``1 / scale`` about ``centre``: world -> policy; ``scale`` back."""

    centre: np.ndarray  # (3,) float64, m
    scale: float  # observed size / training size

    @classmethod
    def measure(cls, keypoints: np.ndarray, object_points: np.ndarray, reference: float) -> SizeFrame:
        """The frame of one observation: the manipulated object's (K, 3) keypoints and its points."""
        if not reference > 0.0:
            raise InvalidParameterError(f"reference spread must be > 0, got {reference}")
        pts = np.asarray(object_points)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
            raise InvalidParameterError(f"object points must be (N >= 1, 3), got {pts.shape}")
        kp = np.asarray(keypoints)
        centre = kp.mean(0).astype(np.float64)
        centre[2] = pts[:, 2].min()
        scale = keypoint_spread(kp) / reference
        if not scale > 0.0:
            raise InvalidParameterError(f"the keypoints have no spread ({keypoint_spread(kp)}); cannot scale")
        return cls(centre, scale)

    def to_policy(self, feats: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """A step's features (``cloud``, ``proprio``, optional ``keypoints``) in the scaled copy."""
        c, s = self.centre, self.scale
        out = dict(feats)
        out["cloud"] = (c + (feats["cloud"] - c) / s).astype(np.float32)
        if "keypoints" in feats:
            out["keypoints"] = (c + (feats["keypoints"] - c) / s).astype(np.float32)
        proprio = np.array(feats["proprio"], copy=True)
        proprio[:3] = c + (proprio[:3] - c) / s
        out["proprio"] = proprio.astype(np.float32)
        return out

    def to_world(self, plan: np.ndarray) -> np.ndarray:
        """(T, 10) planned actions back to the world: positions scaled out, the rest untouched."""
        out = np.array(plan, copy=True)
        out[:, :3] = self.centre + (out[:, :3] - self.centre) * self.scale
        return out
