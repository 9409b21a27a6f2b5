"""Procedural mugs: a tapered cup of revolution with a rim lip and one of five handle styles.

Canonical frame: origin at the centre of the base plane (z = 0, the plane the mug stands on),
+z up the body axis toward the opening, +x toward the handle; the handle lies in the x-z plane,
symmetric about y = 0.

Anchors (scale 1):
  - ``handle_grasp``: the handle centreline point farthest from the axis (middle of the outer bar).
  - ``grasp_approach``: (0, -1, 0): one finger passes through the opening, the jaw closes along x.
  - ``handle_center``: arc-length centroid of the handle centreline (inside the opening).
  - ``pour_point``: (-(rim outer radius - wall / 2), 0, rim top), opposite the handle.
  - ``opening_center``: (0, 0, rim top).
  - ``bottom_center``: (0, 0, 0).

Functional constraints held by every sample (checked in tests/objects/test_mug.py): a clear
gap >= 20 mm in x between the body and the outer bar's inner side at the grasp height, a clear
opening >= 25 mm tall where a finger passes (5 mm inside the bar), an outer bar <= 16 mm thick
in x, the handle between base and rim, an overall x extent <= 200 mm, and a closed cavity.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError

from keygen.errors import InvalidParameterError
from keygen.objects import meshing
from keygen.objects.asset import Anchor, Asset, ConvexPart, MassProperties
from keygen.objects.generators._mug_parts import (
    HANDLE_STYLES,
    RIMS,
    HandleShape,
    MugBody,
    polyline_centroid,
    resample_polyline,
    simplify_polyline,
)
from keygen.objects.generators.base import CategoryGenerator

# Functional targets, with margins over the documented limits (20 mm gap, 25 mm opening).
_MIN_GAP = 0.0225
_MIN_OPENING = 0.027
_MAX_OVERALL_X = 0.195  # the limit is 200 mm; 5 mm spare for the polygonal meshes
_BASE_MARGIN = 0.004  # lowest handle point above the base
_RIM_MARGIN = 0.003  # highest handle point below the rim lip

# Collision budget: wall wedges (bands x segments) + floor + handle hulls <= 50.
_MAX_WALL_SEGMENTS = 16
_MAX_HANDLE_PARTS = 14
_RING_SIDES = 12
_TUBE_SIDES = 16
_BODY_SECTIONS = 64

_PARAM_KEYS = (
    "style",
    "rim",
    "radius_bottom",
    "taper",
    "height",
    "wall",
    "bottom",
    "foot_radius",
    "floor_radius",
    "rim_size",
    "lip_height",
    "density",
    "handle_half_depth",
    "handle_half_width",
    "handle_gap",
    "handle_size",
    "handle_corner",
    "handle_bow",
    "handle_neck",
    "handle_offset",
    "handle_z",
)


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def body_from_params(params: dict[str, Any]) -> MugBody:
    return MugBody(
        r_bottom=float(params["radius_bottom"]),
        r_top=float(params["radius_bottom"]) * float(params["taper"]),
        height=float(params["height"]),
        wall=float(params["wall"]),
        bottom=float(params["bottom"]),
        foot_radius=float(params["foot_radius"]),
        floor_radius=float(params["floor_radius"]),
        rim=str(params["rim"]),
        rim_size=float(params["rim_size"]),
        lip_height=float(params["lip_height"]),
    )


def handle_from_params(params: dict[str, Any]) -> HandleShape:
    return HandleShape(
        style=str(params["style"]),
        half_depth=float(params["handle_half_depth"]),
        half_width=float(params["handle_half_width"]),
        gap=float(params["handle_gap"]),
        size=float(params["handle_size"]),
        corner=float(params["handle_corner"]),
        bow=float(params["handle_bow"]),
        neck=float(params["handle_neck"]),
        offset=float(params["handle_offset"]),
        z_grasp=float(params["handle_z"]),
    )


def handle_room(body: MugBody) -> tuple[float, float]:
    """The z interval the handle solid must stay in: above the base, below the rim lip."""
    return max(_BASE_MARGIN, body.foot_radius + 0.002), body.lip_bottom - _RIM_MARGIN


class MugGenerator(CategoryGenerator):
    category = "mug"
    styles = HANDLE_STYLES

    # -- sampling ---------------------------------------------------------------------------------
    def sample_params(self, rng: np.random.Generator, style: str | None = None) -> dict[str, Any]:
        if style is None:
            style = self.styles[int(rng.integers(len(self.styles)))]
        if style not in self.styles:
            raise InvalidParameterError(f"mug style must be one of {self.styles}, got {style!r}")
        body_params = self._sample_body(rng)
        handle = self._sample_handle_shape(rng, style, body_from_params(body_params))
        params: dict[str, Any] = {"style": style, **body_params}
        params.update(self._fit_handle(rng, handle, params))
        return params

    def _sample_body(self, rng: np.random.Generator) -> dict[str, Any]:
        rim = RIMS[int(rng.integers(len(RIMS)))]
        wall = rng.uniform(0.003, 0.007)
        if rim == "plain":
            rim_size, lip_height = min(rng.uniform(0.25, 0.4) * wall, 0.0025), 0.0
        elif rim == "bead":
            rim_size, lip_height = rng.uniform(0.001, min(0.0025, 0.6 * wall)), 0.0
        else:
            rim_size, lip_height = rng.uniform(0.002, 0.006), rng.uniform(0.006, 0.014)
        return {
            "rim": rim,
            "radius_bottom": _log_uniform(rng, 0.030, 0.055),
            "taper": float(rng.uniform(0.8, 1.3)),
            "height": _log_uniform(rng, 0.065, 0.125),
            "wall": float(wall),
            "bottom": float(rng.uniform(max(0.004, wall), 0.012)),
            "foot_radius": float(rng.uniform(0.001, 0.003)),
            "floor_radius": float(rng.uniform(0.002, 0.006)),
            "rim_size": float(rim_size),
            "lip_height": float(lip_height),
            "density": float(rng.uniform(2000.0, 2400.0)),
        }

    def _sample_handle_shape(self, rng: np.random.Generator, style: str, body: MugBody) -> HandleShape:
        """Everything about the handle but its size and height, which are fitted afterwards."""
        hd = rng.uniform(0.003, 0.005 if style == "ear" else 0.0065)
        hw = rng.uniform(max(0.003, hd - 0.002), min(0.007, hd + 0.0025))
        gap = _log_uniform(rng, _MIN_GAP, 0.036 if style == "round" else 0.046)
        # Keep the whole mug within 200 mm in x (body on one side, handle on the other).
        gap = min(gap, _MAX_OVERALL_X - 2 * body.max_outer_radius - 2 * hd - 0.001)
        corner = bow = neck = offset = 0.0
        if style == "square":
            corner = rng.uniform(0.001, 0.003)
        elif style == "d":
            corner = rng.uniform(0.006, 0.012)
        elif style == "angular":
            corner, bow = rng.uniform(0.001, 0.003), rng.uniform(0.0015, 0.004)
            # Either narrower at the wall than at the bar (a "<" loop) or wider (a trapezoid).
            neck = rng.uniform(0.55, 0.8) if rng.uniform() < 0.5 else rng.uniform(1.15, 1.4)
        elif style == "ear":
            # A narrow neck (a teardrop loop), shifted up or down a little: both attachments
            # must stay on either side of the grasp height to keep the gap in front of the bar.
            corner, bow = rng.uniform(0.005, 0.010), rng.uniform(0.001, 0.003)
            clearance = rng.uniform(0.004, 0.009)  # between the two attachment tubes
            neck = hd + clearance
            offset = rng.uniform(-1.0, 1.0) * max(clearance - 0.002, 0.0)
        return HandleShape(style, hd, hw, gap, 0.03, corner, bow, neck, offset, body.height / 2)

    def _fit_handle(self, rng: np.random.Generator, shape: HandleShape, params: dict[str, Any]) -> dict:
        """Size and place the handle: open enough for a finger, within the room on the body.

        The smallest size giving the required opening is found by bisection. If even that does
        not fit between base and rim, the mug is made taller (a dependent value is re-derived;
        a bounded number of rounds, no rejection loop).
        """
        for _ in range(4):
            body = body_from_params(params)
            size_min = _smallest_open_size(shape, body)
            z_lo, z_hi = handle_room(body)
            deficit = _extent(_with(shape, size=size_min), body) - (z_hi - z_lo)
            if deficit <= 0:
                break
            params["height"] = float(params["height"] + deficit + 0.001)
        body = body_from_params(params)
        z_lo, z_hi = handle_room(body)
        # Real handles span about half to most of the body; never more than the room.
        room = max(min(z_hi - z_lo, 0.8 * body.height), _extent(_with(shape, size=size_min), body))
        hi_size = _size_search_range(shape, body)[1]
        size_max = _bisect(lambda s: _extent(_with(shape, size=s), body) > room, size_min, hi_size)
        size = float(size_min + rng.uniform() * (size_max - size_min))
        fitted = _with(shape, size=size)
        below, above = (v - fitted.z_grasp for v in fitted.z_range(body))
        z_grasp = rng.uniform(z_lo - below, max(z_lo - below, z_hi - above))
        return {
            "handle_half_depth": float(shape.half_depth),
            "handle_half_width": float(shape.half_width),
            "handle_gap": float(shape.gap),
            "handle_size": size,
            "handle_corner": float(shape.corner),
            "handle_bow": float(shape.bow),
            "handle_neck": float(shape.neck),
            "handle_offset": float(shape.offset),
            "handle_z": float(z_grasp),
        }

    # -- building ---------------------------------------------------------------------------------
    def build(self, params: dict[str, Any], instance_id: str) -> Asset:
        _check_params(params)
        body, handle = body_from_params(params), handle_from_params(params)
        path = resample_polyline(handle.centreline(body), 0.002)
        path3 = np.column_stack([path[:, 0], np.zeros(len(path)), path[:, 1]])
        body_mesh = meshing.revolve_profile(body.profile(), sections=_BODY_SECTIONS)
        tube = meshing.sweep_tube(path3, handle.half_width, handle.half_depth, sides=_TUBE_SIDES)
        visual = meshing.union([body_mesh, tube])
        return Asset(
            category="mug",
            instance_id=instance_id,
            visual=visual,
            collision=_collision_parts(body, handle, path),
            mass_properties=MassProperties.from_mesh(visual, float(params["density"])),
            anchors=_anchors(body, handle, path),
            params=dict(params),
            scale=1.0,
            source="procedural",
        )

    def main_dimensions(self, params: dict[str, Any]) -> dict[str, float]:
        _check_params(params)
        body, handle = body_from_params(params), handle_from_params(params)
        z0, z1 = handle.z_range(body)
        return {
            "height": body.height,
            "body_diameter": 2 * body.max_outer_radius,
            "handle_reach": handle.reach(body),
            "handle_height": z1 - z0,
        }

    # -- checks -----------------------------------------------------------------------------------
    def validate_anchors(self, asset: Asset) -> list[str]:
        """Check each anchor against the asset's own meshes (any scale, generated or imported)."""
        anchors = asset.require_anchors()
        mesh = asset.visual
        mm = 1e-3 * asset.scale
        lo, hi = mesh.bounds
        problems: list[str] = []

        # bottom_center: the mesh stands on z = 0 and the point lies in its footprint.
        p = anchors["bottom_center"].value
        if abs(lo[2]) > 1 * mm:
            problems.append(
                f"mesh min z should be 0 (+-1 mm at scale 1), got {lo[2]:.5f} m: re-centre the mesh"
            )
        if abs(p[2] - lo[2]) > 1 * mm or not _in_footprint(mesh, p[:2], 1 * mm):
            problems.append(f"bottom_center {p.round(4).tolist()} is not on the base inside its footprint")

        # opening_center: on the axis at the rim top, with air just below it (open cavity).
        p = anchors["opening_center"].value
        if abs(p[2] - hi[2]) > 5 * mm or np.hypot(p[0], p[1]) > 5 * mm:
            problems.append(
                f"opening_center {p.round(4).tolist()} should be (0, 0, rim top {hi[2]:.4f}) within 5 mm"
            )
        elif mesh.contains([p - [0.0, 0.0, 3 * mm]])[0]:
            problems.append("opening_center has material just below it: the mug should be open at the top")

        # pour_point: on the rim top, on the side opposite the handle.
        p = anchors["pour_point"].value
        surface_gap = float(trimesh.proximity.closest_point(mesh, [p])[1][0])
        if surface_gap > 5 * mm:
            problems.append(
                f"pour_point is {surface_gap * 1e3:.1f} mm from the mesh surface (max 5 mm at scale 1)"
            )
        if p[0] >= 0 or abs(p[1]) > 5 * mm or abs(p[2] - hi[2]) > 5 * mm:
            problems.append(
                f"pour_point {p.round(4).tolist()} should be on the rim top at -x, opposite the handle"
            )

        # handle_grasp: on the handle's outer bar, well clear of the body wall.
        p = anchors["handle_grasp"].value
        dist = float(meshing.distance_to_solid(mesh, p)[0])
        if dist > 5 * mm:
            problems.append(
                f"handle_grasp is {dist * 1e3:.1f} mm from the handle solid (max 5 mm at scale 1)"
            )
        body_r = _body_radius(mesh, p[2])
        if body_r is None or p[0] <= body_r + 15 * mm:
            problems.append(
                f"handle_grasp x={p[0]:.4f} should exceed the body radius at its height "
                f"({body_r}) by 15 mm (scale 1)"
            )
        if abs(p[1]) > 5 * mm or p[0] < hi[0] - 13 * mm:
            problems.append(f"handle_grasp {p.round(4).tolist()} should be on the outermost bar, at y = 0")

        # handle_center: in the opening: air, between body and bar, with handle above and below.
        c = anchors["handle_center"].value
        if mesh.contains([c])[0]:
            problems.append("handle_center lies inside material; it should be in the handle's opening")
        elif not (len(_ray_hits(mesh, c, [0, 0, 1])) and len(_ray_hits(mesh, c, [0, 0, -1]))):
            problems.append("handle_center is not enclosed by the handle above and below")
        between = body_r is not None and body_r < c[0] < p[0]
        if not between or abs(c[1]) > 5 * mm:
            problems.append(
                f"handle_center {c.round(4).tolist()} should lie between the body wall and handle_grasp"
            )

        # grasp_approach: along -y (or +y), across the handle's plane.
        d = anchors["grasp_approach"].value
        if abs(d[1]) < np.cos(np.deg2rad(15)):
            problems.append(f"grasp_approach {d.round(3).tolist()} should be along -y (0, -1, 0)")
        return problems


