"""Geometry helpers for the mug generator: the body profile and the handle centreline.

Everything here is plain 2D geometry in the mug's canonical x-z half plane (metres): the body is a
profile in (r, z) revolved about z, the handle is a centreline in (x, z) at y = 0 swept into a
tube. Keeping it 2D lets :class:`~keygen.objects.generators.mug.MugGenerator` check the handle's
functional constraints (opening size, room on the body) cheaply while sampling, before any mesh
is built.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from keygen.errors import InvalidParameterError

RIMS = ("plain", "bead", "flared")
HANDLE_STYLES = ("round", "d", "square", "angular", "ear")

# Angular step used to sample fillet and circle arcs (radians); the tube is resampled later.
_ARC_STEP = np.deg2rad(5.0)
# The finger that passes through the opening: its centre sits this far inside the outer bar's
# inner side (8 mm thick finger, 1 mm play), and the clear height is measured there.
FINGER_INSET = 0.005


# -- polylines ------------------------------------------------------------------------------------
def fillet_polyline(points: np.ndarray, radii: np.ndarray, closed: bool = False) -> np.ndarray:
    """Round the corners of a 2D polyline with circular arcs.

    ``radii[i]`` is the wanted arc radius at vertex ``i`` (0 keeps the corner sharp). An arc's
    tangent length is clamped to half of each adjacent segment (the whole segment next to an
    unrounded vertex), so neighbouring arcs never overlap; the arc radius shrinks accordingly.
    For an open polyline the end points are kept as they are.
    """
    pts = np.asarray(points, dtype=np.float64)
    radii = np.asarray(radii, dtype=np.float64)
    n = len(pts)
    out: list[np.ndarray] = []
    for i in range(n):
        if not closed and i in (0, n - 1):
            out.append(pts[i][None])
            continue
        prev_i, next_i = (i - 1) % n, (i + 1) % n
        corner = _fillet_corner(pts[prev_i], pts[i], pts[next_i], radii[i], radii[prev_i], radii[next_i])
        out.append(corner)
    return np.vstack(out)


def _fillet_corner(
    prev: np.ndarray, vertex: np.ndarray, nxt: np.ndarray, radius: float, r_prev: float, r_next: float
) -> np.ndarray:
    """Points of the arc replacing one corner (just the vertex when it stays sharp)."""
    a, b = prev - vertex, nxt - vertex
    la, lb = np.linalg.norm(a), np.linalg.norm(b)
    if radius <= 0 or la < 1e-12 or lb < 1e-12:
        return vertex[None]
    ua, ub = a / la, b / lb
    cos_full = float(np.clip(np.dot(ua, ub), -1.0, 1.0))
    interior = np.arccos(cos_full)  # angle between the two legs
    if interior > np.pi - 1e-6:  # collinear: nothing to round
        return vertex[None]
    half = interior / 2
    tangent = radius / np.tan(half)
    # Share each segment with the corner at its other end (all of it if that one stays sharp).
    limit = min(la * (0.5 if r_prev > 0 else 0.95), lb * (0.5 if r_next > 0 else 0.95))
    if tangent > limit:
        tangent = limit
        radius = tangent * np.tan(half)
    bisector = (ua + ub) / np.linalg.norm(ua + ub)
    centre = vertex + bisector * radius / np.sin(half)
    t0, t1 = vertex + ua * tangent, vertex + ub * tangent
    ang0 = np.arctan2(*(t0 - centre)[::-1])
    ang1 = np.arctan2(*(t1 - centre)[::-1])
    sweep = (ang1 - ang0 + np.pi) % (2 * np.pi) - np.pi  # the short way round
    count = max(2, int(np.ceil(abs(sweep) / _ARC_STEP)) + 1)
    angles = ang0 + sweep * np.linspace(0.0, 1.0, count)
    return centre + radius * np.column_stack([np.cos(angles), np.sin(angles)])


def resample_polyline(points: np.ndarray, spacing: float) -> np.ndarray:
    """Points at (nearly) equal arc-length spacing along a polyline, end points kept."""
    pts = np.asarray(points, dtype=np.float64)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-12])
    pts = pts[keep]
    s = np.concatenate([[0.0], np.cumsum(seg[seg > 1e-12])])
    count = max(2, int(np.ceil(s[-1] / spacing)) + 1)
    t = np.linspace(0.0, s[-1], count)
    return np.column_stack([np.interp(t, s, pts[:, k]) for k in range(pts.shape[1])])


def polyline_centroid(points: np.ndarray) -> np.ndarray:
    """Arc-length weighted centroid of a polyline."""
    pts = np.asarray(points, dtype=np.float64)
    mids = (pts[1:] + pts[:-1]) / 2
    lengths = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    return (mids * lengths[:, None]).sum(axis=0) / lengths.sum()


def distance_to_polyline(query: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Euclidean distance from each query point to an open polyline (any dimension)."""
    q = np.atleast_2d(np.asarray(query, dtype=np.float64))
    a, b = points[:-1], points[1:]
    ab = b - a
    denom = np.maximum((ab * ab).sum(axis=1), 1e-24)
    t = np.clip(((q[:, None, :] - a[None]) * ab[None]).sum(axis=2) / denom[None], 0.0, 1.0)
    closest = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(q[:, None, :] - closest, axis=2).min(axis=1)


