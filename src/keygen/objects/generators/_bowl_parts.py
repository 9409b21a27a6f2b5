"""Geometry of the bowl generator: the (r, z) wall profile and the convex collision parts.

Everything here works in the half plane (r, z) of a solid of revolution about the z axis. The
cavity curve (inner surface, from the axis on the inner bottom up to the rim) is built first; the
outer surface is its offset along the outward normal, so the wall keeps its thickness on curved
walls. Because the cavity curve is convex, the outward offset never folds over itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import manifold3d
import numpy as np
from scipy.spatial import ConvexHull, QhullError

from keygen.errors import AssetError
from keygen.objects.asset import ConvexPart
from keygen.objects.meshing import hull_part

CURVE_POINTS = 44  # points on the curved part of the cavity profile
CAP_POINTS = 9  # points inside the rounded rim cap
LIP_POINTS = 12  # polygon of the rim bead
LIP_SKIRT = 2.5  # the bead's skirt meets the wall this many bead radii under the bead's centre
BEND_WEIGHT = 0.025  # metres of "length" per radian of turning when spacing profile points
FOOT_OVERLAP = 0.0015  # how far the foot ring reaches into the body, for a robust union
FOOT_CLEARANCE = 0.001  # the bottom's lowest point stays this far above the base plane on a foot
BAND_OVERLAP = 0.0006  # how far (m) each collision band reaches into its neighbours
MIN_FLOOR = 0.002  # floors narrower than this are merged into the axis point
OUTLINE_EPSILON = 1e-5  # outline vertices within this of their neighbours' line are dropped


@dataclass(frozen=True)
class BowlProfile:
    """The closed (r, z) outlines of a bowl in its canonical frame (base plane at z = 0)."""

    inner: np.ndarray  # (M, 2) cavity surface, from the axis up to the rim
    outer: np.ndarray  # (M, 2) outer surface; point k is inner[k] offset along its normal
    cap: np.ndarray  # (C, 2) rounded rim top, from outer[-1] to inner[-1] (ends excluded)
    lip: np.ndarray | None  # (L, 2) closed polygon of the rim bead, or None
    foot: np.ndarray | None  # (4, 2) closed polygon of the foot ring, or None

    def body(self) -> np.ndarray:
        """The body outline, counter-clockwise: outer wall up, over the rim, inner wall down."""
        return np.vstack([self.outer, self.cap, self.inner[::-1]])

    def outline(self) -> np.ndarray:
        """The (r, z) union of body, bead and foot ring: one polygon to revolve into the visual.

        Merging in 2D (manifold3d's CrossSection) before revolving gives one clean solid; a 3D
        union of coaxial solids revolved on the same meridians makes near-coincident vertices.
        """
        polygons = [self.body()] + [p for p in (self.lip, self.foot) if p is not None]
        # simplify: drop slivers (e.g. where the foot meets the wall) that revolve into bad faces.
        contours = manifold3d.CrossSection(polygons).simplify(OUTLINE_EPSILON).to_polygons()
        if len(contours) != 1:
            raise AssetError(f"bowl outline should be one polygon, got {len(contours)}; check the params")
        return np.clip(np.asarray(contours[0], dtype=np.float64), 0.0, None)  # r >= 0 on the axis

    @property
    def rim_top(self) -> float:
        tops = [self.cap[:, 1].max(), self.inner[-1, 1]] + (
            [] if self.lip is None else [self.lip[:, 1].max()]
        )
        return float(max(tops))

    @property
    def inner_bottom(self) -> float:
        return float(self.inner[0, 1])

    @property
    def rim_radius(self) -> float:
        radii = [self.body()[:, 0].max()] + ([] if self.lip is None else [self.lip[:, 0].max()])
        return float(max(radii))

    @property
    def base_radius(self) -> float:
        """Radius of the footprint: the foot ring's outer edge, else the outer flat bottom."""
        if self.foot is not None:
            return float(self.foot[:, 0].max())
        flat = self.outer[np.abs(self.outer[:, 1] - self.outer[0, 1]) < 1e-9]
        return float(flat[:, 0].max())


# -- cavity curves ------------------------------------------------------------------------------
def superellipse_curve(flat_radius: float, rim_radius: float, depth: float, exponent: float, flare: float):
    """Dense cavity curve from the floor (flat_radius, 0) to the inner rim (rim_radius, depth).

    A quadrant of a superellipse (exponent 2: an ellipse; larger: squarer corners) cut at angle
    ``flare`` (pi/2: the wall ends vertical; less: it flares out) and stretched onto the end points.
    """
    theta = np.linspace(0.0, flare, 2000)
    e = 2.0 / exponent
    x = np.sin(theta) ** e / np.sin(flare) ** e
    y = (1.0 - np.cos(theta) ** e) / (1.0 - np.cos(flare) ** e)
    return np.column_stack([flat_radius + (rim_radius - flat_radius) * x, depth * y])


def filleted_cone_curve(flat_radius: float, rim_radius: float, depth: float, fillet: float):
    """Dense cavity curve: a straight wall from (flat_radius, 0) to the rim, corner rounded.

    The fillet is tangent to the floor and to the wall, so the floor ends at
    ``flat_radius - fillet * tan(alpha / 2)`` where alpha is the wall angle.
    """
    alpha = np.arctan2(depth, rim_radius - flat_radius)
    start = flat_radius - fillet * np.tan(alpha / 2)
    phi = np.linspace(0.0, alpha, 200)
    arc = np.column_stack([start + fillet * np.sin(phi), fillet * (1 - np.cos(phi))])
    line = np.linspace(arc[-1], [rim_radius, depth], 200)[1:]
    return np.vstack([arc, line])


def resample(curve: np.ndarray, count: int) -> np.ndarray:
    """``count`` points along a dense polyline, spaced by length plus turning (denser on bends)."""
    d = np.diff(curve, axis=0)
    seg = np.linalg.norm(d, axis=1)
    heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    turn = np.abs(np.diff(heading))
    turn_per_seg = np.concatenate([[0.0], turn]) / 2 + np.concatenate([turn, [0.0]]) / 2
    u = np.concatenate([[0.0], np.cumsum(seg + BEND_WEIGHT * turn_per_seg)])
    target = np.linspace(0.0, u[-1], count)
    return np.column_stack([np.interp(target, u, curve[:, 0]), np.interp(target, u, curve[:, 1])])


def min_wall_angle(curve: np.ndarray, band: float) -> float:
    """Smallest angle from horizontal of the curve over its top ``band`` metres (the grasp zone)."""
    top = curve[curve[:, 1] >= curve[-1, 1] - band]
    d = np.diff(top, axis=0)
    return float(np.min(np.arctan2(d[:, 1], np.maximum(d[:, 0], 0.0) + 1e-12)))


# -- the profile ----------------------------------------------------------------------------------
def _normals(points: np.ndarray, floor_end: int) -> np.ndarray:
    """Outward (away from the cavity) unit normals of a curve running up and outwards."""
    t = np.gradient(points, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    n = np.column_stack([t[:, 1], -t[:, 0]])
    n[: floor_end + 1] = (0.0, -1.0)  # the curve leaves the floor horizontally: keep the base flat
    return n


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def crossings(polygon: np.ndarray, z: float) -> np.ndarray:
    """Sorted radii where the closed polygon's edges cross the height z."""
    a, b = polygon, np.roll(polygon, -1, axis=0)
    hit = (a[:, 1] - z) * (b[:, 1] - z) <= 0
    hit &= a[:, 1] != b[:, 1]
    t = (z - a[hit, 1]) / (b[hit, 1] - a[hit, 1])
    return np.sort(a[hit, 0] + t * (b[hit, 0] - a[hit, 0]))


def build_profile(
    curve: np.ndarray,
    wall: float,
    bottom: float,
    lip_radius: float,
    foot_height: float,
    foot_radius: float,
    foot_width: float,
) -> BowlProfile:
    """Offset the cavity curve into a wall, add the rim cap, the bead and the foot ring.

    ``curve`` starts on the floor (its first point's z is the inner bottom, 0 here) and ends at
    the inner rim. The wall thickness blends from ``bottom`` on the floor to ``wall`` up the side.
    """
    pts = resample(curve, CURVE_POINTS)
    if pts[0, 0] > MIN_FLOOR:  # a flat floor: join it to the axis
        pts = np.vstack([[0.0, pts[0, 1]], pts])
    else:  # a floor too small to mesh cleanly: start the curve on the axis
        pts[0, 0] = 0.0
    floor_end = int(np.argmax(pts[:, 1] > pts[0, 1])) - 1  # last point on the flat floor
    normals = _normals(pts, floor_end)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    s_wall = np.maximum(s - s[floor_end], 0.0)
    blend_len = max(0.25 * s_wall[-1], 0.010)
    thickness = bottom + (wall - bottom) * _smoothstep(s_wall / blend_len)
    outer = pts + thickness[:, None] * normals

    # Rounded rim: a half circle on the wall's end section, bulging along the wall's tangent.
    end_n = normals[-1]
    end_t = np.array([-end_n[1], end_n[0]])
    mid, half = (pts[-1] + outer[-1]) / 2, thickness[-1] / 2
    phi = np.linspace(0.0, np.pi, CAP_POINTS + 2)[1:-1]
    cap = mid + half * (np.cos(phi)[:, None] * end_n + np.sin(phi)[:, None] * end_t)

    # Lift the body so that it rests on the base plane, or so that the outer bottom meets the
    # foot ring's outer edge at foot_height (curved bottoms dip lower inside the ring).
    lift = -outer[:, 1].min()
    if foot_height > 0:
        lift = foot_height - float(np.interp(foot_radius, np.maximum.accumulate(outer[:, 0]), outer[:, 1]))
    pts, outer, cap = pts + (0, lift), outer + (0, lift), cap + (0, lift)
    body = np.vstack([outer, cap, pts[::-1]])

    lip = None
    if lip_radius > 0:
        top = body[:, 1].max()
        z_c = top - lip_radius
        r_c = crossings(body, z_c)[-1] + 0.4 * lip_radius  # overlaps the wall for a solid union
        ang = np.linspace(0.0, 2 * np.pi, LIP_POINTS, endpoint=False) - np.pi / 2
        bead = np.column_stack([r_c + lip_radius * np.cos(ang), z_c + lip_radius * np.sin(ang)])
        # A sloped skirt under the bead, down to the wall: no undercut that convex parts would fill.
        z_s = z_c - LIP_SKIRT * lip_radius
        r_s = crossings(body, z_s)[-1]
        lip = _hull_2d(np.vstack([bead, [[r_s, z_s], [r_s - 0.5 * lip_radius, z_s]]]))

    foot = None
    if foot_height > 0:
        # The ring's top follows the (rising) outer bottom so it meets the body everywhere.
        r_out_curve = np.maximum.accumulate(outer[:, 0])
        r0, r1 = foot_radius - foot_width, foot_radius
        z0, z1 = (float(np.interp(r, r_out_curve, outer[:, 1])) + FOOT_OVERLAP for r in (r0, r1))
        foot = np.array([[r0, 0.0], [r1, 0.0], [r1, z1], [r0, z0]])
    return BowlProfile(inner=pts, outer=outer, cap=cap, lip=lip, foot=foot)


def bottom_rise(outer: np.ndarray, radius: float) -> float:
    """How far the outer bottom at ``radius`` is above its lowest point."""
    return float(np.interp(radius, np.maximum.accumulate(outer[:, 0]), outer[:, 1]) - outer[:, 1].min())


def foot_radius_limit(outer: np.ndarray, foot_height: float, max_slope_deg: float = 40.0) -> float:
    """Largest foot ring radius: the outer bottom must be flatter than ``max_slope_deg`` there and
    must not rise more than ``foot_height - FOOT_CLEARANCE`` (else the bottom would touch down)."""
    d = np.diff(outer, axis=0)
    slope = np.degrees(np.arctan2(d[:, 1], np.maximum(d[:, 0], 1e-12)))
    steep = np.nonzero(slope > max_slope_deg)[0]
    by_slope = outer[steep[0], 0] if len(steep) else outer[-1, 0]
    rise = np.maximum.accumulate(outer[:, 1] - outer[:, 1].min())
    by_rise = np.interp(foot_height - FOOT_CLEARANCE, rise, np.maximum.accumulate(outer[:, 0]))
    return float(min(by_slope, by_rise))


def grasp_point(profile: BowlProfile, below_top: float) -> tuple[float, float]:
    """(r, z) at mid-wall ``below_top`` under the rim top, or mid-wall on the rim for shallow bowls."""
    top = profile.rim_top
    z = top - below_top
    if z > profile.inner_bottom + 0.5 * below_top:
        r = crossings(profile.body(), z)
        if len(r) >= 2:
            return float((r[-2] + r[-1]) / 2), float(z)
    return float(profile.cap[len(profile.cap) // 2, 0]), top


# -- collision parts ------------------------------------------------------------------------------
def segments_for(radius: float, tolerance: float) -> int:
    """Wedges per ring so the polygon strays at most ``tolerance`` from a circle of ``radius``."""
    if radius <= tolerance:
        return 8
    return int(np.clip(np.ceil(np.pi / np.arccos(1.0 - tolerance / radius)), 8, 32))


def wedge_ring(keep: np.ndarray, push: np.ndarray, segments: int) -> list[ConvexPart]:
    """A ring of convex wedges revolving an (r, z) point set between consecutive angles.

    ``keep`` points (the cavity side) stay on their circle, so a wedge's inner face is a chord;
    ``push`` points are moved out by 1/cos(half angle) so the outer faces circumscribe the
    surface. Wedges are centred on +x (phase of half a wedge) so the ring is mirror symmetric.
    """
    half = np.pi / segments
    grow = 1.0 / np.cos(half)
    pts = _hull_2d(np.vstack([keep, push * (grow, 1.0)]))  # (P, 2): only the outline matters
    parts = []
    for s in range(segments):
        a = np.array([2 * half * s - half, 2 * half * s + half])
        xyz = np.concatenate(
            [np.column_stack([pts[:, 0] * np.cos(ai), pts[:, 0] * np.sin(ai), pts[:, 1]]) for ai in a]
        )
        parts.append(hull_part(xyz))
    return parts


def _hull_2d(points: np.ndarray, flat: float = 2e-5) -> np.ndarray:
    """The vertices of the 2D convex hull, minus near-straight corners.

    Fewer points make each 3D hull cheaper, and a corner within ``flat`` metres of the line
    through its neighbours would only give the 3D hull sliver faces that break its topology.
    """
    try:
        hull = points[ConvexHull(points).vertices]
    except QhullError:  # degenerate (collinear) sets: keep them all
        return points
    while len(hull) > 3:
        prev, nxt = np.roll(hull, 1, axis=0), np.roll(hull, -1, axis=0)
        chord = nxt - prev
        cross = np.abs(chord[:, 0] * (hull - prev)[:, 1] - chord[:, 1] * (hull - prev)[:, 0])
        height = cross / np.maximum(np.linalg.norm(chord, axis=1), 1e-12)
        k = int(np.argmin(height))
        if height[k] >= flat:
            break
        hull = np.delete(hull, k, axis=0)
    return hull


def revolved_hull(keep: np.ndarray, push: np.ndarray, segments: int) -> ConvexPart:
    """One convex part: an (r, z) point set revolved to ``segments`` angles and hulled (a disc)."""
    half = np.pi / segments
    pts = np.vstack([keep, push * (1.0 / np.cos(half), 1.0)])
    ang = 2 * half * np.arange(segments) - half
    xyz = np.concatenate(
        [np.column_stack([pts[:, 0] * np.cos(a), pts[:, 0] * np.sin(a), pts[:, 1]]) for a in ang]
    )
    return hull_part(xyz)


def _chord_deviation(points: np.ndarray) -> float:
    """Largest distance of a polyline's points from the chord joining its ends."""
    a, b = points[0], points[-1]
    d = b - a
    length = np.linalg.norm(d)
    if length < 1e-12:
        return float(np.max(np.linalg.norm(points - a, axis=1)))
    rel = points - a
    return float(np.max(np.abs(rel[:, 0] * d[1] - rel[:, 1] * d[0]) / length))


def split_bands(inner: np.ndarray, start: int, last: int, tolerance: float) -> list[tuple[int, int]]:
    """Greedy index bands of the cavity curve whose chords stray at most ``tolerance`` from it."""
    bands, k = [], start
    while k < last:
        j = k + 1
        while j < last and _chord_deviation(inner[k : j + 2]) <= tolerance:
            j += 1
        bands.append((k, j))
        k = j
    return bands


def floor_end_index(inner: np.ndarray, tolerance: float) -> int:
    """Last cavity point the bottom disc can take while its flat top stays within ``tolerance``."""
    rise = inner[:, 1] - inner[0, 1]
    return max(int(np.nonzero(rise <= tolerance)[0].max()), 1)


@dataclass(frozen=True)
class _Ring:
    """One planned ring of collision parts: (r, z) points kept / pushed out, and its wedge count."""

    keep: np.ndarray
    push: np.ndarray
    segments: int
    whole: bool = False  # one part around the axis (the bottom disc) instead of wedges

    @property
    def count(self) -> int:
        return 1 if self.whole else self.segments

    def parts(self) -> list[ConvexPart]:
        if self.whole:
            return [revolved_hull(self.keep, self.push, self.segments)]
        return wedge_ring(self.keep, self.push, self.segments)


def _overlap_index(inner: np.ndarray, k: int, step: int) -> float:
    """Fractional index BAND_OVERLAP metres along the cavity curve from point k (step -1 or +1)."""
    left, pos = BAND_OVERLAP, k
    while 0 <= pos + step < len(inner):
        seg = float(np.linalg.norm(inner[pos + step] - inner[pos]))
        if seg >= left:
            return pos + step * left / seg
        left, pos = left - seg, pos + step
    return float(pos)


def _overlapping(curve: np.ndarray, inner: np.ndarray, k0: int, k1: int) -> np.ndarray:
    """curve[k0 : k1 + 1] reaching BAND_OVERLAP further along at both ends (same fractional
    indices on the inner and outer curves, so the band's end faces stay matched).

    Neighbouring rings may have different wedge counts, so their end faces differ slightly;
    the overlap closes the hair-thin slivers that would leave between them.
    """
    idx = np.arange(len(curve))
    ends = [_overlap_index(inner, k0, -1), _overlap_index(inner, k1, +1)]
    extra = np.column_stack([np.interp(ends, idx, curve[:, 0]), np.interp(ends, idx, curve[:, 1])])
    return np.vstack([extra[:1], curve[k0 : k1 + 1], extra[1:]])


def _plan(profile: BowlProfile, profile_tol: float, angle_tol: float) -> list[_Ring]:
    inner, outer, last = profile.inner, profile.outer, len(profile.inner) - 1
    j = floor_end_index(inner, profile_tol)
    disc = (_overlapping(inner, inner, 0, j), _overlapping(outer, inner, 0, j))
    rings = [_Ring(*disc, segments_for(outer[j, 0], angle_tol), whole=True)]
    rim_extra = profile.cap
    if profile.lip is None:
        bands = split_bands(inner, j, last, profile_tol)
    else:
        # The bead gets a band of its own: a longer band's hull would fill the step under it.
        rim_extra = np.vstack([profile.cap, profile.lip])
        below = np.nonzero(inner[:, 1] <= profile.lip[:, 1].min())[0]
        rim_start = int(below.max()) if len(below) and below.max() > j else last - 1
        bands = split_bands(inner, j, rim_start, profile_tol) + [(rim_start, last)]
    for b, (k0, k1) in enumerate(bands):
        push = _overlapping(outer, inner, k0, k1)
        if b == len(bands) - 1:
            push = np.vstack([push, rim_extra])
        rings.append(
            _Ring(_overlapping(inner, inner, k0, k1), push, segments_for(push[:, 0].max(), angle_tol))
        )
    if profile.foot is not None:
        foot = profile.foot
        rings.append(_Ring(foot[[0, 3]], foot[[1, 2]], segments_for(foot[:, 0].max(), angle_tol)))
    return rings


def collision_parts(
    profile: BowlProfile, budget: int, profile_tol: float = 0.001, angle_tol: float = 0.001
) -> list[ConvexPart]:
    """Bottom disc + rings of wedges per wall band (+ rim cap and bead) + foot ring wedges.

    The cavity stays hollow: wedges follow the wall, so another bowl can nest inside. When the
    plan would exceed ``budget`` parts the tolerances are relaxed step by step (a bounded loop).
    """
    rings = _plan(profile, profile_tol, angle_tol)
    for _ in range(16):
        if sum(r.count for r in rings) <= budget:
            break
        profile_tol, angle_tol = profile_tol * 1.15, angle_tol * 1.15
        rings = _plan(profile, profile_tol, angle_tol)
    return [part for ring in rings for part in ring.parts()]
