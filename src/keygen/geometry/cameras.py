"""Pinhole cameras: intrinsics, depth back-projection, projection, look-at, OpenGL <-> OpenCV.

Two camera-frame conventions meet here:

- **OpenCV** (used by every function in this module unless its name says otherwise): x right,
  y down, z forward (points in front of the camera have z > 0). Pixel (u, v) = (column, row),
  integer coordinates are pixel centres, so the image spans [-0.5, W - 0.5] x [-0.5, H - 0.5].
  ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` and ``u = fx x / z + cx``, ``v = fy y / z + cy``.
- **OpenGL / MuJoCo**: x right, y up, the camera looks along -z. A MuJoCo camera's world pose
  is ``T_cam2world_gl = make_transform(data.cam_xmat[i].reshape(3, 3), data.cam_xpos[i])``.
  Converting between the two flips the camera's y and z axes: ``T_cv = T_gl @ diag(1, -1, -1, 1)``
  (the same matrix converts back).

Depth images are z-depth in metres (distance along the optical axis, not along the ray), which
is what MuJoCo's depth renderer gives after conversion from its normalised buffer.
"""

from __future__ import annotations

import numpy as np

from keygen.errors import InvalidParameterError
from keygen.geometry.transforms import _check_transform, apply_transform

__all__ = [
    "backproject_depth",
    "camera_points_to_world",
    "fov_from_intrinsics",
    "intrinsics_from_fov",
    "look_at",
    "opencv_to_opengl",
    "opengl_to_opencv",
    "project_points",
]

# Flips the camera's y and z axes: OpenGL (y up, looking along -z) <-> OpenCV (y down, +z).
_GL_CV_FLIP = np.diag([1.0, -1.0, -1.0, 1.0])


def _check_size(width: int, height: int) -> tuple[int, int]:
    if int(width) != width or int(height) != height or width < 1 or height < 1:
        raise InvalidParameterError(
            f"image size must be positive integers, got width={width}, height={height}"
        )
    return int(width), int(height)


def _check_intrinsics(K: np.ndarray) -> np.ndarray:
    arr = np.asarray(K, dtype=np.float64)
    if arr.shape != (3, 3) or not np.all(np.isfinite(arr)):
        raise InvalidParameterError(f"K must be a finite (3, 3) intrinsics matrix, got shape {arr.shape}")
    if arr[0, 0] <= 0 or arr[1, 1] <= 0 or not np.allclose(arr[2], [0.0, 0.0, 1.0]):
        raise InvalidParameterError(
            "K must look like [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, got "
            f"{arr.tolist()}; build it with intrinsics_from_fov"
        )
    return arr


def intrinsics_from_fov(width: int, height: int, fovy_deg: float) -> np.ndarray:
    """Pinhole intrinsics (OpenCV) of a camera with vertical field of view ``fovy_deg`` degrees.

    Matches MuJoCo's ``fovy`` (vertical, in degrees) with square pixels (fx = fy) and the
    principal point at the image centre, ``((W - 1) / 2, (H - 1) / 2)`` in pixel-centre
    coordinates: ``fy = (H / 2) / tan(fovy / 2)``.
    """
    w, h = _check_size(width, height)
    if not 0 < fovy_deg < 180:
        raise InvalidParameterError(f"fovy_deg must be in (0, 180) degrees, got {fovy_deg}")
    f = 0.5 * h / np.tan(np.deg2rad(fovy_deg) / 2.0)
    return np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])


def fov_from_intrinsics(K: np.ndarray, width: int, height: int) -> tuple[float, float]:
    """(horizontal, vertical) fields of view in degrees of ``K`` for an image of this size.

    ``fov = 2 atan((size / 2) / f)``; the inverse of :func:`intrinsics_from_fov` for ``fovy``.
    """
    arr = _check_intrinsics(K)
    w, h = _check_size(width, height)
    fovx = 2.0 * np.degrees(np.arctan(0.5 * w / arr[0, 0]))
    fovy = 2.0 * np.degrees(np.arctan(0.5 * h / arr[1, 1]))
    return float(fovx), float(fovy)