# -- helpers ----------------------------------------------------------------------------------------
def _with(shape: HandleShape, **changes: Any) -> HandleShape:
    values = {k: getattr(shape, k) for k in shape.__dataclass_fields__}
    values.update(changes)
    return HandleShape(**values)


def _extent(shape: HandleShape, body: MugBody) -> float:
    z0, z1 = shape.z_range(body)
    return z1 - z0


def _size_search_range(shape: HandleShape, body: MugBody) -> tuple[float, float]:
    """Sizes worth searching: the loop must be a real loop and (round) meet the wall squarely."""
    hd = shape.half_depth
    if shape.style == "round":
        # Distance from the wall's mid line to the bar; the circle's centre stays within 30 %
        # of its radius from the wall so its ends enter the wall nearly square.
        reach = shape.gap + hd + body.wall / 2
        return reach / 1.3, reach / 0.7
    lo = hd + 0.008
    if shape.style == "angular":
        lo = max(lo, (hd + 0.004) / shape.neck)  # the wall attachments must not touch
    return lo, 0.07


def _smallest_open_size(shape: HandleShape, body: MugBody) -> float:
    """The smallest handle size whose opening lets a finger through."""
    lo, hi = _size_search_range(shape, body)
    return _bisect(lambda s: _with(shape, size=s).opening_clear_height(body) >= _MIN_OPENING, lo, hi)


