"""Keypoint metrics on scans with ground truth (definitions in docs/keypoints.md).

All functions are NumPy and take keypoints in the world (observation) frame together with each scan's
true pose; they move them to the object frame ``x = R^T (k - t)`` to compare across scans. Symmetric
shapes are compared modulo their symmetries (the instance's set of cube rotations, plus every yaw for
surfaces of revolution), because no method can tell those frames apart.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from keygen.errors import InvalidParameterError
from keygen.geometry.rotations import octahedral_group, rotation_angle_between
from keygen.keypoints.symmetry import equivalent_labels, rotation_label

__all__ = [
    "anchor_points",
    "canonicalizer_accuracy",
    "coverage",
    "dual_alignment_score",
    "inclusivity",
    "pair_errors",
    "to_object_frame",
]

_GROUP = octahedral_group()
REPEAT_THRESHOLD = 0.05  # of the diameter (the 5 %)


def to_object_frame(points: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(..., 3) world points -> object frame ``R^T (p - t)`` (rows: ``(p - t) @ R``)."""
    return (np.asarray(points, dtype=np.float64) - translation) @ rotation


def _yaw_align(xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    cross = float(np.sum(xb[:, 0] * xa[:, 1] - xb[:, 1] * xa[:, 0]))
    dot = float(np.sum(xb[:, 0] * xa[:, 0] + xb[:, 1] * xa[:, 1]))
    theta = np.arctan2(cross, dot)
    c, s = np.cos(theta), np.sin(theta)
    return xb @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T


def pair_errors(
    xa: np.ndarray, xb: np.ndarray, symmetry: list[int] | None = None, axial: bool = False
) -> np.ndarray:
    """Per-keypoint distances (K,) between index-matched object-frame keypoints of two scans.

    With ``symmetry`` (indices of the instance's shape symmetries) and ``axial``, view b is first
    mapped by the symmetry (and yaw, for surfaces of revolution) that minimises the mean squared error.
    """
    xa, xb = np.asarray(xa, dtype=np.float64), np.asarray(xb, dtype=np.float64)
    if xa.shape != xb.shape or xa.ndim != 2 or xa.shape[1] != 3:
        raise InvalidParameterError(
            f"xa and xb must be matching (K, 3) arrays, got {xa.shape} and {xb.shape}"
        )
    if axial:
        xb = _yaw_align(xa, xb)
    best = None
    for g in symmetry or [0]:
        d = np.linalg.norm(xa - xb @ _GROUP[g].T, axis=1)  # (K,)
        if best is None or np.mean(d**2) < np.mean(best**2):
            best = d
    return best


def canonicalizer_accuracy(
    predicted: np.ndarray, rotations: np.ndarray, equivalence: np.ndarray, tolerance_deg: float = 50.0
) -> dict[str, float]:
    """Raw top-1, set and symmetry-aware accuracy of predicted classes (S,) for true rotations (S, 3, 3).

    ``equivalence`` (S, 24) bool: each scan's equivalent cube rotations ``g`` (object frame).
    - ``canon_acc_top1``: prediction == nearest cube rotation of the true pose;
    - ``canon_acc_set``: prediction is the nearest cube rotation of some equivalent pose ``R g``;
    - ``canon_acc_sym``: the predicted frame is within ``tolerance_deg`` of some equivalent pose: its
      canonicalised cloud is the canonical shape up to a residual no larger than the nearest-element
      label's own (at most 45 degrees of yaw for table poses) plus 5 degrees.
    """
    predicted = np.asarray(predicted, dtype=np.int64)
    top1, in_set, sym = [], [], []
    for c, R, eq in zip(predicted, rotations, equivalence, strict=True):
        members = np.flatnonzero(eq)
        top1.append(c == int(rotation_label(R)))
        in_set.append(c in equivalent_labels(R, members))
        angles = rotation_angle_between(
            np.broadcast_to(_GROUP[c], (len(members), 3, 3)), R[None] @ _GROUP[members]
        )
        sym.append(np.degrees(np.min(angles)) <= tolerance_deg)
    return {
        "canon_acc_top1": float(np.mean(top1)),
        "canon_acc_set": float(np.mean(in_set)),
        "canon_acc_sym": float(np.mean(sym)),
    }


def anchor_points(
    anchors_object: dict[str, np.ndarray],
    symmetry: list[int],
    axial: bool,
    diameter: float,
    tol: float = 0.05,
) -> dict[str, np.ndarray]:
    """The point anchors that mean the same under every symmetry of the shape (object frame).

    An anchor moved by a shape symmetry by more than ``tol * diameter`` (a bowl's rim grasp under yaw)
    names no particular place of the shape and is left out; 3-vectors of kind "direction" are not
    passed in here (callers give points only).
    """
    out = {}
    for name, a in anchors_object.items():
        moved = max(float(np.linalg.norm(_GROUP[g] @ a - a)) for g in symmetry) if symmetry else 0.0
        if axial:
            moved = max(moved, 2.0 * float(np.linalg.norm(a[:2])))
        if moved <= tol * diameter:
            out[name] = np.asarray(a, dtype=np.float64)
    return out


def _nearest(queries: np.ndarray, targets: np.ndarray) -> np.ndarray:
    return np.argmin(np.linalg.norm(queries[:, None] - targets[None], axis=-1), axis=1)


def dual_alignment_score(
    keypoints: list[np.ndarray], anchors: list[dict[str, np.ndarray]], reference: np.ndarray
) -> dict[str, float]:
    """Dual alignment score of keypoints (object frame, one (K, 3) per scan) against GT anchors.

    ``reference`` (S,) bool marks the scans of the reference instances. Forward: each keypoint index
    gets, on the reference scans, its most frequent nearest anchor; on the other scans we count how
    often its nearest anchor is that one. Backward: each anchor gets its most frequent nearest keypoint
    index on the reference scans; we count how often it is the same elsewhere. DAS is the mean of both.
    Only anchors present in every scan are used.
    """
    names = sorted(set.intersection(*(set(a) for a in anchors)))
    if not names:
        raise InvalidParameterError("no point anchor is shared by all scans; DAS needs at least one")
    K = keypoints[0].shape[0]
    near_anchor = np.array(
        [_nearest(kp, np.stack([a[n] for n in names])) for kp, a in zip(keypoints, anchors, strict=True)]
    )
    near_kp = np.array(
        [_nearest(np.stack([a[n] for n in names]), kp) for kp, a in zip(keypoints, anchors, strict=True)]
    )
    ref, other = np.asarray(reference, bool), ~np.asarray(reference, bool)
    if not ref.any() or not other.any():
        raise InvalidParameterError("DAS needs scans both in and outside the reference set")
    ref_anchor = [Counter(near_anchor[ref, k]).most_common(1)[0][0] for k in range(K)]
    ref_kp = [Counter(near_kp[ref, j]).most_common(1)[0][0] for j in range(len(names))]
    forward = float(np.mean(near_anchor[other] == np.array(ref_anchor)[None]))
    backward = float(np.mean(near_kp[other] == np.array(ref_kp)[None]))
    return {"das": 0.5 * (forward + backward), "das_forward": forward, "das_backward": backward}


def coverage(
    keypoints_object: np.ndarray, anchors: dict[str, np.ndarray], diameter: float, radius: float = 0.1
) -> float:
    """Fraction of anchors with a keypoint within ``radius * diameter`` (object frame)."""
    if not anchors:
        return float("nan")
    pts = np.stack(list(anchors.values()))
    d = np.linalg.norm(pts[:, None] - keypoints_object[None], axis=-1).min(axis=1)
    return float(np.mean(d <= radius * diameter))


def volume_ratio(keypoints_object: np.ndarray, cloud_object: np.ndarray) -> float:
    """AABB volume of the keypoints over that of the observed cloud, both in the object frame."""
    vol = lambda x: float(np.prod(x.max(axis=0) - x.min(axis=0)))  # noqa: E731
    return vol(keypoints_object) / max(vol(cloud_object), 1e-12)


def inclusivity(keypoints_object: np.ndarray, surface_tree, diameter: float, radius: float = 0.03) -> float:
    """Fraction of keypoints within ``radius * diameter`` of the object's full surface (a cKDTree)."""
    d = surface_tree.query(keypoints_object)[0]
    return float(np.mean(d <= radius * diameter))