def backproject_depth(
    depth: np.ndarray,
    K: np.ndarray,
    mask: np.ndarray | None = None,
    min_depth: float = 0.0,
    max_depth: float = np.inf,
    return_pixels: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Points (M, 3) in the OpenCV camera frame from a z-depth image (H, W) in metres.

    A pixel is kept when its depth is finite, ``> 0``, within ``[min_depth, max_depth]``, and
    ``mask`` (H, W bool, optional) is true there; 0, inf and NaN mark missing depth. Points come
    in row-major pixel order. With ``return_pixels``, also an (M, 2) int array of the (row, col)
    of each point, so per-pixel data (segmentation, colour) can follow: ``seg[rows, cols]``.
    """
    d = np.asarray(depth, dtype=np.float64)
    if d.ndim != 2:
        raise InvalidParameterError(f"depth must be an (H, W) image, got shape {d.shape}")
    Kc = _check_intrinsics(K)
    if not min_depth <= max_depth:
        raise InvalidParameterError(f"need min_depth <= max_depth, got {min_depth} and {max_depth}")
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(d) & (d > 0) & (d >= min_depth) & (d <= max_depth)
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != d.shape:
            raise InvalidParameterError(f"mask must have the depth image's shape {d.shape}, got {m.shape}")
        valid &= m.astype(bool)
    rows, cols = np.nonzero(valid)
    z = d[rows, cols]
    fx, fy, cx, cy, skew = Kc[0, 0], Kc[1, 1], Kc[0, 2], Kc[1, 2], Kc[0, 1]
    y = (rows - cy) * z / fy
    x = ((cols - cx) * z - skew * y) / fx
    points = np.stack([x, y, z], axis=1)
    if return_pixels:
        return points, np.stack([rows, cols], axis=1).astype(np.int64)
    return points


def project_points(points_cam: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (..., 2) as (u, v) = (column, row) and depths (...) of points (..., 3) in the
    OpenCV camera frame.

    Points at or behind the camera (z <= 0) have no image; their pixels are NaN (their depth is
    still returned, so callers can filter on ``depth > 0``).
    """
    pts = np.asarray(points_cam, dtype=np.float64)
    if pts.ndim < 1 or pts.shape[-1] != 3:
        raise InvalidParameterError(f"points_cam must be (..., 3), got shape {pts.shape}")
    Kc = _check_intrinsics(K)
    z = pts[..., 2]
    safe_z = np.where(z > 0, z, np.nan)
    homog = pts @ Kc.T
    pixels = homog[..., :2] / safe_z[..., None]
    return pixels, z.copy()


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world 4x4 transform (OpenCV convention) of a camera at ``eye`` looking at ``target``.

    The camera's +z points at the target, +x is ``forward x up`` (to the right in the image) and
    +y = z x x points down in the image, so ``up`` appears upward. Raises when ``eye`` equals
    ``target`` or the view direction is parallel to ``up`` (choose another ``up`` then).
    """
    e = np.asarray(eye, dtype=np.float64)
    t = np.asarray(target, dtype=np.float64)
    u = np.asarray(up, dtype=np.float64)
    for name, v in (("eye", e), ("target", t), ("up", u)):
        if v.shape != (3,) or not np.all(np.isfinite(v)):
            raise InvalidParameterError(f"{name} must be a finite (3,) vector, got {v.tolist()}")
    forward = t - e
    dist = np.linalg.norm(forward)
    if dist < 1e-12:
        raise InvalidParameterError(
            f"eye and target coincide at {e.tolist()}; the view direction is undefined"
        )
    z = forward / dist
    x = np.cross(z, u)
    nx = np.linalg.norm(x)
    if nx < 1e-9 * max(np.linalg.norm(u), 1e-300):
        raise InvalidParameterError(
            f"view direction {z.tolist()} is parallel to up={u.tolist()}; pass a different up vector"
        )
    x /= nx
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = e
    return T


def opengl_to_opencv(T_cam2world: np.ndarray) -> np.ndarray:
    """Camera-to-world pose of an OpenGL/MuJoCo camera (y up, looking along -z) -> OpenCV pose.

    Flips the camera's y and z axes: ``T @ diag(1, -1, -1, 1)``; batched over (..., 4, 4).
    """
    return _check_transform(T_cam2world) @ _GL_CV_FLIP


def opencv_to_opengl(T_cam2world: np.ndarray) -> np.ndarray:
    """Camera-to-world pose in OpenCV convention -> OpenGL/MuJoCo convention (the same flip)."""
    return _check_transform(T_cam2world) @ _GL_CV_FLIP


def camera_points_to_world(points_cam: np.ndarray, T_cam2world: np.ndarray) -> np.ndarray:
    """Points (..., 3) in a camera frame -> world frame, with the camera-to-world transform.

    The transform must be in the same convention as the points (OpenCV for back-projected depth;
    convert a MuJoCo camera pose with :func:`opengl_to_opencv` first).
    """
    return apply_transform(T_cam2world, points_cam)
