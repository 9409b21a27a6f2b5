"""Rotations in 3D: the octahedral group, 6D, quaternions (w, x, y, z), axis-angle, sampling.

Conventions (see the design notes):

- Rotation matrices act on column vectors, ``x_world = R @ x_local``; their columns are the
  local axes expressed in the parent frame.
- The 6D representation (Zhou et al., "On the Continuity of Rotation Representations in Neural
  Networks", CVPR 2019) is the first two COLUMNS of the matrix, concatenated:
  ``[R[:, 0], R[:, 1]]``. It is what actions and proprioception carry.
- Quaternions only appear at the MuJoCo boundary; MuJoCo stores them scalar first, so every
  function that reads or writes one says ``wxyz`` in its name. Returned quaternions are unit
  and have ``w >= 0`` (q and -q are the same rotation).
- Axis-angle is the rotation vector ``axis * angle`` (radians), as in scipy's ``as_rotvec``.

Functions accept a single rotation (3, 3) or any batch (..., 3, 3) where that is natural. All
of it is NumPy; a torch version of the 6D conversions belongs to the learning packages.
"""

from __future__ import annotations

import itertools
from functools import cache

import numpy as np

from keygen.errors import InvalidParameterError

__all__ = [
    "axis_angle_to_matrix",
    "is_rotation",
    "matrix_to_axis_angle",
    "matrix_to_quat_wxyz",
    "matrix_to_rot6d",
    "nearest_octahedral",
    "octahedral_group",
    "octahedral_index",
    "octahedral_inverse_indices",
    "octahedral_multiplication_table",
    "quat_wxyz_to_matrix",
    "random_rotation",
    "rot6d_to_matrix",
    "rotation_angle_between",
    "yaw_matrix",
]

# Below this norm a vector has no usable direction (6D columns, quaternions, axes).
_DEGENERATE_NORM = 1e-12


# -- validation ---------------------------------------------------------------------------
def _as_matrices(R: np.ndarray, name: str = "R") -> np.ndarray:
    """``R`` as a float64 array of shape (..., 3, 3) with finite entries, or an error."""
    arr = np.asarray(R, dtype=np.float64)
    if arr.ndim < 2 or arr.shape[-2:] != (3, 3):
        raise InvalidParameterError(
            f"{name} must be a (3, 3) matrix or a (..., 3, 3) batch, got shape {arr.shape}; "
            "pass rotation matrices (not quaternions or 6D vectors)"
        )
    if not np.all(np.isfinite(arr)):
        raise InvalidParameterError(f"{name} contains NaN or inf; check where the rotation came from")
    return arr