def _bisect(ok: Any, lo: float, hi: float, iterations: int = 24) -> float:
    """Smallest x in [lo, hi] with ok(x) (ok monotone false -> true); hi if none."""
    if ok(lo):
        return lo
    if not ok(hi):
        return hi
    for _ in range(iterations):
        mid = (lo + hi) / 2
        lo, hi = (lo, mid) if ok(mid) else (mid, hi)
    return hi


def _check_params(params: dict[str, Any]) -> None:
    missing = [k for k in _PARAM_KEYS if k not in params]
    if missing:
        raise InvalidParameterError(
            f"mug params lack {missing}; draw them with MugGenerator().sample_params(rng)"
        )


def _collision_parts(body: MugBody, handle: HandleShape, path: np.ndarray) -> list[ConvexPart]:
    # Wedges fine enough that the polygon stays within 1.5 mm of the round wall.
    r_max = body.max_outer_radius
    segments = int(np.clip(np.ceil(np.pi / np.arccos(1 - 0.0015 / r_max)), 12, _MAX_WALL_SEGMENTS))
    parts: list[ConvexPart] = []
    for z, r_in, r_out in body.wall_bands():
        parts += meshing.ring_wall_parts(z, r_in, r_out, segments)
    # The floor reaches into the middle of the wall so that floor and wall overlap all round.
    floor_radius = float(max(body.r_mid(0.0), body.r_mid(body.bottom)))
    parts.append(meshing.disc_part(floor_radius, 0.0, body.bottom))
    return meshing.with_label(parts, "body") + meshing.with_label(_handle_hulls(handle, path), "handle")