def simplify_polyline(points: np.ndarray, tolerance: float, max_segments: int) -> np.ndarray:
    """Indices of a coarse polyline within ``tolerance`` of the dense one (greedy splitting).

    The segment whose dense points stray farthest is split at that point until every point is
    within tolerance or ``max_segments`` is reached, so the collision chain stays in budget.
    """
    pts = np.asarray(points, dtype=np.float64)
    keep = [0, len(pts) - 1]
    while len(keep) - 1 < max_segments:
        worst, worst_at = 0.0, -1
        for lo, hi in zip(keep[:-1], keep[1:], strict=True):
            if hi - lo < 2:
                continue
            d = distance_to_polyline(pts[lo + 1 : hi], pts[[lo, hi]])
            k = int(np.argmax(d))
            if d[k] > worst:
                worst, worst_at = float(d[k]), lo + 1 + k
        if worst <= tolerance:
            break
        keep = sorted(keep + [worst_at])
    return np.asarray(keep)


# -- body -----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MugBody:
    """The body of revolution: a tapered cup with a foot fillet, a floor and a rim lip.

    ``wall`` is measured horizontally. ``rim_size`` is the rim rounding radius (plain), the
    bead's outward bulge (bead) or the flare's outward offset at the top (flared);
    ``lip_height`` is the flare's height (flared only).
    """

    r_bottom: float
    r_top: float
    height: float
    wall: float
    bottom: float
    foot_radius: float
    floor_radius: float
    rim: str
    rim_size: float
    lip_height: float

    def __post_init__(self) -> None:
        if self.rim not in RIMS:
            raise InvalidParameterError(f"rim must be one of {RIMS}, got {self.rim!r}")
        if min(self.r_bottom, self.r_top, self.height, self.wall, self.bottom) <= 0:
            raise InvalidParameterError(
                "mug body sizes must be positive: got "
                f"r_bottom={self.r_bottom}, r_top={self.r_top}, height={self.height}, "
                f"wall={self.wall}, bottom={self.bottom}"
            )
        if self.r_top - self.wall < 0.008 or self.r_bottom - self.wall < 0.008:
            raise InvalidParameterError(
                f"the cavity needs an inner radius >= 8 mm; got radii {self.r_bottom:.4f}/{self.r_top:.4f} m "
                f"with wall {self.wall:.4f} m: use a thinner wall or a wider body"
            )
        if self.rim == "bead" and self.rim_size >= self.wall:
            raise InvalidParameterError(
                f"a bead rim's bulge must be < wall ({self.wall}), got {self.rim_size}"
            )

    # Straight outer wall line; the rim lip and the foot fillet are added in the profile.
    @property
    def slope(self) -> float:
        return (self.r_top - self.r_bottom) / self.height

    def r_out(self, z: np.ndarray | float) -> np.ndarray | float:
        return self.r_bottom + self.slope * z

    def r_in(self, z: np.ndarray | float) -> np.ndarray | float:
        return self.r_out(z) - self.wall

    def r_mid(self, z: np.ndarray | float) -> np.ndarray | float:
        return self.r_out(z) - self.wall / 2

    # The bead is a circle touching the inner wall line with its top at the rim height.
    @property
    def _bead_radius(self) -> float:
        return (self.wall + self.rim_size) / 2

    @property
    def _bead_centre(self) -> tuple[float, float]:
        cz = self.height - self._bead_radius
        return float(self.r_in(cz)) + self._bead_radius, cz

    def _bead_start(self) -> float:
        """Height offset (below the bead centre, negative) where the outer wall meets the bead."""
        rb, s = self._bead_radius, self.slope
        q = self.wall - rb  # outer wall's distance from the centre, at the centre's height
        disc = (q * s) ** 2 - (1 + s * s) * (q * q - rb * rb)
        return float((-q * s - np.sqrt(disc)) / (1 + s * s))

    @property
    def rim_outer_radius(self) -> float:
        if self.rim == "bead":
            return self._bead_centre[0] + self._bead_radius
        if self.rim == "flared":
            return float(self.r_out(self.height)) + self.rim_size
        return float(self.r_out(self.height))

    @property
    def max_outer_radius(self) -> float:
        """The body's largest radius, rim lip and corner rounding included."""
        return float(self.profile()[:, 0].max())

    @property
    def lip_bottom(self) -> float:
        """Height where the rim lip starts (the handle must stay below it)."""
        if self.rim == "bead":
            return self._bead_centre[1] + self._bead_start()
        if self.rim == "flared":
            return self.height - self.lip_height
        return self.height - self.rim_size

    def profile(self) -> np.ndarray:
        """Closed (r, z) polygon, counter-clockwise, ready for :func:`meshing.revolve_profile`."""
        h, w = self.height, self.wall
        pts: list[tuple[float, float]] = [(0.0, 0.0), (self.r_bottom, 0.0)]
        radii: list[float] = [0.0, self.foot_radius]
        if self.rim == "plain":
            pts += [(float(self.r_out(h)), h), (float(self.r_in(h)), h)]
            radii += [self.rim_size, self.rim_size]
        elif self.rim == "flared":
            z_l = h - self.lip_height
            t = np.linspace(0.0, 1.0, 9)
            z = z_l + t * self.lip_height
            bulge = self.rim_size * t**2
            outer = np.column_stack([self.r_out(z) + bulge, z])
            inner = np.column_stack([self.r_in(z) + bulge, z])[::-1]
            corner = min(0.35 * w, 0.0025)
            pts += [tuple(p) for p in outer] + [tuple(p) for p in inner]
            radii += [0.0] * 8 + [corner, corner] + [0.0] * 8
        else:  # bead: the outer wall runs into a round lip that ends on the inner wall
            cr, cz = self._bead_centre
            rb = self._bead_radius
            dz = self._bead_start()
            a0 = np.arctan2(dz, float(self.r_out(cz + dz)) - cr)
            # Sample the crown (pi / 2) exactly so the rim top sits at the nominal height.
            n_low = max(4, int(np.ceil((np.pi / 2 - a0) / _ARC_STEP)) + 1)
            n_high = max(4, int(np.ceil((np.pi / 2) / _ARC_STEP)) + 1)
            angles = np.concatenate(
                [np.linspace(a0, np.pi / 2, n_low), np.linspace(np.pi / 2, np.pi, n_high)[1:]]
            )
            arc = np.column_stack([cr + rb * np.cos(angles), cz + rb * np.sin(angles)])
            pts += [tuple(p) for p in arc]
            radii += [0.0] * len(arc)
        pts += [(float(self.r_in(self.bottom)), self.bottom), (0.0, self.bottom)]
        radii += [self.floor_radius, 0.0]
        return fillet_polyline(np.array(pts), np.array(radii), closed=True)

    def wall_bands(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Stacked wall bands for the convex collision wedges, bottom first.

        Each band is (z, r_inner, r_outer) per band edge, as :func:`meshing.ring_wall_parts`
        takes them. Consecutive bands share their boundary height and inner radius, so the
        stack is closed; the outer radius may step out where the rim lip starts.
        """
        h = self.height
        if self.rim == "plain":
            z = np.array([0.0, h])
            return [(z, self.r_in(z), self.r_out(z))]
        if self.rim == "flared":
            z = np.array([0.0, h - self.lip_height, h])
            bulge = np.array([0.0, 0.0, self.rim_size])
            return [(z, self.r_in(z) + bulge, self.r_out(z) + bulge)]
        # Bead: the straight wall up to where the bead starts, then one band holding the bead's
        # widest circle; its top stops short of the crown so the corners hug the round lip.
        cr, cz = self._bead_centre
        rb = self._bead_radius
        z_b = cz + self._bead_start()
        wall_z = np.array([0.0, z_b])
        wall = (wall_z, self.r_in(wall_z), self.r_out(wall_z))
        lip_z = np.array([z_b, cz + 0.6 * rb])
        lip = (lip_z, np.array([float(self.r_in(z_b)), cr - rb]), np.array([cr + rb, cr + rb]))
        return [wall, lip]


# -- handle ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class HandleShape:
    """A handle in the x-z plane, built around the outer bar's middle at height ``z_grasp``.

    ``size`` is the outer bar's half length (the circle radius for "round"); ``gap`` the clear
    gap in x between the body's outer wall and the bar's inner side at ``z_grasp``;
    ``corner`` the inner corner radius; ``bow`` how far the bar's ends sit back from its
    middle (angular, ear); ``neck`` the half span of the attachment on the wall (angular: as a
    fraction of ``size``; ear: in metres); ``offset`` the height of the ear's attachment
    centre above the loop's middle (metres; small, so that the two attachments stay on either
    side of the grasp height and the gap in front of the bar is clear).
    """

    style: str
    half_depth: float
    half_width: float
    gap: float
    size: float
    corner: float
    bow: float
    neck: float
    offset: float
    z_grasp: float

    def __post_init__(self) -> None:
        if self.style not in HANDLE_STYLES:
            raise InvalidParameterError(f"handle style must be one of {HANDLE_STYLES}, got {self.style!r}")
        if min(self.half_depth, self.half_width, self.gap, self.size) <= 0:
            raise InvalidParameterError(
                "handle sizes must be positive: got "
                f"half_depth={self.half_depth}, half_width={self.half_width}, "
                f"gap={self.gap}, size={self.size}"
            )

    def bar_x(self, body: MugBody) -> float:
        """x of the outer bar's centreline at the grasp height."""
        return float(body.r_out(self.z_grasp)) + self.gap + self.half_depth

    def centreline(self, body: MugBody) -> np.ndarray:
        """Dense (x, z) centreline from the upper attachment (inside the wall) to the lower one."""
        if self.style == "round":
            return self._round(body)
        return self._polygon(body)

    def _wall_point(self, body: MugBody, z: float) -> np.ndarray:
        # Tube ends stop in the middle of the wall, so they merge into it without reaching
        # the cavity.
        return np.array([float(body.r_mid(z)), z])

    def _round(self, body: MugBody) -> np.ndarray:
        rho, zg = self.size, self.z_grasp
        xc = self.bar_x(body) - rho
        d0 = float(body.r_mid(zg)) - xc
        s = body.slope
        # Where the circle meets the wall's mid line x = r_mid(zg) + s (z - zg).
        disc = (d0 * s) ** 2 - (1 + s * s) * (d0 * d0 - rho * rho)
        if disc <= 0:
            raise InvalidParameterError(
                f"round handle of radius {rho:.4f} m does not reach the wall; use a larger size or gap"
            )
        roots = [(-d0 * s + sign * np.sqrt(disc)) / (1 + s * s) for sign in (1.0, -1.0)]
        a_top = np.arctan2(roots[0], d0 + s * roots[0])
        a_bot = np.arctan2(roots[1], d0 + s * roots[1])
        count = max(8, int(np.ceil((a_top - a_bot) / _ARC_STEP)) + 1)
        angles = np.linspace(a_top, a_bot, count)
        return np.column_stack([xc + rho * np.cos(angles), zg + rho * np.sin(angles)])

    def _polygon(self, body: MugBody) -> np.ndarray:
        hd, b, zg, x = self.half_depth, self.size, self.z_grasp, self.bar_x(body)
        if self.style in ("square", "d"):
            top, bottom = zg + b, zg - b
            bar = [(x, top), (x, bottom)]
            bar_radii = [hd + self.corner, hd + self.corner]
        else:
            if self.style == "angular":
                top, bottom = zg + self.neck * b, zg - self.neck * b
            else:  # ear: narrow neck set above the loop's middle
                z_a = zg + self.offset
                top, bottom = z_a + self.neck, z_a - self.neck
            # The bar bends outward at its middle ("<" seen from the body); the apex fillet
            # spans about a third of each half so the bar's outermost point is at z_grasp.
            apex_radius = 0.35 * b * b / max(self.bow, 1e-6)
            bar = [(x - self.bow, zg + b), (x, zg), (x - self.bow, zg - b)]
            bar_radii = [hd + self.corner, apex_radius, hd + self.corner]
        upper, lower = self._wall_point(body, top), self._wall_point(body, bottom)
        if self.style in ("square", "d"):  # horizontal bars already leave the wall square on
            pts = [tuple(upper), *bar, tuple(lower)]
            radii = [0.0, *bar_radii, 0.0]
        else:  # slanted bars: leave the wall horizontally through a short stub, then turn
            stub_top = float(body.r_out(top)) + hd + 0.002
            stub_bottom = float(body.r_out(bottom)) + hd + 0.002
            pts = [tuple(upper), (stub_top, top), *bar, (stub_bottom, bottom), tuple(lower)]
            turn_radius = hd + max(self.corner, 0.002)
            radii = [0.0, turn_radius, *bar_radii, turn_radius, 0.0]
        return fillet_polyline(np.array(pts), np.array(radii))

    # -- derived quantities -------------------------------------------------------------------
    def z_range(self, body: MugBody) -> tuple[float, float]:
        """Lowest and highest z of the handle solid."""
        path = self.centreline(body)
        return float(path[:, 1].min() - self.half_depth), float(path[:, 1].max() + self.half_depth)

    def grasp_point(self, body: MugBody) -> np.ndarray:
        """The centreline point farthest from the axis; the middle of a straight bar."""
        return _farthest_point(self.centreline(body))

    def opening_clear_height(self, body: MugBody) -> float:
        """Clear z height of the opening where a finger passes, just inside the outer bar."""
        path = self.centreline(body)
        gx, gz = _farthest_point(path)
        lo, hi = tube_on_vertical_line(path, self.half_depth, gx - self.half_depth - FINGER_INSET)
        if np.any((lo <= gz) & (hi >= gz)):
            return 0.0
        above = lo[lo > gz] - gz
        below = gz - hi[hi < gz]
        return float(min(above.min(initial=0.15), 0.15) + min(below.min(initial=0.15), 0.15))

    def reach(self, body: MugBody) -> float:
        """Max x of the handle solid minus the body's outer radius at the grasp height."""
        gx, gz = self.grasp_point(body)
        return float(gx + self.half_depth - body.r_out(gz))


