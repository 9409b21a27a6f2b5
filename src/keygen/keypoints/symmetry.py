"""Symmetries of objects and of partial scans over the 24 cube rotations, and rotation labels.

Two kinds of equivalence, both expressed as sets of indices into
:func:`keygen.geometry.rotations.octahedral_group`:

- :func:`instance_symmetry_set`: the rotations ``g`` of the canonical frame that leave the whole
  shape unchanged (``g S = S`` up to a tolerance): a bowl's four 90-degree yaws, maybe a knife's
  turn-over. Computed from a dense surface sample of the canonical mesh with a Chamfer test.
- :func:`scan_equivalence_set`: the rotations ``g`` under which the *visible* part of a scan still
  lies on the shape (``x_vis`` inside ``g S``): these add view-dependent symmetries, such as a mug
  whose handle is hidden (its visible body fits every yaw). A partial cloud cannot tell these apart,
  so they are the target set of the canonicaliser and the basis of the symmetry-aware accuracy.

Labels: the class of a rotation ``R`` (canonical -> observation) is the nearest group element by
geodesic angle (:func:`keygen.geometry.rotations.nearest_octahedral`); table poses leave a residual
yaw of up to 45 degrees between the two.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from keygen.errors import InvalidParameterError
from keygen.geometry.rotations import nearest_octahedral, octahedral_group

__all__ = [
    "SymmetryReference",
    "equivalent_labels",
    "instance_symmetry_set",
    "is_axial",
    "rotation_label",
    "scan_equivalence_set",
    "surface_sample",
    "yaw_indices",
]

# Tolerances relative to the object's diameter; chosen on the generated categories (docs/keypoints.md).
SHAPE_DISTANCE = 0.03  # a shape symmetry moves the surface onto itself within this distance ...
SHAPE_FRACTION = 0.99  # ... for this fraction of the surface (a mean would miss a mug's small handle)
INLIER_DISTANCE = 0.03  # a visible point "lies on" the shape within this distance
INLIER_FRACTION = 0.97  # ... and this fraction of the visible points must


@cache
def yaw_indices() -> tuple[int, ...]:
    """Group indices of the four rotations about +z (0, 90, 180, 270 degrees), identity first."""
    group = octahedral_group()
    out = []
    for angle in (0.0, 0.5 * np.pi, np.pi, 1.5 * np.pi):
        c, s = round(np.cos(angle)), round(np.sin(angle))
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        out.append(int(np.argmin(np.abs(group - R).max(axis=(1, 2)))))
    return tuple(out)


def surface_sample(mesh: trimesh.Trimesh, count: int = 8000, seed: int = 0) -> np.ndarray:
    """``count`` points (count, 3) spread evenly over the mesh surface, deterministic for a seed."""
    if count < 1:
        raise InvalidParameterError(f"count must be >= 1, got {count}")
    points, _ = trimesh.sample.sample_surface_even(mesh, count, seed=seed)
    if len(points) < count:  # rejection can return a few less; top up with plain area sampling
        extra, _ = trimesh.sample.sample_surface(mesh, count - len(points), seed=seed + 1)
        points = np.concatenate([points, extra])
    return np.asarray(points, dtype=np.float64)


def rotation_label(R: np.ndarray) -> np.ndarray | int:
    """Class of a rotation (3, 3) or a batch (..., 3, 3): the nearest cube rotation's index."""
    return nearest_octahedral(np.asarray(R, dtype=np.float64))


def instance_symmetry_set(
    surface: np.ndarray, diameter: float, distance: float = SHAPE_DISTANCE, fraction: float = SHAPE_FRACTION
) -> list[int]:
    """Indices ``g`` that map the canonical shape onto itself (identity included).

    ``surface`` (M, 3): a dense surface sample of the canonical mesh (:func:`surface_sample`). ``g`` is
    a symmetry when at least ``fraction`` of ``g S`` lies within ``distance * diameter`` of ``S``
    (the sample is symmetric in law, so one direction suffices). A robust fraction rather than a
    mean Chamfer distance: a mug's handle is ~10 % of its surface and must not average away.
    Rotations act about the canonical origin, which lies on the symmetry axes of the categories here.
    """
    reference = SymmetryReference(surface, diameter)
    return [
        index
        for index, g in enumerate(octahedral_group())
        if index == 0 or reference.inlier_fraction(reference.surface @ g.T, distance) >= fraction
    ]


def is_axial(symmetry_set: list[int] | tuple[int, ...]) -> bool:
    """True for shapes with all four yaws as symmetries: treated as symmetric under EVERY yaw.

    The generated bowls are surfaces of revolution; a shape that is 4-fold symmetric about z here is
    one of them, and its keypoints can only be compared up to a rotation about the axis.
    """
    return set(yaw_indices()) <= set(symmetry_set)


class SymmetryReference:
    """A canonical surface sample with a KD-tree, to test where a visible cloud lies on the shape."""

    def __init__(self, surface: np.ndarray, diameter: float) -> None:
        self.surface = _check_cloud(surface, "surface")
        self.diameter = _check_positive(diameter, "diameter")
        self.tree = cKDTree(self.surface)

    def inlier_fraction(self, points_object: np.ndarray, distance: float = INLIER_DISTANCE) -> float:
        """Fraction of points (object frame, (N, 3)) within ``distance * diameter`` of the surface."""
        limit = distance * self.diameter
        # The bound lets the KD-tree stop early: only "within the limit or not" matters here.
        d = self.tree.query(np.asarray(points_object, dtype=np.float64), distance_upper_bound=limit)[0]
        return float(np.mean(d < limit))


def scan_equivalence_set(
    points: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    reference: SymmetryReference,
    distance: float = INLIER_DISTANCE,
    fraction: float = INLIER_FRACTION,
) -> list[int]:
    """Indices ``g`` for which the visible cloud, turned by ``g^-1`` in the object frame, lies on the shape.

    ``points`` (N, 3) world frame; ``rotation``/``translation`` the true canonical -> world pose.
    ``g`` is in the set when at least ``fraction`` of ``g^T x_vis`` lies within ``distance * diameter``
    of the canonical surface, ``x_vis = R^T (p - t)``; the identity always is (the scan is the shape).
    Then the pose ``R g`` explains the scan as well as ``R`` does.
    """
    x = (np.asarray(points, dtype=np.float64) - translation) @ rotation  # (N, 3) object frame: R^T (p - t)
    out = [0]
    for index, g in enumerate(octahedral_group()):
        if index == 0:
            continue
        if reference.inlier_fraction(x @ g, distance) >= fraction:  # rows: g^T x
            out.append(index)
    return out


def equivalent_labels(rotation: np.ndarray, equivalence: list[int] | tuple[int, ...]) -> list[int]:
    """Classes of ``R g`` for ``g`` in an equivalence set: every label a correct canonicaliser may give."""
    group = octahedral_group()
    labels = rotation_label(np.asarray(rotation)[None] @ group[list(equivalence)])  # (E,)
    return sorted({int(v) for v in np.atleast_1d(labels)})


def _check_cloud(points: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3 or len(arr) == 0:
        raise InvalidParameterError(f"{name} must be a non-empty (N, 3) array, got shape {arr.shape}")
    return arr


def _check_positive(value: float, name: str) -> float:
    if not np.isfinite(value) or value <= 0:
        raise InvalidParameterError(f"{name} must be a positive length (metres), got {value}")
    return float(value)
