"""Mesh-building helpers shared by the category generators.

Visual meshes are built as closed solids (solids of revolution, swept tubes, extrusions) and
merged with a robust boolean union (manifold3d) so that the result is watertight. Collision
geometry is built separately as convex parts that follow the functional shape.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import trimesh

from keygen.errors import AssetError
from keygen.objects.asset import ConvexPart


def revolve_profile(profile_rz: np.ndarray, sections: int = 64) -> trimesh.Trimesh:
    """Revolve a closed (r, z) polygon about the z axis into a watertight solid.

    ``profile_rz`` is an (M, 2) polygon, counter-clockwise in the (r, z) half plane, not closed
    (the last point is joined to the first). Points with r == 0 lie on the axis.
    """
    p = np.asarray(profile_rz, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 3:
        raise AssetError(f"profile must be (M>=3, 2), got {p.shape}")
    if np.any(p[:, 0] < 0):
        raise AssetError("profile radii must be non-negative")
    closed = np.vstack([p, p[:1]])
    mesh = trimesh.creation.revolve(closed, sections=sections)
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    trimesh.repair.fix_normals(mesh)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def union(meshes: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    """Boolean union through manifold3d; the result is checked to be a watertight volume."""
    if len(meshes) == 1:
        result = meshes[0].copy()
    else:
        result = trimesh.boolean.union(meshes, engine="manifold")
    # No merge_vertices here: manifold3d's output is already manifold, and merging its close
    # intersection vertices (< 1e-8 m apart) can tear it open.
    if not result.is_watertight or not result.is_volume:
        raise AssetError("boolean union did not give a watertight volume")
    return result


def sweep_tube(path: np.ndarray, half_width: float, half_depth: float, sides: int = 16) -> trimesh.Trimesh:
    """A closed tube of elliptical section swept along an open 3D polyline.

    The section is carried along the path with parallel-transport frames (no twisting).
    ``half_depth`` is its half size along the first frame normal (for a planar path, the
    in-plane normal), ``half_width`` along the second (the binormal). Ends are capped with a
    centre vertex each, so the tube is a watertight volume.
    """
    path = np.asarray(path, dtype=np.float64)
    if path.ndim != 2 or path.shape[1] != 3 or len(path) < 2:
        raise AssetError(f"tube path must be (M>=2, 3), got {path.shape}")
    tangents = np.gradient(path, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    # Initial normal: any vector orthogonal to the first tangent, preferring the path's plane.
    seed = np.cross(np.cross(tangents[0], path[len(path) // 2] - path[0]), tangents[0])
    if np.linalg.norm(seed) < 1e-9:
        seed = np.cross(tangents[0], [1.0, 0, 0] if abs(tangents[0][0]) < 0.9 else [0, 1.0, 0])
    normal = seed / np.linalg.norm(seed)
    angles = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    rings = []
    for i, t in enumerate(tangents):
        if i > 0:  # parallel transport: remove the component along the new tangent
            normal = normal - np.dot(normal, t) * t
            normal /= np.linalg.norm(normal)
        binormal = np.cross(t, normal)
        ring = (
            path[i]
            + half_depth * np.outer(np.cos(angles), normal)
            + half_width * np.outer(np.sin(angles), binormal)
        )
        rings.append(ring)
    vertices = np.vstack(rings + [path[:1], path[-1:]])
    m, n = len(path), sides
    faces = []
    for i in range(m - 1):
        for j in range(n):
            a, b = i * n + j, i * n + (j + 1) % n
            c, d = a + n, b + n
            faces += [(a, b, d), (a, d, c)]
    start, end = m * n, m * n + 1
    for j in range(n):
        faces.append((start, (j + 1) % n, j))
        faces.append((end, (m - 1) * n + j, (m - 1) * n + (j + 1) % n))
    mesh = trimesh.Trimesh(vertices, np.array(faces), process=True)
    trimesh.repair.fix_normals(mesh)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def with_label(parts: list[ConvexPart], label: str) -> list[ConvexPart]:
    """The parts tagged with a functional label (e.g. "handle"), see ConvexPart.label."""
    return [replace(p, label=label) for p in parts]


def hull_part(points: np.ndarray) -> ConvexPart:
    """A convex collision part: the hull of the given points."""
    return ConvexPart("mesh", vertices=np.asarray(points, dtype=np.float64))


def ring_wall_parts(
    z: np.ndarray, r_inner: np.ndarray, r_outer: np.ndarray, segments: int, phase: float = 0.0
) -> list[ConvexPart]:
    """Convex wedges approximating a thin wall of revolution.

    The wall between heights ``z[k]`` and ``z[k+1]`` with inner and outer radii given per height
    is cut into ``segments`` angular wedges per band; each wedge is the hull of its 8 corners.
    The outer corners are pushed out by 1/cos(half angle) so the polygonal ring circumscribes
    the true outer surface (no gaps for particles to leak through at the seams).
    """
    z, r_in, r_out = (np.asarray(a, dtype=np.float64) for a in (z, r_inner, r_outer))
    half = np.pi / segments
    grow = 1.0 / np.cos(half)
    parts = []
    for k in range(len(z) - 1):
        for s in range(segments):
            a0, a1 = phase + 2 * half * s, phase + 2 * half * (s + 1)
            pts = []
            for zk, ri, ro in ((z[k], r_in[k], r_out[k]), (z[k + 1], r_in[k + 1], r_out[k + 1])):
                for a in (a0, a1):
                    c, sn = np.cos(a), np.sin(a)
                    pts.append((ri * c, ri * sn, zk))
                    pts.append((ro * grow * c, ro * grow * sn, zk))
            parts.append(hull_part(np.array(pts)))
    return parts


def disc_part(radius: float, z0: float, z1: float, segments: int = 24) -> ConvexPart:
    """A convex polygonal disc (prism) between two heights, circumscribing the circle."""
    angles = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    r = radius / np.cos(np.pi / segments)
    ring = np.stack([r * np.cos(angles), r * np.sin(angles)], axis=1)
    pts = np.vstack(
        [np.column_stack([ring, np.full(segments, z0)]), np.column_stack([ring, np.full(segments, z1)])]
    )
    return hull_part(pts)


def capsule_chain(path: np.ndarray, radius: float) -> list[ConvexPart]:
    """Capsules along consecutive points of a polyline (joints overlap smoothly)."""
    path = np.asarray(path, dtype=np.float64)
    return [ConvexPart("capsule", p0=path[i], p1=path[i + 1], radius=radius) for i in range(len(path) - 1)]


def distance_to_solid(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """Distance from each point to a closed solid: 0 inside, the surface distance outside."""
    points = np.atleast_2d(np.asarray(points, dtype=np.float64))
    signed = trimesh.proximity.signed_distance(mesh, points)  # positive inside
    return np.where(signed > 0, 0.0, -signed)
