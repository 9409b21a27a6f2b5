"""Rigid transforms as 4x4 homogeneous matrices, and a small :class:`RigidTransform` value type.

A transform ``T_a2b`` maps coordinates in frame a to frame b: ``x_b = R @ x_a + t`` with
``T = [[R, t], [0, 0, 0, 1]]``. Composition reads right to left like matrix products:
``compose(T_b2c, T_a2b) = T_a2c``. Functions take a single (4, 4) or a batch (..., 4, 4).

Poses at the MuJoCo boundary are (position, quaternion w x y z), MuJoCo's own order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from keygen.errors import InvalidParameterError
from keygen.geometry.rotations import is_rotation, matrix_to_quat_wxyz, quat_wxyz_to_matrix

__all__ = [
    "RigidTransform",
    "apply_transform",
    "compose",
    "invert_transform",
    "make_transform",
    "pose_to_transform",
    "transform_directions",
    "transform_to_pose",
]

# Rotations coming from simulators and file formats drift a little from orthonormality.
_ROTATION_ATOL = 1e-5
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])


def _check_rotation(R: np.ndarray, atol: float) -> np.ndarray:
    arr = np.asarray(R, dtype=np.float64)
    if arr.ndim < 2 or arr.shape[-2:] != (3, 3):
        raise InvalidParameterError(f"rotation must have shape (3, 3) or (..., 3, 3), got {arr.shape}")
    if not np.all(is_rotation(arr, atol=atol)):
        raise InvalidParameterError(
            f"rotation is not a proper rotation matrix (orthonormal, det +1) within atol={atol}; "
            "orthonormalise it first (e.g. rot6d_to_matrix(matrix_to_rot6d(R)))"
        )
    return arr


def _check_vectors(v: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(v, dtype=np.float64)
    if arr.ndim < 1 or arr.shape[-1] != 3:
        raise InvalidParameterError(f"{name} must have shape (3,) or (..., 3), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InvalidParameterError(f"{name} contains NaN or inf")
    return arr


def _check_transform(T: np.ndarray, atol: float = _ROTATION_ATOL) -> np.ndarray:
    """``T`` as float64 (..., 4, 4) with a rotation block and a (0, 0, 0, 1) last row, or an error."""
    arr = np.asarray(T, dtype=np.float64)
    if arr.ndim < 2 or arr.shape[-2:] != (4, 4):
        raise InvalidParameterError(
            f"transform must have shape (4, 4) or (..., 4, 4), got {arr.shape}; "
            "build one with make_transform(R, t)"
        )
    if not np.all(np.isfinite(arr)):
        raise InvalidParameterError("transform contains NaN or inf")
    if not np.allclose(arr[..., 3, :], _LAST_ROW, atol=atol):
        raise InvalidParameterError(
            f"transform's last row must be (0, 0, 0, 1), got {arr[..., 3, :].reshape(-1, 4)[0].tolist()}"
        )
    _check_rotation(arr[..., :3, :3], atol)
    return arr


def make_transform(R: np.ndarray | None = None, t: np.ndarray | None = None) -> np.ndarray:
    """The 4x4 transform ``x -> R x + t``; batched over matching leading dims (broadcast).

    Omitted parts default to the identity rotation / zero translation.
    """
    rot = np.eye(3) if R is None else _check_rotation(R, _ROTATION_ATOL)
    trans = np.zeros(3) if t is None else _check_vectors(t, "translation")
    batch = np.broadcast_shapes(rot.shape[:-2], trans.shape[:-1])
    T = np.zeros((*batch, 4, 4))
    T[..., :3, :3] = rot
    T[..., :3, 3] = trans
    T[..., 3, 3] = 1.0
    return T


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms: ``[R^T, -R^T t]`` (exact, no general matrix inverse)."""
    arr = _check_transform(T)
    rot_t = np.swapaxes(arr[..., :3, :3], -1, -2)
    out = np.zeros_like(arr)
    out[..., :3, :3] = rot_t
    out[..., :3, 3] = -(rot_t @ arr[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def compose(*Ts: np.ndarray) -> np.ndarray:
    """``Ts[0] @ Ts[1] @ ... @ Ts[-1]``: apply the last one first, like matrix products."""
    if not Ts:
        raise InvalidParameterError("compose needs at least one transform, got none")
    result = _check_transform(Ts[0])
    for T in Ts[1:]:
        result = result @ _check_transform(T)
    return result


def apply_transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points mapped by ``T``: ``R p + t``.

    With one transform (4, 4), ``points`` may be any (..., 3). With a batch (B..., 4, 4),
    ``points`` is (B..., N, 3) (leading dims broadcast) and each batch entry is moved by its
    own transform.
    """
    arr = _check_transform(T)
    pts = _check_vectors(points, "points")
    return _rotate(arr, pts) + _translation(arr, pts)


def transform_directions(T: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Directions (free vectors, e.g. normals of a rigid motion) mapped by ``T``: rotation only."""
    arr = _check_transform(T)
    return _rotate(arr, _check_vectors(dirs, "directions"))


def _rotate(T: np.ndarray, v: np.ndarray) -> np.ndarray:
    R = T[..., :3, :3]
    if T.ndim == 2:
        return v @ R.T
    if v.ndim < 2:
        raise InvalidParameterError(
            f"a batch of transforms {T.shape} needs points shaped (..., N, 3), got {v.shape}"
        )
    return v @ np.swapaxes(R, -1, -2)


def _translation(T: np.ndarray, v: np.ndarray) -> np.ndarray:
    t = T[..., :3, 3]
    return t if T.ndim == 2 else t[..., None, :]


def pose_to_transform(pos: np.ndarray, quat_wxyz: np.ndarray) -> np.ndarray:
    """(position (..., 3), quaternion w x y z (..., 4)) -> (..., 4, 4); the quaternion is normalised."""
    return make_transform(quat_wxyz_to_matrix(quat_wxyz), _check_vectors(pos, "position"))


def transform_to_pose(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 4, 4) -> (position (..., 3), unit quaternion w x y z with w >= 0 (..., 4))."""
    arr = _check_transform(T)
    return arr[..., :3, 3].copy(), matrix_to_quat_wxyz(arr[..., :3, :3])


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=np.float64)  # a private copy, so nobody else can mutate it
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class RigidTransform:
    """One rigid transform ``x -> rotation @ x + translation`` (immutable).

    ``A @ B`` is "B then A", like matrices. Equality is identity-based (arrays have no single
    truth value); compare with :meth:`allclose`.
    """

    rotation: np.ndarray
    translation: np.ndarray

    # Makes numpy defer to us, so ``transform @ array`` is a TypeError rather than an
    # object-array broadcast (use .apply for points, .as_matrix() for matrix algebra).
    __array_ufunc__ = None

    def __post_init__(self) -> None:
        rot = _check_rotation(self.rotation, _ROTATION_ATOL)
        trans = _check_vectors(self.translation, "translation")
        if rot.shape != (3, 3) or trans.shape != (3,):
            raise InvalidParameterError(
                f"RigidTransform holds one transform: rotation (3, 3) and translation (3,), got "
                f"{rot.shape} and {trans.shape}; use the array functions for batches"
            )
        object.__setattr__(self, "rotation", _frozen(rot))
        object.__setattr__(self, "translation", _frozen(trans))

    @classmethod
    def identity(cls) -> RigidTransform:
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, T: np.ndarray) -> RigidTransform:
        arr = _check_transform(T)
        if arr.shape != (4, 4):
            raise InvalidParameterError(f"from_matrix takes one (4, 4) transform, got {arr.shape}")
        return cls(arr[:3, :3], arr[:3, 3])

    @classmethod
    def from_pose(cls, pos: np.ndarray, quat_wxyz: np.ndarray) -> RigidTransform:
        return cls.from_matrix(pose_to_transform(pos, quat_wxyz))

    def as_matrix(self) -> np.ndarray:
        return make_transform(self.rotation, self.translation)

    def as_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(position (3,), quaternion w x y z (4,))."""
        return self.translation.copy(), matrix_to_quat_wxyz(self.rotation)

    def inverse(self) -> RigidTransform:
        rot_t = self.rotation.T
        return RigidTransform(rot_t, -rot_t @ self.translation)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Points (..., 3) mapped by the transform."""
        return _check_vectors(points, "points") @ self.rotation.T + self.translation

    def apply_directions(self, dirs: np.ndarray) -> np.ndarray:
        """Directions (..., 3) rotated (no translation)."""
        return _check_vectors(dirs, "directions") @ self.rotation.T

    def __matmul__(self, other: RigidTransform) -> RigidTransform:
        if not isinstance(other, RigidTransform):
            return NotImplemented
        return RigidTransform(
            self.rotation @ other.rotation, self.rotation @ other.translation + self.translation
        )

    def allclose(self, other: RigidTransform, atol: float = 1e-9) -> bool:
        return bool(
            np.allclose(self.rotation, other.rotation, atol=atol)
            and np.allclose(self.translation, other.translation, atol=atol)
        )

    def __repr__(self) -> str:
        return f"RigidTransform(rotation={self.rotation.tolist()}, translation={self.translation.tolist()})"
