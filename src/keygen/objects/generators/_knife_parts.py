"""Geometry helpers of the knife generator: blade outlines, the blade and handle solids, their convex parts.

The blade is an x-monotone outline: at each *station* x it spans from the cutting edge ``ye`` up
to the spine ``ys``, and the last station is the tip, where the two meet. That lets the blade be
built as a "ladder" of trapezoidal cross-sections (full thickness at the spine, thin at the edge)
whose top and bottom faces are triangulated station to station, with no polygon triangulator. The
handle is a loft of superellipse sections along -x with a rounded butt. Both are closed solids; the
generator merges them with :func:`keygen.objects.meshing.union`.

Collision parts are hulls of the very vertices of these solids, grouped by runs of stations or
rings, so every part contains its piece of the visual exactly and neighbouring parts share a
boundary section (no gaps between them).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh

from keygen.objects.asset import ConvexPart
from keygen.objects.meshing import hull_part

# Blade stations closer than this are merged away (keeps the ladder free of sliver faces).
_MIN_STATION_GAP = 1e-5


@dataclass(frozen=True)
class BladeOutline:
    """An x-monotone blade outline: spine ``ys`` above edge ``ye`` at stations ``xs``; the last is the tip."""

    xs: np.ndarray
    ys: np.ndarray
    ye: np.ndarray

    @property
    def tip(self) -> np.ndarray:
        return np.array([self.xs[-1], self.ys[-1]])


def _ramp(x: np.ndarray, start: float, end: float, power: float) -> np.ndarray:
    """0 before ``start``, rising as ((x - start) / (end - start))**power to 1 at ``end``."""
    u = np.clip((x - start) / max(end - start, 1e-9), 0.0, 1.0)
    return u**power


def _stations(length: float, spacing: float, dense_from: float) -> np.ndarray:
    """Stations from 0 to ``length``: ``spacing`` apart, four times denser after ``dense_from``."""
    coarse = np.linspace(0.0, dense_from, max(2, int(np.ceil(dense_from / spacing)) + 1))
    fine_count = max(2, int(np.ceil((length - dense_from) / (spacing / 4))) + 1)
    fine = np.linspace(dense_from, length, fine_count)
    return np.unique(np.concatenate([coarse, fine]))


def pointed_outline(
    length: float,
    width: float,
    tip_y: float,
    spine_drop_start: float,
    spine_drop_power: float,
    edge_rise_start: float,
    edge_rise_power: float,
) -> BladeOutline:
    """A blade whose spine drops and edge rises to meet at a point (chef, paring, utility, santoku).

    Spine and edge are straight from the heel, then curve as power ramps (power >= 1) to the tip at
    (``length``, ``tip_y``). A dropping spine with power >= 1 is concave and a rising edge is convex,
    so the outline is convex and every x-slab of it is convex too.
    """
    half = width / 2
    start = min(spine_drop_start, edge_rise_start) * length
    xs = _stations(length, spacing=min(0.0025, length / 40), dense_from=max(start, 0.7 * length))
    ys = half - (half - tip_y) * _ramp(xs, spine_drop_start * length, length, spine_drop_power)
    ye = -half + (tip_y + half) * _ramp(xs, edge_rise_start * length, length, edge_rise_power)
    ys[-1] = ye[-1] = tip_y
    return BladeOutline(xs, ys, ye)


def rounded_outline(
    length: float,
    width: float,
    spine_taper: float,
    edge_belly: float,
    tip_bulge: float,
    serration_pitch: float = 0.0,
    serration_depth: float = 0.0,
) -> BladeOutline:
    """A blade with a blunt, elliptic front (bread: round tip; cleaver: almost flat front).

    The body runs from x = 0 to the start of the front, its spine sloping down by ``spine_taper``
    and its edge rising by ``edge_belly`` (a convex parabola); the front is a quarter ellipse on each
    side, ``tip_bulge`` times the front half-height long in x. Serrations are scallops cut into
    the straight part of the edge (visual detail; the collision strips bridge them).
    """
    half = width / 2
    # Front half-height is known before the body length (the taper/belly are fractions of the body).
    front_half = half - (spine_taper + edge_belly) / 2
    bulge = tip_bulge * front_half
    body = length - bulge
    spacing = min(0.0025, body / 40)
    if serration_depth > 0 and serration_pitch > 0:
        spacing = min(spacing, serration_pitch / 8)
    xs = np.linspace(0.0, body, max(2, int(np.ceil(body / spacing)) + 1))
    ys = half - spine_taper * xs / body
    ye = -half + edge_belly * (xs / body) ** 2
    if serration_depth > 0 and serration_pitch > 0:
        teeth = (xs > serration_pitch) & (xs < body - serration_pitch)
        ye = ye + teeth * serration_depth * np.abs(np.sin(np.pi * xs / serration_pitch))
    centre = (ys[-1] + ye[-1]) / 2
    theta = np.linspace(0.0, np.pi / 2, 17)[1:]
    front_x = body + bulge * np.sin(theta)
    front_h = (ys[-1] - ye[-1]) / 2 * np.cos(theta)
    xs = np.concatenate([xs, front_x])
    ys = np.concatenate([ys, centre + front_h])
    ye = np.concatenate([ye, centre - front_h])
    ys[-1] = ye[-1] = centre
    return BladeOutline(xs, ys, ye)


def _clean(outline: BladeOutline) -> BladeOutline:
    """Drop stations that are (nearly) on top of the last kept one; the tip always stays."""
    keep = [0]
    for i in range(1, len(outline.xs)):
        if outline.xs[i] - outline.xs[keep[-1]] > _MIN_STATION_GAP:
            keep.append(i)
        elif i == len(outline.xs) - 1:
            keep[-1] = i
    idx = np.asarray(keep)
    return BladeOutline(outline.xs[idx], outline.ys[idx], outline.ye[idx])


def blade_vertices(outline: BladeOutline, spine_thickness: float, edge_thickness: float) -> np.ndarray:
    """(N, 4, 3) section corners: spine-top, edge-top, edge-bottom, spine-bottom per station.

    The tip station is collapsed to one point in x-y (its top and bottom keep the edge thickness).
    """
    o = _clean(outline)
    n = len(o.xs)
    v = np.zeros((n, 4, 3))
    v[:, :, 0] = o.xs[:, None]
    v[:, [0, 3], 1] = o.ys[:, None]
    v[:, [1, 2], 1] = o.ye[:, None]
    ts, te = spine_thickness / 2, edge_thickness / 2
    v[:, 0, 2], v[:, 3, 2] = ts, -ts
    v[:, 1, 2], v[:, 2, 2] = te, -te
    v[-1, [0, 1], 2] = te
    v[-1, [2, 3], 2] = -te
    return v


def _ring_faces(n_rings: int, ring_size: int) -> list[tuple[int, int, int]]:
    """Quads between consecutive closed rings of ``ring_size`` vertices, two triangles each."""
    faces = []
    for i in range(n_rings - 1):
        for k in range(ring_size):
            a, b = i * ring_size + k, i * ring_size + (k + 1) % ring_size
            c, d = b + ring_size, a + ring_size
            faces += [(a, b, c), (a, c, d)]
    return faces


def _closed_mesh(vertices: np.ndarray, faces: list[tuple[int, int, int]]) -> trimesh.Trimesh:
    """A mesh from raw faces, with repeated vertices merged, slivers dropped and outward normals."""
    mesh = trimesh.Trimesh(vertices, np.asarray(faces), process=True)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def blade_mesh(corners: np.ndarray) -> trimesh.Trimesh:
    """The closed blade solid from :func:`blade_vertices` corners (heel cap at the first station)."""
    n = len(corners)
    vertices = corners.reshape(-1, 3)
    faces = _ring_faces(n, 4)  # the tip ring's coincident corners give slivers that get dropped
    faces += [(0, 3, 2), (0, 2, 1)]  # heel cap, wound against the ring order
    return _closed_mesh(vertices, faces)


def strip_bounds(xs: np.ndarray, count: int) -> np.ndarray:
    """Station indices splitting the stations into ``count`` runs of about equal x length."""
    targets = np.linspace(xs[0], xs[-1], count + 1)
    idx = np.unique(np.searchsorted(xs, targets).clip(0, len(xs) - 1))
    idx[0], idx[-1] = 0, len(xs) - 1
    return np.unique(idx)


def blade_strip_parts(corners: np.ndarray, count: int) -> list[ConvexPart]:
    """Convex strips along x: the hull of each run of blade sections (neighbours share a section)."""
    bounds = strip_bounds(corners[:, 0, 0], count)
    return [
        hull_part(corners[a : b + 1].reshape(-1, 3)) for a, b in zip(bounds[:-1], bounds[1:], strict=True)
    ]


# -- handle and bolster --------------------------------------------------------------------------


@dataclass(frozen=True)
class LoftSections:
    """Superellipse sections along x: position, full width (y), full thickness (z), centre y."""

    x: np.ndarray
    width: np.ndarray
    thickness: np.ndarray
    centre: np.ndarray
    exponent: float


def superellipse_ring(width: float, thickness: float, exponent: float, sides: int) -> np.ndarray:
    """(sides, 2) points on |2y/w|^n + |2z/t|^n = 1 (an inscribed polygon of the curve)."""
    a = np.linspace(0.0, 2 * np.pi, sides, endpoint=False)
    c, s = np.cos(a), np.sin(a)
    e = 2.0 / exponent
    return np.column_stack(
        [width / 2 * np.sign(c) * np.abs(c) ** e, thickness / 2 * np.sign(s) * np.abs(s) ** e]
    )


def loft_rings(sections: LoftSections, sides: int) -> np.ndarray:
    """(R, sides, 3) ring vertices of the sections."""
    rings = np.zeros((len(sections.x), sides, 3))
    for i in range(len(sections.x)):
        yz = superellipse_ring(sections.width[i], sections.thickness[i], sections.exponent, sides)
        rings[i, :, 0] = sections.x[i]
        rings[i, :, 1] = sections.centre[i] + yz[:, 0]
        rings[i, :, 2] = yz[:, 1]
    return rings


def loft_mesh(rings: np.ndarray, first_cap: np.ndarray, last_cap: np.ndarray) -> trimesh.Trimesh:
    """A closed loft through ``rings``, each end closed by a fan to a cap point."""
    r, s = rings.shape[:2]
    vertices = np.vstack([rings.reshape(-1, 3), first_cap[None], last_cap[None]])
    faces = _ring_faces(r, s)
    first, last = r * s, r * s + 1
    for k in range(s):
        faces.append((first, (k + 1) % s, k))
        faces.append((last, (r - 1) * s + k, (r - 1) * s + (k + 1) % s))
    return _closed_mesh(vertices, faces)


def loft_parts(rings: np.ndarray, last_cap: np.ndarray, count: int) -> list[ConvexPart]:
    """Hulls of ``count`` runs of consecutive rings (the last run also takes the end cap point)."""
    bounds = np.unique(np.linspace(0, len(rings) - 1, count + 1).round().astype(int))
    parts = []
    for j, (a, b) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
        pts = rings[a : b + 1].reshape(-1, 3)
        if j == len(bounds) - 2:
            pts = np.vstack([pts, last_cap[None]])
        parts.append(hull_part(pts))
    return parts


def handle_sections(
    shape: str,
    x_front: float,
    x_butt: float,
    width: float,
    thickness: float,
    centre_y: float,
    taper: float,
    belly: float,
    sag: float,
    exponent: float,
    spacing: float = 0.006,
) -> tuple[LoftSections, np.ndarray]:
    """Sections of the grip from ``x_front`` back to ``x_butt`` and the butt's cap point.

    ``width``/``thickness`` are the grip's largest; the shape decides how they vary with u (0 at
    the front, 1 at the butt): straight, tapered (narrower toward the butt), belly (fullest in the
    middle) or curved (the butt drops toward the edge side by ``sag`` and flares slightly).
    The butt is rounded by a few shrinking sections over a radius of 30 % of its smaller size.
    """
    length = x_front - x_butt
    w_t_c = _grip_profile(shape, width, thickness, centre_y, taper, belly, sag)
    w_b, t_b, c_b = w_t_c(np.array([1.0]))
    radius = 0.3 * min(w_b[0], t_b[0])
    flat_end = x_butt + radius
    count = max(8, int(np.ceil((x_front - flat_end) / spacing)) + 1)
    x = np.linspace(x_front, flat_end, count)
    w, t, c = w_t_c((x_front - x) / length)
    phi = np.linspace(0.0, np.pi / 2, 6)[1:-1]
    shrink = 2 * radius * (1 - np.cos(phi))
    x = np.concatenate([x, flat_end - radius * np.sin(phi)])
    w = np.concatenate([w, w_b[0] - shrink])
    t = np.concatenate([t, t_b[0] - shrink])
    c = np.concatenate([c, np.full(len(phi), c_b[0])])
    cap = np.array([x_butt, c_b[0], 0.0])
    return LoftSections(x, w, t, c, exponent), cap


def _grip_profile(
    shape: str, width: float, thickness: float, centre_y: float, taper: float, belly: float, sag: float
) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """A function u -> (width, thickness, centre y) arrays for the grip shape."""

    def profile(u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ones = np.ones_like(u)
        if shape == "tapered":
            return width * (1 - taper * u), thickness * (1 - 0.7 * taper * u), centre_y * ones
        if shape == "belly":
            bulge = np.sin(np.pi * u)
            w = width * (1 - belly + belly * bulge)
            t = thickness * (1 - 0.6 * belly + 0.6 * belly * bulge)
            return w, t, centre_y * ones
        if shape == "curved":
            return width * (0.92 + 0.08 * u), thickness * ones, centre_y - sag * u**2
        return width * ones, thickness * ones, centre_y * ones

    return profile


def grip_centre(
    shape: str,
    width: float,
    thickness: float,
    centre_y: float,
    taper: float,
    belly: float,
    sag: float,
    u: float,
) -> float:
    """The grip's centre y at fraction ``u`` of its length (0 front, 1 butt)."""
    return float(_grip_profile(shape, width, thickness, centre_y, taper, belly, sag)(np.array([u]))[2][0])
