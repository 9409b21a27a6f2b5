"""A lighter copy of an object's visual mesh for the simulator's cameras.

Offscreen rendering here is Mesa's software rasteriser, whose cost grows with the vertices drawn,
not with the pixels: a procedural mug's 12,000-14,000 faces were a third or more of a four-view
observation at 128 x 128, where one pixel spans ~6 mm at the table. :func:`render_mesh` simplifies
such a mesh toward a face budget by quadric edge collapse (``trimesh`` over
``fast_simplification``) and keeps the result only if it stays within ``tolerance`` of the original
surface both ways (checked on seeded surface samples); otherwise the original is used. The asset
itself is untouched: collision, mass properties, anchors and keypoint scans still use the full mesh.
"""

from __future__ import annotations

import hashlib
import logging

import numpy as np
import trimesh

from keygen.errors import InvalidParameterError

__all__ = ["render_mesh"]

log = logging.getLogger(__name__)

DEFAULT_TOLERANCE = 0.002  # m; a third of a pixel at the rig's default 128 x 128
_CHECK_SAMPLES = 1500
# fast_simplification's default aggressiveness (7) tore the handle or rim open (deviations up to
# 5 cm) on a third of the procedural mugs at half their faces; at 2 every mug stayed within 0.9 mm,
# at the price of stopping short of the target on some (6,500-7,800 faces for a target of 7,000).
_AGGRESSION = 2
_CACHE: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
_CACHE_SIZE = 64


def _key(vertices: np.ndarray, faces: np.ndarray, max_faces: int, tolerance: float) -> tuple:
    digest = hashlib.blake2b(vertices.tobytes(), digest_size=16)
    digest.update(faces.tobytes())
    return digest.hexdigest(), max_faces, tolerance


def _one_way_distance(source: trimesh.Trimesh, target: trimesh.Trimesh) -> float:
    """Largest distance from seeded samples of ``source``'s surface to ``target``'s surface."""
    points, _ = trimesh.sample.sample_surface(source, _CHECK_SAMPLES, seed=0)
    _, distance, _ = trimesh.proximity.closest_point(target, points)
    return float(distance.max())


def render_mesh(
    vertices: np.ndarray, faces: np.ndarray, max_faces: int, tolerance: float = DEFAULT_TOLERANCE
) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices, faces)`` simplified toward ``max_faces`` faces when the result has fewer faces
    and lies within ``tolerance`` metres of the original both ways; otherwise the input arrays.
    Meshes with at most ``max_faces`` faces are returned as they are. Cached by content."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise InvalidParameterError(
            f"render_mesh needs (V, 3) vertices and (F, 3) faces, got {vertices.shape} and {faces.shape}"
        )
    if max_faces < 4 or not tolerance > 0:
        raise InvalidParameterError(f"need max_faces >= 4 and tolerance > 0, got {max_faces}, {tolerance}")
    if len(faces) <= max_faces:
        return vertices, faces
    key = _key(vertices, faces, int(max_faces), float(tolerance))
    if key not in _CACHE:
        full = trimesh.Trimesh(vertices, faces, process=False)
        try:
            light = full.simplify_quadric_decimation(face_count=int(max_faces), aggression=_AGGRESSION)
            deviation = max(_one_way_distance(full, light), _one_way_distance(light, full))
        except Exception as err:  # noqa: BLE001 - an imported mesh the simplifier cannot take: draw it whole
            log.debug("render mesh: simplification failed (%s); keeping %d faces", err, len(faces))
            light, deviation = full, np.inf
        if len(light.faces) < len(faces) and deviation <= tolerance:
            result = (np.asarray(light.vertices, np.float64), np.asarray(light.faces, np.int64))
        else:
            log.debug(
                "render mesh: %d faces would leave %.4f m of deviation (limit %.4f); keeping %d",
                len(light.faces),
                deviation,
                tolerance,
                len(faces),
            )
            result = (vertices, faces)
        if len(_CACHE) >= _CACHE_SIZE:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = result
    return _CACHE[key]
