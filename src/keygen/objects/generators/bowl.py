"""Procedural bowls: a solid of revolution with a hollow cavity, optional foot ring and rim bead.

Canonical frame: origin at the centre of the base plane (the plane the bowl rests on, z = 0),
+z up along the axis of symmetry; +x is the side of the rim grasp anchor.

Styles are wall profiles of the cavity: ``hemispherical`` and ``deep`` (elliptic, on a foot),
``rounded_flat`` (a wide floor with rounded corners), ``flat_bottomed`` (near-vertical straight
walls) and ``conical`` (sloped straight walls). The outer surface is the cavity curve offset by
the wall thickness, so every style gets an even wall.

Anchors:
  - ``rim_grasp`` (point): +x side, mid-wall, 8 mm under the rim top (rim top for shallow bowls).
  - ``opening_center`` (point): (0, 0, rim top height).
  - ``bottom_center`` (point): (0, 0, 0).
  - ``rim_radius`` (scalar): outer radius at the rim top (including a bead).
  - ``inner_bottom_center`` (point, extra): (0, 0, height of the inner bottom), for stacking.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from keygen.errors import InvalidParameterError
from keygen.objects.asset import Anchor, Asset, MassProperties
from keygen.objects.generators import _bowl_parts as parts
from keygen.objects.generators.base import CategoryGenerator
from keygen.objects.meshing import distance_to_solid, revolve_profile, union, with_label

SECTIONS = 64  # angular resolution of the visual mesh
COLLISION_BUDGET = 96
GRASP_BELOW_RIM = 0.008
MAX_RIM_THICKNESS = 0.0095  # horizontal wall width near the rim, under the 10 mm pinch limit
GRASP_ZONE = 0.016  # height under the rim where the pinch limit applies
MM = 1e-3


@dataclass(frozen=True)
class _Style:
    curve: str  # "superellipse" or "cone"
    radius: tuple[float, float]  # outer rim radius range (log-uniform)
    depth_ratio: tuple[float, float]  # cavity depth / inner rim radius
    foot_probability: float
    flat: tuple[float, float] = (0.0, 0.0)  # superellipse: floor radius / inner rim radius
    exponent: tuple[float, float] = (2.0, 2.0)  # superellipse: 2 = ellipse, larger = squarer
    flare_deg: tuple[float, float] = (90.0, 90.0)  # superellipse: 90 = vertical rim, less = flared
    wall_deg: tuple[float, float] = (60.0, 60.0)  # cone: wall angle from horizontal
    fillet: tuple[float, float] = (0.005, 0.01)  # cone: corner radius (m)


_STYLES: dict[str, _Style] = {
    "hemispherical": _Style(
        "superellipse",
        (0.05, 0.10),
        (0.6, 0.95),
        1.0,
        flat=(0.0, 0.12),
        exponent=(1.8, 2.3),
        flare_deg=(75, 90),
    ),
    "deep": _Style(
        "superellipse",
        (0.05, 0.085),
        (0.9, 1.3),
        0.7,
        flat=(0.2, 0.4),
        exponent=(2.2, 3.2),
        flare_deg=(78, 90),
    ),
    "rounded_flat": _Style(
        "superellipse",
        (0.06, 0.115),
        (0.35, 0.65),
        0.4,
        flat=(0.3, 0.55),
        exponent=(2.3, 3.5),
        flare_deg=(60, 85),
    ),
    "flat_bottomed": _Style("cone", (0.06, 0.115), (0.3, 0.6), 0.2, wall_deg=(68, 85), fillet=(0.005, 0.014)),
    "conical": _Style("cone", (0.05, 0.115), (0.3, 0.7), 0.5, wall_deg=(35, 58), fillet=(0.006, 0.02)),
}

_REQUIRED = (
    "style", "inner_rim_radius", "depth", "flat_radius", "wall_thickness", "bottom_thickness",
    "lip_radius", "foot_height", "foot_radius", "foot_width", "density",
)  # fmt: skip
_REQUIRED_BY_CURVE = {"superellipse": ("exponent", "flare_deg"), "cone": ("fillet_radius",)}


def _uniform(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    return float(rng.uniform(*lo_hi))


def _cavity_curve(p: dict[str, Any]) -> np.ndarray:
    """The dense cavity curve (floor to inner rim) of a parameter dict, inner bottom at z = 0."""
    if _STYLES[p["style"]].curve == "superellipse":
        return parts.superellipse_curve(
            p["flat_radius"], p["inner_rim_radius"], p["depth"], p["exponent"], np.radians(p["flare_deg"])
        )
    return parts.filleted_cone_curve(p["flat_radius"], p["inner_rim_radius"], p["depth"], p["fillet_radius"])


def _profile(p: dict[str, Any], with_foot: bool = True) -> parts.BowlProfile:
    foot = p["foot_height"] if with_foot else 0.0
    return parts.build_profile(
        _cavity_curve(p), p["wall_thickness"], p["bottom_thickness"], p["lip_radius"],
        foot, p["foot_radius"], p["foot_width"],
    )  # fmt: skip


class BowlGenerator(CategoryGenerator):
    category = "bowl"
    styles = tuple(_STYLES)

    # -- sampling -----------------------------------------------------------------------------
    def sample_params(self, rng: np.random.Generator, style: str | None = None) -> dict[str, Any]:
        if style is None:
            style = self.styles[int(rng.integers(len(self.styles)))]
        if style not in _STYLES:
            raise InvalidParameterError(f"bowl style must be one of {self.styles}, got {style!r}")
        spec = _STYLES[style]
        # Every draw happens whatever the branch, so one stream always yields the same dict.
        rim = float(np.exp(rng.uniform(*np.log(spec.radius))))
        wall = _uniform(rng, (0.003, 0.008))
        lip_draw, lip_size = rng.random(), _uniform(rng, (0.0015, 0.003))
        lip = lip_size if lip_draw < 0.35 else 0.0
        bottom_factor = _uniform(rng, (1.0, 1.6))
        density = _uniform(rng, (2000.0, 2400.0))
        foot_draw, foot_h = rng.random(), _uniform(rng, (0.003, 0.008))
        foot_w, foot_frac = _uniform(rng, (0.004, 0.008)), _uniform(rng, (0.35, 0.6))
        depth_ratio = _uniform(rng, spec.depth_ratio)
        shape = rng.uniform(size=3)

        inner_rim = rim - wall - 1.4 * lip
        depth = float(np.clip(depth_ratio * inner_rim, 0.030, 0.085))
        p: dict[str, Any] = {"style": style, "inner_rim_radius": inner_rim, "depth": depth, "lip_radius": lip}
        if spec.curve == "superellipse":
            p["flat_radius"] = float(inner_rim * np.interp(shape[0], [0, 1], spec.flat))
            p["exponent"] = float(np.interp(shape[1], [0, 1], spec.exponent))
            p["flare_deg"] = self._steep_enough_flare(p, float(np.interp(shape[2], [0, 1], spec.flare_deg)))
        else:
            p.update(self._cone_shape(spec, inner_rim, depth, float(shape[0]), float(shape[1])))
        curve = _cavity_curve(p)
        # The pinch limit: horizontal width t / sin(angle) plus the bead stays under 10 mm.
        alpha = parts.min_wall_angle(curve, GRASP_ZONE)
        wall = float(np.clip(min(wall, (MAX_RIM_THICKNESS - 1.4 * lip) * np.sin(alpha)), 0.003, 0.008))
        p["wall_thickness"] = wall
        p["bottom_thickness"] = float(np.clip(wall * bottom_factor, wall, 0.012))
        p["density"] = density
        # A bowl without a foot must stand on a wide enough floor: else it gets a foot.
        has_foot = foot_draw < spec.foot_probability or curve[0, 0] < 0.3 * inner_rim
        p.update(foot_height=0.0, foot_radius=0.0, foot_width=0.0)
        if has_foot:
            outer = _profile(p, with_foot=False).outer
            smallest = foot_w + 0.010
            limit = parts.foot_radius_limit(outer, foot_h)
            radius = float(np.clip(foot_frac * inner_rim, smallest, max(limit, smallest)))
            # Only when even the smallest ring sits too high: raise the foot to clear the bottom.
            foot_h = max(foot_h, parts.bottom_rise(outer, radius) + parts.FOOT_CLEARANCE)
            p.update(foot_height=foot_h, foot_radius=radius, foot_width=foot_w)
        return {k: (float(v) if k != "style" else v) for k, v in p.items()}

    def _steep_enough_flare(self, p: dict[str, Any], flare_deg: float) -> float:
        """Open the flare towards vertical (a few fixed steps) until the rim zone is >= 35 deg."""
        for f in np.linspace(flare_deg, 90.0, 4):
            curve = _cavity_curve({**p, "flare_deg": float(f)})
            if np.degrees(parts.min_wall_angle(curve, GRASP_ZONE)) >= 35.0:
                return float(f)
        return 90.0

    @staticmethod
    def _cone_shape(spec: _Style, inner_rim: float, depth: float, u_angle: float, u_fillet: float) -> dict:
        """Floor radius and fillet of a straight-walled cavity, with a floor of >= 1/4 the rim."""
        alpha = np.radians(np.interp(u_angle, [0, 1], spec.wall_deg))
        flat = max(inner_rim - depth / np.tan(alpha), 0.25 * inner_rim)  # else steepen the wall
        alpha = np.arctan2(depth, inner_rim - flat)
        # The fillet's tangent length must fit on the floor and on the wall.
        tangent = np.interp(u_fillet, [0, 1], spec.fillet) * np.tan(alpha / 2)
        tangent = min(tangent, 0.5 * flat, 0.4 * np.hypot(depth, inner_rim - flat))
        return {
            "flat_radius": float(flat),
            "fillet_radius": float(tangent / np.tan(alpha / 2)),
            "wall_angle_deg": float(np.degrees(alpha)),
        }

    # -- building -----------------------------------------------------------------------------
    def profile(self, params: dict[str, Any]) -> parts.BowlProfile:
        """The (r, z) outlines of a parameter dict (cheap: no meshes)."""
        if params.get("style") not in _STYLES:
            raise InvalidParameterError(
                f"bowl style must be one of {self.styles}, got {params.get('style')!r}"
            )
        needed = _REQUIRED + _REQUIRED_BY_CURVE[_STYLES[params["style"]].curve]
        missing = [k for k in needed if k not in params]
        if missing:
            raise InvalidParameterError(
                f"bowl params lack {missing}; draw them with BowlGenerator.sample_params(rng)"
            )
        lengths = ("inner_rim_radius", "depth", "wall_thickness", "bottom_thickness", "density")
        bad = [k for k in lengths if not (np.isfinite(params[k]) and params[k] > 0)]
        if bad:
            raise InvalidParameterError(
                f"bowl params {bad} must be positive numbers, got {[params[k] for k in bad]}"
            )
        return _profile(params)

    def build(self, params: dict[str, Any], instance_id: str) -> Asset:
        prof = self.profile(params)
        visual = union([revolve_profile(prof.outline(), SECTIONS)])  # union() checks it is watertight
        r, z = parts.grasp_point(prof, GRASP_BELOW_RIM)
        anchors = {
            "rim_grasp": Anchor("point", [r, 0.0, z]),
            "opening_center": Anchor("point", [0.0, 0.0, prof.rim_top]),
            "bottom_center": Anchor("point", [0.0, 0.0, 0.0]),
            "rim_radius": Anchor("scalar", [prof.rim_radius]),
            "inner_bottom_center": Anchor("point", [0.0, 0.0, prof.inner_bottom]),
        }
        return Asset(
            category="bowl",
            instance_id=instance_id,
            visual=visual,
            collision=with_label(parts.collision_parts(prof, COLLISION_BUDGET), "body"),
            mass_properties=MassProperties.from_mesh(visual, float(params["density"])),
            anchors=anchors,
            params=dict(params),
            scale=1.0,
            source="procedural",
        )

    def main_dimensions(self, params: dict[str, Any]) -> dict[str, float]:
        prof = self.profile(params)
        return {
            "rim_diameter": 2 * prof.rim_radius,
            "depth": prof.rim_top - prof.inner_bottom,
            "height": prof.rim_top,
            "base_diameter": 2 * prof.base_radius,
        }

    # -- validation ---------------------------------------------------------------------------
    def validate_anchors(self, asset: Asset) -> list[str]:
        """Check each anchor against the visual mesh (works at any scale and on imported bowls)."""
        a = asset.require_anchors()
        mesh = asset.visual

        def tol(mm: float) -> float:  # the named millimetre tolerances hold at scale 1
            return mm * MM * asset.scale

        v = np.asarray(mesh.vertices)
        z_min, z_max = float(v[:, 2].min()), float(v[:, 2].max())
        r_max = float(np.hypot(v[:, 0], v[:, 1]).max())
        size = float(np.ptp(v, axis=0).max())
        problems: list[str] = []

        if abs(z_min) > tol(1):
            problems.append(f"mesh min z is {z_min:.4f} m, expected 0 (the base plane); re-centre the mesh")
        axis_offset = np.linalg.norm((v[:, :2].min(0) + v[:, :2].max(0)) / 2)
        if axis_offset > 0.01 * size:
            problems.append(f"bowl is {axis_offset:.4f} m off the z axis; centre it on the axis")
        bottom = a["bottom_center"].value
        if np.linalg.norm(bottom - (0, 0, z_min)) > tol(1):
            problems.append(f"bottom_center {bottom.round(4).tolist()} is not at (0, 0, min z = {z_min:.4f})")

        rim = float(a["rim_radius"].value[0])
        if abs(rim - r_max) > tol(2):
            problems.append(
                f"rim_radius {rim:.4f} m does not match the mesh's max radius {r_max:.4f} m (2 mm)"
            )

        opening = a["opening_center"].value
        if np.linalg.norm(opening[:2]) > tol(2) or abs(opening[2] - z_max) > tol(2):
            problems.append(
                f"opening_center {opening.round(4).tolist()} is not at (0, 0, rim top {z_max:.4f})"
            )
        floor = self._floor_height(asset, z_max)
        if floor is None or z_max - floor < 0.1 * (z_max - z_min) or floor < z_min + tol(0.5):
            problems.append(
                "no open cavity: a ray down the axis from the opening must land on an inner floor"
            )

        grasp = a["rim_grasp"].value
        gap = float(distance_to_solid(mesh, grasp)[0])
        if gap > tol(5):
            problems.append(f"rim_grasp is {gap * 1e3:.1f} mm from the bowl (at most {tol(5) * 1e3:.1f} mm)")
        if abs(grasp[2] - z_max) > tol(12):
            problems.append(
                f"rim_grasp z {grasp[2]:.4f} is not within {tol(12):.4f} m of the rim top {z_max:.4f}"
            )
        if grasp[0] <= 0 or abs(grasp[1]) > tol(5):
            problems.append(f"rim_grasp {grasp.round(4).tolist()} must lie on the +x side (y ~ 0, x > 0)")

        if "inner_bottom_center" in a:
            inner = a["inner_bottom_center"].value
            if np.linalg.norm(inner[:2]) > tol(1) or floor is None or abs(inner[2] - floor) > tol(1):
                found = "none" if floor is None else f"{floor:.4f}"
                problems.append(
                    f"inner_bottom_center {inner.round(4).tolist()} is not on the floor (z {found})"
                )
        return problems

    @staticmethod
    def _floor_height(asset: Asset, z_max: float) -> float | None:
        """Height where a ray cast down near the axis from above the rim first meets the bowl."""
        # Slightly off the axis: the revolved mesh's triangle fans all meet on the axis itself.
        origin = np.array([[0.3, 0.2, 0.0]]) * MM * asset.scale + (0, 0, z_max + 0.01 * asset.scale)
        hits, _, _ = asset.visual.ray.intersects_location(origin, np.array([[0.0, 0.0, -1.0]]))
        return float(hits[:, 2].max()) if len(hits) else None