def _farthest_point(path: np.ndarray) -> np.ndarray:
    # Points tied for the largest x form a straight vertical bar: take its middle.
    far = path[path[:, 0] >= path[:, 0].max() - 1e-7]
    return far.mean(axis=0)


def tube_on_vertical_line(path: np.ndarray, radius: float, x: float) -> tuple[np.ndarray, np.ndarray]:
    """Where the line x = const crosses the band of points within ``radius`` of a 2D polyline.

    The band is the union of one capsule per segment; a capsule is convex, so it meets the line
    in one interval: the hull of the intervals cut by its two end discs and its middle strip.
    Returns per-segment (lo, hi) z arrays; segments that miss the line get lo > hi.
    """
    a, b = path[:-1], path[1:]
    ab = b - a
    length = np.maximum(np.linalg.norm(ab, axis=1), 1e-12)
    los, his = [], []
    for end in (a, b):  # the end discs
        dx = x - end[:, 0]
        h = np.sqrt(np.maximum(radius**2 - dx**2, 0.0))
        hit = np.abs(dx) <= radius
        los.append(np.where(hit, end[:, 1] - h, np.inf))
        his.append(np.where(hit, end[:, 1] + h, -np.inf))
    # The strip: 0 <= t(z) <= 1 along the segment and |s(z)| <= radius across it, both linear in z.
    dx = x - a[:, 0]
    lo, hi = np.full(len(a), -np.inf), np.full(len(a), np.inf)
    for c0, c1, bound_lo, bound_hi in (
        (dx * ab[:, 0] / length**2, ab[:, 1] / length**2, 0.0, 1.0),  # t = c0 + c1 (z - a_z)
        (-dx * ab[:, 1] / length, ab[:, 0] / length, -radius, radius),  # s = c0 + c1 (z - a_z)
    ):
        with np.errstate(divide="ignore", invalid="ignore"):
            z0 = (bound_lo - c0) / c1
            z1 = (bound_hi - c0) / c1
        flat = np.abs(c1) < 1e-12
        inside = (c0 >= bound_lo) & (c0 <= bound_hi)
        zl = np.where(flat, np.where(inside, -np.inf, np.inf), np.minimum(z0, z1))
        zh = np.where(flat, np.where(inside, np.inf, -np.inf), np.maximum(z0, z1))
        lo, hi = np.maximum(lo, zl + a[:, 1]), np.minimum(hi, zh + a[:, 1])
    strip = lo <= hi
    los.append(np.where(strip, lo, np.inf))
    his.append(np.where(strip, hi, -np.inf))
    return np.min(los, axis=0), np.max(his, axis=0)
