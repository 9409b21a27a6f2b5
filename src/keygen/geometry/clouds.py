"""Point-cloud utilities: cropping, voxel and farthest-point sampling, distances, normalisation.

A cloud is an (N, 3) float array in metres. Functions that select points can also return the
selected row indices (``return_index=True``) so per-point attributes (object ids, normals,
colours) can follow with ``attr[index]``. Floating inputs keep their dtype; integer inputs are
converted to float64. Every random choice takes a seed or Generator.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from keygen.errors import InvalidParameterError

try:  # fpsample is a declared dependency; the fallback only keeps the module importable without it.
    import fpsample
except ImportError:  # pragma: no cover - exercised by monkeypatching in the tests
    fpsample = None

# Selected points, or (points, row indices) when return_index is set.
Selection = np.ndarray | tuple[np.ndarray, np.ndarray]

__all__ = [
    "chamfer_distance",
    "crop_box",
    "farthest_point_sample",
    "nearest_distances",
    "normalize_cloud",
    "random_subset",
    "voxel_downsample",
]


def _as_cloud(points: np.ndarray, name: str = "points", allow_empty: bool = False) -> np.ndarray:
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidParameterError(f"{name} must be an (N, 3) array, got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.floating):
        if not np.issubdtype(arr.dtype, np.number):
            raise InvalidParameterError(f"{name} must hold numbers, got dtype {arr.dtype}")
        arr = arr.astype(np.float64)
    if len(arr) == 0 and not allow_empty:
        raise InvalidParameterError(
            f"{name} is empty (0 points); check the crop or the depth mask that produced it"
        )
    if not np.all(np.isfinite(arr)):
        raise InvalidParameterError(
            f"{name} contains NaN or inf; drop invalid points first (e.g. backproject_depth skips them)"
        )
    return arr


def _select(points: np.ndarray, index: np.ndarray, return_index: bool) -> Selection:
    index = np.asarray(index, dtype=np.int64)
    return (points[index], index) if return_index else points[index]


def _as_generator(rng: np.random.Generator | int | None) -> np.random.Generator:
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)


# -- selection ----------------------------------------------------------------------------
def crop_box(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, return_index: bool = False) -> Selection:
    """Points inside the axis-aligned box ``lo <= p <= hi`` (bounds inclusive), in input order.

    A filter: an empty cloud, or a box holding no points, gives an empty (0, 3) result.
    """
    pts = _as_cloud(points, allow_empty=True)
    lo_arr, hi_arr = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    if lo_arr.shape != (3,) or hi_arr.shape != (3,):
        raise InvalidParameterError(f"box bounds must be (3,) each, got lo {lo_arr.shape}, hi {hi_arr.shape}")
    if np.any(np.isnan(lo_arr)) or np.any(np.isnan(hi_arr)) or np.any(lo_arr > hi_arr):
        raise InvalidParameterError(
            f"box needs lo <= hi on every axis, got lo={lo_arr.tolist()}, hi={hi_arr.tolist()}"
        )
    # Column by column: five times faster than np.all over an (N, 3) boolean array.
    inside = (pts[:, 0] >= lo_arr[0]) & (pts[:, 0] <= hi_arr[0])
    for k in (1, 2):
        inside &= pts[:, k] >= lo_arr[k]
        inside &= pts[:, k] <= hi_arr[k]
    return _select(pts, np.flatnonzero(inside), return_index)


def voxel_downsample(points: np.ndarray, voxel_size: float, return_index: bool = False) -> Selection:
    """One representative point per occupied voxel of a grid of cubes of side ``voxel_size``.

    The grid is anchored at the world origin (voxel keys ``floor(p / voxel_size)``), so the same
    region of space falls in the same voxels whatever else the cloud holds. The representative
    is the input point nearest the centroid of its voxel's points (an actual input point, so
    indices and per-point attributes stay valid; exact ties go to the lower index). The output
    keeps input order (indices ascending). Vectorised: one stable sort of packed keys.
    """
    pts = _as_cloud(points)
    size = float(voxel_size)
    if not np.isfinite(size) or size <= 0:
        raise InvalidParameterError(f"voxel_size must be a positive length in metres, got {voxel_size}")
    pts64 = pts.astype(np.float64, copy=False)
    keys = np.floor(pts64 / size).astype(np.int64)
    keys -= keys.min(axis=0)
    dims = keys.max(axis=0) + 1
    if float(np.prod(dims.astype(np.float64))) >= 2.0**62:
        # A huge extent relative to the voxel size: number the voxels by a row-wise unique.
        _, packed = np.unique(keys, axis=0, return_inverse=True)
        packed = packed.reshape(-1)
    else:  # pack the three integer keys into one int64: a 1D sort is much faster
        packed = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
    # One stable sort groups each voxel's points, in input order within the voxel.
    order = np.argsort(packed, kind="stable")
    sorted_keys = packed[order]
    new_voxel = np.empty(len(order), dtype=bool)
    new_voxel[0] = True
    np.not_equal(sorted_keys[1:], sorted_keys[:-1], out=new_voxel[1:])
    starts = np.flatnonzero(new_voxel)
    voxel = np.cumsum(new_voxel) - 1  # voxel number of each sorted point
    sorted_pts = pts64[order]
    counts = np.diff(np.append(starts, len(order))).astype(np.float64)
    centroids = np.add.reduceat(sorted_pts, starts, axis=0) / counts[:, None]
    dist2 = np.sum((sorted_pts - centroids[voxel]) ** 2, axis=1)
    # The representative: the first point (lowest index, as the sort is stable) at its voxel's
    # smallest distance to the centroid.
    nearest = np.flatnonzero(dist2 == np.minimum.reduceat(dist2, starts)[voxel])
    first = np.ones(len(nearest), dtype=bool)
    first[1:] = voxel[nearest[1:]] != voxel[nearest[:-1]]
    return _select(pts, np.sort(order[nearest[first]]), return_index)


def _fps_numpy(points: np.ndarray, n: int, start: int) -> np.ndarray:
    """Plain farthest-point sampling, O(N n); used only when fpsample is unavailable."""
    pts = points.astype(np.float64, copy=False)
    chosen = np.empty(n, dtype=np.int64)
    chosen[0] = start
    dist2 = np.sum((pts - pts[start]) ** 2, axis=1)
    for i in range(1, n):
        chosen[i] = int(np.argmax(dist2))
        dist2 = np.minimum(dist2, np.sum((pts - pts[chosen[i]]) ** 2, axis=1))
    return chosen


def _fps_library(points: np.ndarray, n: int, start: int, method: str) -> np.ndarray:
    n_pts = len(points)
    # start_idx must be a Python int: fpsample draws from numpy's global RNG when it is None.
    if method == "fast" and n < n_pts and n_pts >= 64:
        # QuickFPS with KD-line buckets. The tree height follows the library's advice (3 small,
        # 5-7 medium, 9 large) and must satisfy 2**h <= n_pts.
        h = 3 if n_pts < 2_000 else 5 if n_pts < 20_000 else 7 if n_pts < 200_000 else 9
        idx = fpsample.bucket_fps_kdline_sampling(points, n, h, start_idx=int(start))
    else:
        idx = fpsample.fps_sampling(points, n, start_idx=int(start))
    return np.asarray(idx, dtype=np.int64)


def farthest_point_sample(
    points: np.ndarray,
    n: int,
    start_index: int | None = None,
    seed: np.random.Generator | int | None = None,
    return_index: bool = False,
    method: Literal["exact", "fast"] = "exact",
) -> Selection:
    """``n`` points spread by farthest-point sampling; always exactly ``n`` rows.

    ``method="exact"`` (default) is greedy FPS: the first point is ``start_index`` (default 0),
    or drawn from ``seed`` when that is given instead (giving both is an error); each next point
    is the one farthest from those already chosen, and the output is in that greedy order.
    ``method="fast"`` uses fpsample's bucketed QuickFPS (KD-line tree): about 15x faster on 100k
    points with a slightly less even spread (covering radius ~1-2 % larger in tests). It is
    deterministic for a given start, but fpsample (1.0.2) applies the start index after its own
    tree reordering, so the start point is not necessarily included and the order is not the
    greedy order. Both run in fpsample with float32 distances (near-ties may resolve unlike a
    float64 implementation); a pure-NumPy exact loop is used only if fpsample is missing.

    Padding: when the cloud has fewer than ``n`` points, every point is taken once in exact FPS
    order and the sequence is repeated cyclically (row ``k`` is ``order[k % N]``), so outputs
    have a fixed size and the result is deterministic.
    """
    pts = _as_cloud(points)
    n = int(n)
    if n < 1:
        raise InvalidParameterError(f"number of samples n must be >= 1, got {n}")
    if method not in ("exact", "fast"):
        raise InvalidParameterError(f"method must be 'exact' or 'fast', got {method!r}")
    n_pts = len(pts)
    if start_index is not None and seed is not None:
        raise InvalidParameterError("give either start_index or seed for the first FPS point, not both")
    if seed is not None:
        start = int(_as_generator(seed).integers(n_pts))
    else:
        start = 0 if start_index is None else int(start_index)
    if not 0 <= start < n_pts:
        raise InvalidParameterError(f"start_index must be in [0, {n_pts}), got {start}")
    take = min(n, n_pts)
    if fpsample is not None:
        order = _fps_library(pts, take, start, method)
    else:
        order = _fps_numpy(pts, take, start)
    if take < n:
        order = order[np.arange(n) % take]
    return _select(pts, order, return_index)


def random_subset(
    points: np.ndarray,
    n: int,
    rng: np.random.Generator | int | None,
    replace: bool = False,
    return_index: bool = False,
) -> Selection:
    """``n`` points drawn uniformly at random (without replacement unless ``replace``).

    Without replacement, ``n`` may not exceed the number of points (pass ``replace=True`` or use
    :func:`farthest_point_sample`, which pads). Order is the random draw order.
    """
    pts = _as_cloud(points)
    n = int(n)
    if n < 1:
        raise InvalidParameterError(f"number of samples n must be >= 1, got {n}")
    if not replace and n > len(pts):
        raise InvalidParameterError(
            f"cannot draw {n} distinct points from a cloud of {len(pts)}; pass replace=True to allow repeats"
        )
    index = _as_generator(rng).choice(len(pts), size=n, replace=replace)
    return _select(pts, index, return_index)


# -- distances and normalisation ----------------------------------------------------------
def nearest_distances(query: np.ndarray, points: np.ndarray, return_index: bool = False) -> Selection:
    """Distance from each query point (M, 3) to its nearest neighbour in ``points`` (N, 3).

    With ``return_index``, also the index into ``points`` of that neighbour.
    """
    q = _as_cloud(query, "query")
    p = _as_cloud(points)
    dist, index = cKDTree(p).query(q, k=1)
    return (dist, index.astype(np.int64)) if return_index else dist


def chamfer_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Chamfer distance: the average of the two directed mean nearest-neighbour distances.

    ``0.5 * (mean_a d(a, B) + mean_b d(b, A))``, in metres (distances, not squared distances).
    Zero exactly when both clouds hold the same points.
    """
    pa, pb = _as_cloud(a, "a"), _as_cloud(b, "b")
    return 0.5 * float(np.mean(nearest_distances(pa, pb)) + np.mean(nearest_distances(pb, pa)))


def normalize_cloud(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Centre a cloud on its centroid and scale it into the unit ball.

    Returns ``(normalised, centre, scale)`` with ``normalised = (points - centre) / scale``,
    ``centre`` the mean point and ``scale`` the largest distance from it, so the farthest point
    lies on the unit sphere. Undo with ``normalised * scale + centre``. A cloud whose points
    all coincide has no extent; its scale is 1.0 (pure centring).
    """
    pts = _as_cloud(points)
    centre = pts.astype(np.float64).mean(axis=0)
    centred = pts - centre
    radius = float(np.max(np.linalg.norm(centred, axis=1)))
    scale = radius if radius > 0 else 1.0
    return (centred / scale).astype(pts.dtype, copy=False), centre, scale