def _handle_hulls(handle: HandleShape, path: np.ndarray) -> list[ConvexPart]:
    """Convex hulls of consecutive tube sections along a simplified centreline."""
    keep = simplify_polyline(path, 0.0008, _MAX_HANDLE_PARTS)
    tangents = np.gradient(path, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    angles = np.linspace(0, 2 * np.pi, _RING_SIDES, endpoint=False)
    grow = 1 / np.cos(np.pi / _RING_SIDES)  # circumscribe the elliptical section
    rings = []
    for i in keep:
        tx, tz = tangents[i]
        normal = np.array([-tz, 0.0, tx])
        centre = np.array([path[i, 0], 0.0, path[i, 1]])
        ring = (
            centre
            + grow * handle.half_depth * np.outer(np.cos(angles), normal)
            + grow * handle.half_width * np.outer(np.sin(angles), [0.0, 1.0, 0.0])
        )
        rings.append(ring)
    return [meshing.hull_part(np.vstack([a, b])) for a, b in zip(rings[:-1], rings[1:], strict=True)]


def _anchors(body: MugBody, handle: HandleShape, path: np.ndarray) -> dict[str, Anchor]:
    gx, gz = handle.grasp_point(body)
    cx, cz = polyline_centroid(path)
    top = body.height
    return {
        "handle_grasp": Anchor("point", np.array([gx, 0.0, gz])),
        "grasp_approach": Anchor("direction", np.array([0.0, -1.0, 0.0])),
        "handle_center": Anchor("point", np.array([cx, 0.0, cz])),
        "pour_point": Anchor("point", np.array([-(body.rim_outer_radius - body.wall / 2), 0.0, top])),
        "opening_center": Anchor("point", np.array([0.0, 0.0, top])),
        "bottom_center": Anchor("point", np.zeros(3)),
    }


def _ray_hits(mesh: trimesh.Trimesh, origin: np.ndarray, direction: Any) -> np.ndarray:
    """Hit points of one ray, sorted by distance from the origin."""
    locations, _, _ = mesh.ray.intersects_location([origin], [np.asarray(direction, dtype=np.float64)])
    locations = np.asarray(locations, dtype=np.float64).reshape(-1, 3)
    order = np.argsort(np.linalg.norm(locations - origin, axis=1))
    return locations[order]


def _body_radius(mesh: trimesh.Trimesh, z: float) -> float | None:
    """Outer radius of the body at height z, from rays along +-y (the handle lies at y = 0)."""
    radii = []
    for sign in (1.0, -1.0):
        hits = _ray_hits(mesh, np.array([0.0, 0.0, z]), [0.0, sign, 0.0])
        if len(hits):
            radii.append(float(np.abs(hits[:, 1]).max()))
    return max(radii) if radii else None


def _in_footprint(mesh: trimesh.Trimesh, xy: np.ndarray, tol: float) -> bool:
    """Whether xy lies in the convex hull of the vertices touching the base plane."""
    v = mesh.vertices
    low = v[v[:, 2] <= v[:, 2].min() + tol][:, :2]
    if len(low) < 3:
        return False
    try:
        hull = ConvexHull(low)
    except QhullError:  # degenerate contact (a line or a point): no footprint to stand on
        return False
    return bool(np.all(hull.equations[:, :2] @ xy + hull.equations[:, 2] <= tol))