def _as_vectors(x: np.ndarray, size: int, name: str) -> np.ndarray:
    """``x`` as a float64 array of shape (..., size) with finite entries, or an error."""
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim < 1 or arr.shape[-1] != size:
        raise InvalidParameterError(
            f"{name} must have shape ({size},) or (..., {size}), got shape {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise InvalidParameterError(f"{name} contains NaN or inf")
    return arr


def is_rotation(R: np.ndarray, atol: float = 1e-6) -> bool | np.ndarray:
    """Whether ``R`` is a proper rotation: orthonormal (R^T R = I) with determinant +1.

    A single (3, 3) matrix gives a bool; a batch (..., 3, 3) gives a boolean array (...).
    Anything that is not shaped (..., 3, 3) or is not finite is simply not a rotation.
    """
    arr = np.asarray(R, dtype=np.float64)
    if arr.ndim < 2 or arr.shape[-2:] != (3, 3):
        return False
    gram = np.swapaxes(arr, -1, -2) @ arr
    finite = np.all(np.isfinite(arr), axis=(-2, -1))
    with np.errstate(invalid="ignore"):
        orthonormal = np.all(np.abs(gram - np.eye(3)) <= atol, axis=(-2, -1))
        proper = np.abs(np.linalg.det(np.where(np.isfinite(arr), arr, 0.0)) - 1.0) <= atol
    result = finite & orthonormal & proper
    return bool(result) if arr.ndim == 2 else result


# -- the octahedral group -----------------------------------------------------------------
@cache
def _octahedral_group() -> np.ndarray:
    elements = []
    # Fixed order: permutations in itertools (lexicographic) order, then sign patterns in
    # itertools.product((1, -1), repeat=3) order, keeping det = +1. Index 0 is the identity.
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            g = np.zeros((3, 3))
            g[np.arange(3), perm] = signs
            if np.linalg.det(g) > 0:
                elements.append(g)
    group = np.stack(elements)
    group.setflags(write=False)
    return group


def octahedral_group() -> np.ndarray:
    """The 24 proper rotations of the cube, shape (24, 3, 3), read-only and cached.

    These are the signed permutation matrices with determinant +1. Order (fixed, part of the
    API because indices are stored): for each permutation ``p`` of (0, 1, 2) in lexicographic
    order, and for each sign pattern ``s`` in ``itertools.product((1, -1), repeat=3)`` order,
    the matrix with ``G[i, p[i]] = s[i]`` is kept when its determinant is +1. Index 0 is the
    identity.
    """
    return _octahedral_group()


def octahedral_index(R: np.ndarray, atol: float = 1e-6) -> int:
    """Index in :func:`octahedral_group` of the rotation ``R`` (3, 3).

    Raises InvalidParameterError when ``R`` is not a group element within ``atol`` (use
    :func:`nearest_octahedral` to snap an arbitrary rotation).
    """
    arr = _as_matrices(R)
    if arr.ndim != 2:
        raise InvalidParameterError(f"octahedral_index takes one (3, 3) matrix, got shape {arr.shape}")
    diffs = np.max(np.abs(_octahedral_group() - arr), axis=(1, 2))
    best = int(np.argmin(diffs))
    if diffs[best] > atol:
        raise InvalidParameterError(
            "R is not one of the 24 cube rotations (signed permutation matrices with det +1): "
            f"closest element differs by {diffs[best]:.3g} > atol={atol}; "
            "use nearest_octahedral(R) to snap it first"
        )
    return best


@cache
def _multiplication_table() -> np.ndarray:
    group = _octahedral_group()
    table = np.empty((24, 24), dtype=np.int64)
    for i in range(24):
        for j in range(24):
            table[i, j] = octahedral_index(group[i] @ group[j])
    table.setflags(write=False)
    return table


def octahedral_multiplication_table() -> np.ndarray:
    """(24, 24) int table with ``table[i, j] = octahedral_index(G[i] @ G[j])``; read-only."""
    return _multiplication_table()


@cache
def _inverse_indices() -> np.ndarray:
    group = _octahedral_group()
    # Rotations are orthogonal, so the inverse is the transpose.
    inv = np.array([octahedral_index(g.T) for g in group], dtype=np.int64)
    inv.setflags(write=False)
    return inv


def octahedral_inverse_indices() -> np.ndarray:
    """(24,) int array: ``G[inv[i]] = G[i]^-1``; read-only."""
    return _inverse_indices()


def nearest_octahedral(R: np.ndarray) -> int | np.ndarray:
    """Index of the cube rotation closest to ``R`` in geodesic angle.

    The angle between R and G_k is ``arccos((tr(G_k^T R) - 1) / 2)``, so the closest element is
    the one with the largest trace; ties (R exactly half-way) go to the lower index. A single
    (3, 3) gives an int, a batch (..., 3, 3) an int array (...).
    """
    arr = _as_matrices(R)
    # tr(G_k^T R) = sum_ij G_k[i, j] R[i, j]
    traces = np.einsum("kij,...ij->...k", _octahedral_group(), arr)
    best = np.argmax(traces, axis=-1)
    return int(best) if arr.ndim == 2 else best


# -- 6D -----------------------------------------------------------------------------------
def matrix_to_rot6d(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 6): the first two columns of R, ``[R[:, 0], R[:, 1]]``."""
    arr = _as_matrices(R)
    return np.concatenate([arr[..., :, 0], arr[..., :, 1]], axis=-1)


def rot6d_to_matrix(x: np.ndarray) -> np.ndarray:
    """(..., 6) -> (..., 3, 3) by Gram-Schmidt on the two 3-vectors (Zhou et al. 2019).

    b1 = a1 / |a1|; b2 = the part of a2 orthogonal to b1, normalised; b3 = b1 x b2; the
    result has columns (b1, b2, b3). Any input whose two halves are non-zero and not parallel
    maps to a proper rotation; degenerate inputs raise InvalidParameterError.
    """
    arr = _as_vectors(x, 6, "rot6d")
    a1, a2 = arr[..., :3], arr[..., 3:]
    n1 = np.linalg.norm(a1, axis=-1, keepdims=True)
    if np.any(n1 < _DEGENERATE_NORM):
        raise InvalidParameterError(
            "6D rotation has a zero first column; expected two non-parallel 3-vectors"
        )
    b1 = a1 / n1
    a2_perp = a2 - np.sum(b1 * a2, axis=-1, keepdims=True) * b1
    n2 = np.linalg.norm(a2_perp, axis=-1, keepdims=True)
    if np.any(n2 < _DEGENERATE_NORM):
        raise InvalidParameterError(
            "6D rotation has a second column that is zero or parallel to the first; "
            "expected two non-parallel 3-vectors"
        )
    b2 = a2_perp / n2
    b3 = np.cross(b1, b2)
    return np.stack([b1, b2, b3], axis=-1)


# -- quaternions (w, x, y, z) -------------------------------------------------------------
def quat_wxyz_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions, scalar first (MuJoCo order), -> (..., 3, 3).

    The quaternion is normalised first, so any non-zero 4-vector is accepted.
    """
    arr = _as_vectors(q, 4, "quaternion (w, x, y, z)")
    norm = np.linalg.norm(arr, axis=-1, keepdims=True)
    if np.any(norm < _DEGENERATE_NORM):
        raise InvalidParameterError("quaternion (w, x, y, z) has zero norm; expected a unit quaternion")
    w, x, y, z = np.moveaxis(arr / norm, -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def matrix_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 4) unit quaternions, scalar first, with ``w >= 0``.

    Shepperd's method: of the four components, the one with the largest magnitude is computed
    from the diagonal and the others are divided by it, so the result stays accurate at every
    angle, including half turns where ``w`` is near 0. Input matrices should be rotations;
    a slightly non-orthonormal one gives the quaternion of a nearby rotation.
    """
    m = _as_matrices(R)
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    # 4 * w^2, 4 * x^2, 4 * y^2, 4 * z^2
    squares = np.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], axis=-1
    )
    # Row k holds 4 * c_k * (w, x, y, z) where c_k is component k (exact for a rotation).
    scaled = np.stack(
        [
            np.stack([squares[..., 0], m21 - m12, m02 - m20, m10 - m01], axis=-1),
            np.stack([m21 - m12, squares[..., 1], m01 + m10, m02 + m20], axis=-1),
            np.stack([m02 - m20, m01 + m10, squares[..., 2], m12 + m21], axis=-1),
            np.stack([m10 - m01, m02 + m20, m12 + m21, squares[..., 3]], axis=-1),
        ],
        axis=-2,
    )
    best = np.argmax(squares, axis=-1)
    # The largest of the four is >= 1 for any rotation (they sum to 4), so no division by ~0.
    q = np.take_along_axis(scaled, best[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


# -- axis-angle ---------------------------------------------------------------------------
def axis_angle_to_matrix(axis: np.ndarray, angle: float | np.ndarray | None = None) -> np.ndarray:
    """Rotation matrices from axis-angle, by Rodrigues' formula.

    Two forms: ``axis_angle_to_matrix(rotvec)`` with ``rotvec`` (..., 3) = unit axis * angle
    (radians; the zero vector is the identity), or ``axis_angle_to_matrix(axis, angle)`` with
    any non-zero ``axis`` (..., 3) (normalised here) and ``angle`` (...) in radians.
    """
    vec = _as_vectors(axis, 3, "axis")
    if angle is None:
        theta = np.linalg.norm(vec, axis=-1)
        # The direction of a zero rotation vector does not matter; avoid 0/0.
        unit = vec / np.where(theta > 0, theta, 1.0)[..., None]
    else:
        norm = np.linalg.norm(vec, axis=-1)
        if np.any(norm < _DEGENERATE_NORM):
            raise InvalidParameterError("rotation axis is the zero vector; pass a non-zero axis")
        theta = np.asarray(angle, dtype=np.float64)
        if not np.all(np.isfinite(theta)):
            raise InvalidParameterError("rotation angle contains NaN or inf")
        unit, theta = np.broadcast_arrays(vec / norm[..., None], theta[..., None])
        theta = theta[..., 0]
    x, y, z = np.moveaxis(unit, -1, 0)
    zero = np.zeros_like(x)
    # K is the cross-product matrix of the unit axis: K v = axis x v.
    K = np.stack(
        [np.stack([zero, -z, y], -1), np.stack([z, zero, -x], -1), np.stack([-y, x, zero], -1)],
        axis=-2,
    )
    s, c = np.sin(theta)[..., None, None], np.cos(theta)[..., None, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def matrix_to_axis_angle(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 3) rotation vectors with angle in [0, pi].

    Goes through the quaternion, which keeps it accurate near 0 and near pi (where the
    trace-based formula loses the axis).
    """
    q = matrix_to_quat_wxyz(R)
    w, v = q[..., 0], q[..., 1:]
    sin_half = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(sin_half, w)
    # rotvec = v * angle / sin(angle / 2); the factor tends to 2 as the angle goes to 0.
    small = sin_half < 1e-8
    factor = np.where(small, 2.0 / np.where(small, w, 1.0), angle / np.where(small, 1.0, sin_half))
    return v * factor[..., None]


# -- distances, sampling, yaw -------------------------------------------------------------
def rotation_angle_between(R1: np.ndarray, R2: np.ndarray) -> float | np.ndarray:
    """Geodesic angle (radians, in [0, pi]) of the relative rotation R1^T R2; batched.

    ``atan2(sin, cos)`` with the sine from the skew part of R1^T R2 and the cosine from its
    trace: accurate at every angle, unlike ``arccos`` of the trace near 0 and pi.
    """
    a, b = _as_matrices(R1, "R1"), _as_matrices(R2, "R2")
    rel = np.swapaxes(a, -1, -2) @ b
    skew = np.stack(
        [rel[..., 2, 1] - rel[..., 1, 2], rel[..., 0, 2] - rel[..., 2, 0], rel[..., 1, 0] - rel[..., 0, 1]],
        axis=-1,
    )
    sin = 0.5 * np.linalg.norm(skew, axis=-1)
    cos = 0.5 * (np.trace(rel, axis1=-2, axis2=-1) - 1.0)
    angle = np.arctan2(sin, cos)
    return float(angle) if np.ndim(angle) == 0 else angle


def random_rotation(
    rng: np.random.Generator | int | None, size: int | tuple[int, ...] | None = None
) -> np.ndarray:
    """Rotations drawn uniformly (Haar measure) on SO(3).

    A normalised 4D Gaussian is a uniform unit quaternion, hence a uniform rotation. ``rng`` is a
    Generator or a seed (pass one: every random draw in keygen is seeded). ``size`` None gives
    one (3, 3) matrix; an int or tuple gives (*size, 3, 3).
    """
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    shape = () if size is None else ((size,) if isinstance(size, (int, np.integer)) else tuple(size))
    q = gen.standard_normal((*shape, 4))
    # A draw this close to zero has probability ~0; resample rather than divide by it.
    norms = np.linalg.norm(q, axis=-1)
    while np.any(norms < 1e-6):
        bad = norms < 1e-6
        q[bad] = gen.standard_normal((int(bad.sum()), 4))
        norms = np.linalg.norm(q, axis=-1)
    return quat_wxyz_to_matrix(q)


def yaw_matrix(theta: float | np.ndarray) -> np.ndarray:
    """Rotation about the world z axis by ``theta`` radians (counter-clockwise seen from +z).

    A scalar gives (3, 3); an array of angles (...) gives (..., 3, 3).
    """
    t = np.asarray(theta, dtype=np.float64)
    if not np.all(np.isfinite(t)):
        raise InvalidParameterError("yaw angle contains NaN or inf")
    c, s = np.cos(t), np.sin(t)
    zero, one = np.zeros_like(t), np.ones_like(t)
    return np.stack(
        [np.stack([c, -s, zero], -1), np.stack([s, c, zero], -1), np.stack([zero, zero, one], -1)],
        axis=-2,
    )
