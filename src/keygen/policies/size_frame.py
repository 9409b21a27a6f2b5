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

Per-axis variant (``keygen eval --size-normalize axes``): width and height are measured apart, the
horizontal and the vertical root-mean-square spreads of the keypoints, each against its median over
the first step of every training episode (the object at rest, as at the test's first query)::

    s = (s_xy, s_xy, s_z)   applied per axis in the two maps above

One uniform scale assumes the unseen object has the training object's proportions. Measured on
stacking, a bowl as shallow as the training bowl but 1.25 times as wide (test bowl 6) had its grasp
raised with its width to the rim's top edge, and the bowl slipped out of the fingers on the lift
(3 of 20 in the uniform frame, 19 of 20 in the world frame); the per-axis frame keeps its height.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from keygen.errors import InvalidParameterError
from keygen.policies.data import CACHE_EPISODE_ENDS, KEYPOINT_CACHE

SIZE_MODES = ("uniform", "axes")
# Below a micrometre an axis's spread is rounding noise (keypoints on a plane), not a size.
MIN_AXIS_SPREAD = 1e-6


def _spreads(kp: np.ndarray) -> np.ndarray:
    """(...,) root-mean-square distance of (..., K, 3) keypoints from their centroid."""
    return np.sqrt(((kp - kp.mean(-2, keepdims=True)) ** 2).sum(-1).mean(-1))


def _axis_spreads(kp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(...,) horizontal and vertical root-mean-square distances of (..., K, 3) keypoints from their
    centroid."""
    d = kp - kp.mean(-2, keepdims=True)
    return np.sqrt((d[..., :2] ** 2).sum(-1).mean(-1)), np.sqrt((d[..., 2] ** 2).mean(-1))


def _check_keypoints(kp: np.ndarray) -> np.ndarray:
    kp = np.asarray(kp)
    if kp.ndim != 2 or kp.shape[1] != 3 or len(kp) < 2:
        raise InvalidParameterError(f"keypoints must be (K >= 2, 3), got {kp.shape}")
    return kp


def keypoint_spread(keypoints: np.ndarray) -> float:
    """Root-mean-square distance (m) of (K, 3) keypoints from their centroid."""
    return float(_spreads(_check_keypoints(keypoints)))


def keypoint_axis_spreads(keypoints: np.ndarray) -> tuple[float, float]:
    """Horizontal and vertical root-mean-square distances (m) of (K, 3) keypoints from their centroid."""
    h, v = _axis_spreads(_check_keypoints(keypoints))
    return float(h), float(v)


def _cached_keypoints(run_dir: str | Path, num_keypoints: int) -> np.ndarray:
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
    return kp


def reference_spread(run_dir: str | Path, num_keypoints: int) -> float:
    """Median spread of the manipulated object's keypoints (the first ``num_keypoints`` tokens) over
    every step of the run's training data, read from the run's keypoint cache."""
    return float(np.median(_spreads(_cached_keypoints(run_dir, num_keypoints))))


def cached_episode_ends(run_dir: str | Path) -> np.ndarray | None:
    """The training dataset's episode boundaries as the run's keypoint cache keeps them (None for a
    cache written before it kept them, or no cache)."""
    path = Path(run_dir) / KEYPOINT_CACHE
    if not path.is_file():
        return None
    with np.load(path) as cache:
        if CACHE_EPISODE_ENDS not in cache.files:
            return None
        return np.asarray(cache[CACHE_EPISODE_ENDS], dtype=np.int64)


def rest_axis_references(
    run_dir: str | Path, num_keypoints: int, episode_ends: np.ndarray | None = None
) -> tuple[float, float]:
    """Median horizontal and vertical spreads of the manipulated object's keypoints over the first
    step of every training episode (the object at rest), from the run's keypoint cache; the episodes
    are ``episode_ends`` (cumulative step counts of the run's dataset), by default the boundaries
    the cache keeps."""
    kp = _cached_keypoints(run_dir, num_keypoints)
    if episode_ends is None:
        episode_ends = cached_episode_ends(run_dir)
        if episode_ends is None:
            raise InvalidParameterError(
                f"the keypoint cache of {run_dir} does not keep its dataset's episode boundaries "
                f"(written by an older keygen); pass them from the dataset"
            )
    ends = np.asarray(episode_ends, dtype=np.int64)
    if ends.ndim != 1 or len(ends) == 0 or ends[-1] != len(kp) or np.any(np.diff(ends) <= 0):
        raise InvalidParameterError(
            f"episode ends {ends[:3].tolist()}... (last {ends[-1:].tolist()}) do not split the "
            f"{len(kp)} cached steps of {run_dir}: is this the run's own dataset?"
        )
    starts = np.concatenate([[0], ends[:-1]])
    h, v = _axis_spreads(kp[starts])
    return float(np.median(h)), float(np.median(v))


def _footprint(keypoints: np.ndarray, object_points: np.ndarray) -> np.ndarray:
    """(3,) the point the scene is scaled about: the keypoint centroid's x, y on the lowest point of
    the object's cloud (the table under it), so that scaling keeps the table where it is."""
    pts = np.asarray(object_points)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise InvalidParameterError(f"object points must be (N >= 1, 3), got {pts.shape}")
    centre = np.asarray(keypoints).mean(0).astype(np.float64)
    centre[2] = pts[:, 2].min()
    return centre


@dataclass(frozen=True)
class SizeFrame:
    """Scaling by ``1 / scale`` (one factor, or one per axis) about ``centre``: world -> policy;
    ``scale`` back."""

    centre: np.ndarray  # (3,) float64, m
    scale: float | np.ndarray  # observed size / training size: one for all axes, or (3,) per axis

    @classmethod
    def measure(cls, keypoints: np.ndarray, object_points: np.ndarray, reference: float) -> SizeFrame:
        """The frame of one observation: the manipulated object's (K, 3) keypoints and its points."""
        if not reference > 0.0:
            raise InvalidParameterError(f"reference spread must be > 0, got {reference}")
        kp = np.asarray(keypoints)
        centre = _footprint(kp, object_points)
        scale = keypoint_spread(kp) / reference
        if not scale > 0.0:
            raise InvalidParameterError(f"the keypoints have no spread ({keypoint_spread(kp)}); cannot scale")
        return cls(centre, scale)

    @classmethod
    def measure_axes(
        cls, keypoints: np.ndarray, object_points: np.ndarray, reference: tuple[float, float]
    ) -> SizeFrame:
        """The per-axis frame of one observation: width and height scaled apart, against the training
        object's ``reference`` (horizontal, vertical) spreads at rest."""
        ref_h, ref_v = (float(r) for r in reference)
        if not (ref_h > 0.0 and ref_v > 0.0):
            raise InvalidParameterError(f"reference spreads must be > 0, got {reference}")
        h, v = keypoint_axis_spreads(keypoints)
        if not (h > MIN_AXIS_SPREAD and v > MIN_AXIS_SPREAD):
            raise InvalidParameterError(
                f"the keypoints have no horizontal or no vertical spread ({h}, {v}); cannot scale per axis"
            )
        return cls(_footprint(keypoints, object_points), np.array([h / ref_h, h / ref_h, v / ref_v]))

    def about_xy(self, xy: np.ndarray) -> SizeFrame:
        """The same scale about another horizontal point (the height of the centre, the table, stays)."""
        centre = np.array(self.centre, dtype=np.float64, copy=True)
        centre[:2] = np.asarray(xy, dtype=np.float64)[:2]
        return SizeFrame(centre, self.scale)

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


def size_mode(size_normalize: bool | str | None) -> str | None:
    """The size frame asked for: None (off), ``"uniform"`` (also ``True``) or ``"axes"``."""
    if size_normalize is None or size_normalize is False:
        return None
    if size_normalize is True:
        return "uniform"
    if size_normalize not in SIZE_MODES:
        raise InvalidParameterError(f"size normalisation must be one of {SIZE_MODES}, got {size_normalize!r}")
    return str(size_normalize)
