"""The knife category: a parametric family of kitchen knives (chef, paring, bread, cleaver, santoku, utility).

Canonical frame: the knife lies flat, blade in the x-y plane, thickness along z; +x runs from the
handle to the tip, the cutting edge faces -y and the spine +y. The origin is the blade base: where
the blade meets the bolster or handle, halfway between spine and edge, at mid-thickness. The handle
(bolster included) extends from x = 0 to x = -handle_length.

Geometry: the blade is a thin steel solid built from an x-monotone outline (see
``_knife_parts``), tapering in thickness from the spine to the edge; an optional steel bolster
block sits at the junction; the grip is a loft of superellipse sections with a rounded butt.
Collision: convex strips of the blade along x, one hull for the bolster, 4-5 hulls for the grip.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import trimesh

from keygen.errors import InvalidParameterError
from keygen.objects.asset import Anchor, Asset, MassProperties
from keygen.objects.generators import _knife_parts as parts
from keygen.objects.generators.base import CategoryGenerator
from keygen.objects.meshing import distance_to_solid, hull_part, union, with_label

STEEL_DENSITY = 7800.0  # kg/m^3
HANDLE_SIDES = 24  # polygon sides of a grip section
# Handle and bolster reach this far past x = 0 into the blade, so the union never meets coplanar faces.
JOIN_OVERLAP = 3e-4

POINTED_STYLES = ("chef", "paring", "santoku", "utility")
ROUNDED_STYLES = ("bread", "cleaver")
HANDLE_SHAPES = ("straight", "tapered", "belly", "curved")

# Per style: blade length (log-uniform), base width, spine thickness, handle length (log-uniform),
# handle width and handle thickness ranges, in metres.
_STYLE_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "chef": {
        "blade_length": (0.150, 0.240),
        "blade_width": (0.038, 0.058),
        "spine_thickness": (0.0018, 0.0030),
        "handle_length": (0.110, 0.140),
        "handle_width": (0.021, 0.028),
        "handle_thickness": (0.015, 0.022),
    },
    "paring": {
        "blade_length": (0.070, 0.105),
        "blade_width": (0.014, 0.024),
        "spine_thickness": (0.0015, 0.0022),
        "handle_length": (0.080, 0.105),
        "handle_width": (0.016, 0.021),
        "handle_thickness": (0.012, 0.016),
    },
    "bread": {
        "blade_length": (0.180, 0.240),
        "blade_width": (0.022, 0.034),
        "spine_thickness": (0.0016, 0.0026),
        "handle_length": (0.105, 0.140),
        "handle_width": (0.020, 0.027),
        "handle_thickness": (0.015, 0.021),
    },
    "cleaver": {
        "blade_length": (0.140, 0.200),
        "blade_width": (0.065, 0.090),
        "spine_thickness": (0.0025, 0.0040),
        "handle_length": (0.110, 0.140),
        "handle_width": (0.024, 0.030),
        "handle_thickness": (0.018, 0.024),
    },
    "santoku": {
        "blade_length": (0.130, 0.190),
        "blade_width": (0.038, 0.052),
        "spine_thickness": (0.0018, 0.0028),
        "handle_length": (0.105, 0.135),
        "handle_width": (0.021, 0.028),
        "handle_thickness": (0.015, 0.021),
    },
    "utility": {
        "blade_length": (0.100, 0.160),
        "blade_width": (0.020, 0.032),
        "spine_thickness": (0.0015, 0.0024),
        "handle_length": (0.090, 0.125),
        "handle_width": (0.018, 0.025),
        "handle_thickness": (0.013, 0.018),
    },
}

# Pointed tips: tip height (fraction of the base width above the centre line), where the spine starts
# dropping and the edge starts rising (fractions of the blade length), and the powers of those curves.
_TIP_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "chef": {
        "tip_height": (0.20, 0.38),
        "spine_drop_start": (0.60, 0.85),
        "spine_drop_power": (1.4, 2.4),
        "edge_rise_start": (0.25, 0.50),
        "edge_rise_power": (1.6, 2.6),
    },
    "paring": {
        "tip_height": (-0.10, 0.30),
        "spine_drop_start": (0.35, 0.70),
        "spine_drop_power": (1.2, 2.2),
        "edge_rise_start": (0.35, 0.65),
        "edge_rise_power": (1.5, 2.5),
    },
    "santoku": {
        "tip_height": (-0.45, -0.30),
        "spine_drop_start": (0.45, 0.70),
        "spine_drop_power": (1.6, 2.6),
        "edge_rise_start": (0.75, 0.92),
        "edge_rise_power": (1.5, 2.5),
    },
    "utility": {
        "tip_height": (0.00, 0.30),
        "spine_drop_start": (0.55, 0.80),
        "spine_drop_power": (1.3, 2.3),
        "edge_rise_start": (0.45, 0.70),
        "edge_rise_power": (1.5, 2.5),
    },
}

# Rounded fronts: spine taper and edge belly (fractions of the base width), front bulge (fraction of
# the front half-height).
_FRONT_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "bread": {"spine_taper": (0.0, 0.2), "edge_belly": (0.0, 0.0), "tip_bulge": (0.5, 1.0)},
    "cleaver": {"spine_taper": (0.0, 0.08), "edge_belly": (0.0, 0.06), "tip_bulge": (0.04, 0.12)},
}

_BOLSTER_PROBABILITY = {
    "chef": 0.6,
    "santoku": 0.5,
    "utility": 0.4,
    "paring": 0.3,
    "bread": 0.3,
    "cleaver": 0.2,
}

PARAM_KEYS = (
    "style",
    "handle_shape",
    "blade_length",
    "blade_width",
    "spine_thickness",
    "edge_thickness",
    "tip_height",
    "spine_drop_start",
    "spine_drop_power",
    "edge_rise_start",
    "edge_rise_power",
    "spine_taper",
    "edge_belly",
    "tip_bulge",
    "serration_pitch",
    "serration_depth",
    "bolster_length",
    "bolster_width_ratio",
    "bolster_thickness_ratio",
    "handle_length",
    "handle_width",
    "handle_thickness",
    "handle_exponent",
    "handle_taper",
    "handle_belly",
    "handle_sag",
    "handle_spine_gap",
    "handle_density",
)


def _uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return float(rng.uniform(*bounds))


def _log_uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return float(np.exp(rng.uniform(np.log(bounds[0]), np.log(bounds[1]))))


def _unit(v: np.ndarray) -> np.ndarray:
    return np.asarray(v, dtype=np.float64) / np.linalg.norm(v)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(np.dot(_unit(a), _unit(b)), -1.0, 1.0))))


class KnifeGenerator(CategoryGenerator):
    category = "knife"
    styles = ("chef", "paring", "bread", "cleaver", "santoku", "utility")

    # -- parameters ------------------------------------------------------------------------------
    def sample_params(self, rng: np.random.Generator, style: str | None = None) -> dict[str, Any]:
        if style is None:
            style = self.styles[int(rng.integers(len(self.styles)))]
        if style not in self.styles:
            raise InvalidParameterError(f"knife style must be one of {self.styles}, got {style!r}")
        r = _STYLE_RANGES[style]
        spine = _uniform(rng, r["spine_thickness"])
        p: dict[str, Any] = {
            "style": style,
            "handle_shape": HANDLE_SHAPES[int(rng.integers(len(HANDLE_SHAPES)))],
            "blade_length": _log_uniform(rng, r["blade_length"]),
            "blade_width": _uniform(rng, r["blade_width"]),
            "spine_thickness": spine,
            # The edge is left a little thick (0.4 mm at least) so the solid stays well conditioned.
            "edge_thickness": max(0.0004, spine * float(rng.uniform(0.2, 0.4))),
            # Neutral values for the fields a style does not use, so every dict has every key.
            "tip_height": 0.0,
            "spine_drop_start": 1.0,
            "spine_drop_power": 1.0,
            "edge_rise_start": 1.0,
            "edge_rise_power": 1.0,
            "spine_taper": 0.0,
            "edge_belly": 0.0,
            "tip_bulge": 0.0,
            "serration_pitch": 0.0,
            "serration_depth": 0.0,
        }
        for key, bounds in _TIP_RANGES.get(style, {}).items():
            p[key] = _uniform(rng, bounds)
        for key, bounds in _FRONT_RANGES.get(style, {}).items():
            p[key] = _uniform(rng, bounds)
        if style == "bread":
            p["serration_pitch"] = float(rng.uniform(0.003, 0.006))
            p["serration_depth"] = float(rng.uniform(0.0004, 0.0009))
        has_bolster = rng.uniform() < _BOLSTER_PROBABILITY[style]
        p["bolster_length"] = float(rng.uniform(0.008, 0.018)) if has_bolster else 0.0
        p["bolster_width_ratio"] = float(rng.uniform(1.04, 1.15))
        p["bolster_thickness_ratio"] = float(rng.uniform(0.6, 0.85))
        p["handle_length"] = _log_uniform(rng, r["handle_length"])
        p["handle_width"] = _uniform(rng, r["handle_width"])
        p["handle_thickness"] = _uniform(rng, r["handle_thickness"])
        p["handle_exponent"] = float(rng.uniform(2.2, 4.0))
        p["handle_taper"] = float(rng.uniform(0.1, 0.28))
        p["handle_belly"] = float(rng.uniform(0.08, 0.2))
        p["handle_sag"] = float(rng.uniform(0.004, 0.012))
        p["handle_spine_gap"] = float(rng.uniform(0.0, 0.006))
        p["handle_density"] = float(rng.uniform(900.0, 1300.0))
        return p

    def main_dimensions(self, params: dict[str, Any]) -> dict[str, float]:
        self._check_params(params)
        blade, handle = float(params["blade_length"]), float(params["handle_length"])
        return {
            "blade_length": blade,
            "blade_width": float(params["blade_width"]),
            "handle_length": handle,
            "total_length": blade + handle,
        }

    def _check_params(self, p: dict[str, Any]) -> None:
        missing = [k for k in PARAM_KEYS if k not in p]
        if missing:
            raise InvalidParameterError(
                f"knife params lack {missing}; draw a complete dict with KnifeGenerator.sample_params"
            )
        if p["style"] not in self.styles:
            raise InvalidParameterError(f"knife style must be one of {self.styles}, got {p['style']!r}")
        if p["handle_shape"] not in HANDLE_SHAPES:
            raise InvalidParameterError(
                f"handle_shape must be one of {HANDLE_SHAPES}, got {p['handle_shape']!r}"
            )
        for key in ("blade_length", "blade_width", "spine_thickness", "edge_thickness", "handle_length"):
            if not float(p[key]) > 0:
                raise InvalidParameterError(f"knife {key} must be positive, got {p[key]}")
        if not float(p["edge_thickness"]) <= float(p["spine_thickness"]):
            raise InvalidParameterError(
                f"edge_thickness ({p['edge_thickness']}) must not exceed spine_thickness "
                f"({p['spine_thickness']}); lower it or draw params with sample_params"
            )
        if not 0 <= float(p["bolster_length"]) < 0.5 * float(p["handle_length"]):
            raise InvalidParameterError(
                f"bolster_length must be in [0, handle_length / 2), got {p['bolster_length']} "
                f"for a {p['handle_length']} m handle"
            )
        if not float(p["handle_thickness"]) > 2 * float(p["spine_thickness"]):
            raise InvalidParameterError(
                f"handle_thickness ({p['handle_thickness']}) must exceed twice the spine thickness "
                f"({p['spine_thickness']}) so the knife rests on its handle"
            )

    # -- building --------------------------------------------------------------------------------
    def blade_outline(self, p: dict[str, Any]) -> parts.BladeOutline:
        length, width = float(p["blade_length"]), float(p["blade_width"])
        if p["style"] in ROUNDED_STYLES:
            return parts.rounded_outline(
                length,
                width,
                spine_taper=float(p["spine_taper"]) * width,
                edge_belly=float(p["edge_belly"]) * width,
                tip_bulge=float(p["tip_bulge"]),
                serration_pitch=float(p["serration_pitch"]),
                serration_depth=float(p["serration_depth"]),
            )
        return parts.pointed_outline(
            length,
            width,
            tip_y=float(p["tip_height"]) * width,
            spine_drop_start=float(p["spine_drop_start"]),
            spine_drop_power=float(p["spine_drop_power"]),
            edge_rise_start=float(p["edge_rise_start"]),
            edge_rise_power=float(p["edge_rise_power"]),
        )

    def _grip(self, p: dict[str, Any]) -> dict[str, Any]:
        """Grip placement: front x, butt x and the section arguments shared by its helpers."""
        width, hw = float(p["blade_width"]), float(p["handle_width"])
        # The grip hangs from the spine side (knuckle room under it on wide blades) but stays on the
        # centre line for blades narrower than the grip.
        centre_y = max(0.0, width / 2 - hw / 2 - float(p["handle_spine_gap"]))
        bolster = float(p["bolster_length"])
        return {
            "x_front": (-bolster + 0.5e-3) if bolster > 0 else JOIN_OVERLAP,
            "x_butt": -float(p["handle_length"]),
            "shape": p["handle_shape"],
            "width": hw,
            "thickness": float(p["handle_thickness"]),
            "centre_y": centre_y,
            "taper": float(p["handle_taper"]),
            "belly": float(p["handle_belly"]),
            "sag": float(p["handle_sag"]),
        }

    def build(self, params: dict[str, Any], instance_id: str) -> Asset:
        p = dict(params)
        self._check_params(p)
        outline = self.blade_outline(p)
        corners = parts.blade_vertices(outline, float(p["spine_thickness"]), float(p["edge_thickness"]))
        blade = parts.blade_mesh(corners)
        length = float(p["blade_length"])
        collision = with_label(
            parts.blade_strip_parts(corners, int(np.clip(np.ceil(length / 0.018), 5, 12))), "blade"
        )

        grip = self._grip(p)
        sections, butt_cap = parts.handle_sections(exponent=float(p["handle_exponent"]), **grip)
        rings = parts.loft_rings(sections, HANDLE_SIDES)
        front_cap = np.array([sections.x[0], sections.centre[0], 0.0])
        handle = parts.loft_mesh(rings, front_cap, butt_cap)
        shape = grip["shape"]
        collision += with_label(
            parts.loft_parts(rings, butt_cap, 5 if shape in ("belly", "curved") else 4), "handle"
        )

        steel = [blade]
        bolster_length = float(p["bolster_length"])
        if bolster_length > 0:
            bolster_rings = self._bolster_rings(p, sections)
            bolster = parts.loft_mesh(
                bolster_rings,
                np.array([bolster_rings[0, 0, 0], sections.centre[0], 0.0]),
                np.array([bolster_rings[-1, 0, 0], sections.centre[0], 0.0]),
            )
            steel.append(bolster)
            collision += with_label([hull_part(bolster_rings.reshape(-1, 3))], "bolster")

        visual = union([*steel, handle])
        mass = MassProperties.combine(
            [MassProperties.from_mesh(m, STEEL_DENSITY) for m in steel]
            + [MassProperties.from_mesh(handle, float(p["handle_density"]))]
        )
        return Asset(
            category="knife",
            instance_id=instance_id,
            visual=visual,
            collision=collision,
            mass_properties=mass,
            anchors=self._anchors(p, outline),
            params=dict(params),
            scale=1.0,
            source="procedural",
        )

    def _bolster_rings(self, p: dict[str, Any], grip: parts.LoftSections) -> np.ndarray:
        """Rings of the bolster: a short block from x = -bolster_length to just past x = 0.

        Wider than the grip front and thinner (the two surfaces cross, never coincide), thinning a
        little toward the blade, and always clearly thicker than the blade.
        """
        spine = float(p["spine_thickness"])
        width = grip.width[0] * float(p["bolster_width_ratio"])
        thickness = max(grip.thickness[0] * float(p["bolster_thickness_ratio"]), spine + 0.003)
        sections = parts.LoftSections(
            x=np.array([JOIN_OVERLAP, -float(p["bolster_length"])]),
            width=np.array([width * 0.95, width]),
            thickness=np.array([thickness * 0.85, thickness]),
            centre=np.full(2, grip.centre[0]),
            exponent=max(3.0, grip.exponent),
        )
        return parts.loft_rings(sections, HANDLE_SIDES)

    def _anchors(self, p: dict[str, Any], outline: parts.BladeOutline) -> dict[str, Anchor]:
        grip = self._grip(p)
        section_args = {
            k: grip[k] for k in ("shape", "width", "thickness", "centre_y", "taper", "belly", "sag")
        }
        grip_mid = (grip["x_front"] + grip["x_butt"]) / 2
        front = np.array([grip["x_front"], parts.grip_centre(u=0.0, **section_args), 0.0])
        butt = np.array([grip["x_butt"], parts.grip_centre(u=1.0, **section_args), 0.0])
        grasp = np.array([grip_mid, parts.grip_centre(u=0.5, **section_args), 0.0])
        tip = np.array([outline.tip[0], outline.tip[1], 0.0])
        blade_axis = _unit(tip)
        edge = np.array([0.0, -1.0, 0.0])
        edge = _unit(edge - np.dot(edge, blade_axis) * blade_axis)
        return {
            "handle_grasp": Anchor("point", grasp),
            "handle_axis": Anchor("direction", front - butt),
            "blade_base": Anchor("point", np.zeros(3)),
            "blade_tip": Anchor("point", tip),
            "blade_axis": Anchor("direction", blade_axis),
            "edge_direction": Anchor("direction", edge),
        }

    # -- validation ------------------------------------------------------------------------------
    def validate_anchors(self, asset: Asset) -> list[str]:
        anchors = asset.require_anchors("knife anchor validation")
        mesh = asset.visual
        lo, hi = mesh.bounds
        size = float(hi[0] - lo[0])  # the knife's length: relative tolerances scale with it
        mm = 1e-3 * asset.scale  # the brief's fixed tolerances are millimetres at nominal scale
        problems: list[str] = []

        grasp = anchors["handle_grasp"].value
        base = anchors["blade_base"].value
        tip = anchors["blade_tip"].value
        dist = distance_to_solid(mesh, np.vstack([grasp, base, tip]))

        if dist[0] > 1e-6 * size:
            problems.append(f"handle_grasp {grasp.round(4).tolist()} is {dist[0]:.4f} m outside the solid")
        if not grasp[0] < base[0]:
            problems.append(
                f"handle_grasp x={grasp[0]:.4f} must lie behind the blade base (x < {base[0]:.4f})"
            )
        problems += _centred_in_section(mesh, grasp, "handle_grasp", tol=0.15)

        butt = _butt_point(mesh, size)
        axis = anchors["handle_axis"].value
        angle = _angle_deg(axis, grasp - butt)
        if angle > 20.0:
            problems.append(
                f"handle_axis is {angle:.1f} deg off the butt -> grasp direction (expected <= 20)"
            )

        if dist[1] > 5 * mm:
            problems.append(
                f"blade_base is {dist[1] * 1e3:.1f} mm from the solid (expected <= {5 * mm * 1e3:.1f})"
            )
        problems += _blade_base_centred(mesh, base, tip, 5 * mm)

        if dist[2] > 2 * mm:
            problems.append(
                f"blade_tip is {dist[2] * 1e3:.1f} mm from the solid (expected <= {2 * mm * 1e3:.1f})"
            )
        if abs(tip[0] - hi[0]) > 2 * mm:
            problems.append(
                f"blade_tip x={tip[0]:.4f} is not the knife's far end "
                f"(max x {hi[0]:.4f}, tolerance {2 * mm:.4f})"
            )

        blade_axis = anchors["blade_axis"].value
        if np.linalg.norm(tip - base) > 0 and _angle_deg(blade_axis, tip - base) > 2.0:
            problems.append(
                f"blade_axis is {_angle_deg(blade_axis, tip - base):.1f} deg off blade_base -> blade_tip"
            )

        edge = anchors["edge_direction"].value
        if abs(np.dot(edge, blade_axis)) > 0.05:
            problems.append(
                f"edge_direction is not perpendicular to blade_axis (dot {np.dot(edge, blade_axis):.3f})"
            )
        problems += _edge_direction_in_blade(mesh, base, tip, edge)
        return problems


# -- geometric probes used by validate_anchors (mesh only, so they work on imported assets) ----------


def _section_points(mesh: trimesh.Trimesh, origin: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Points of the mesh's cross-section by a plane (segment end points), (K, 3); empty if none."""
    segments = trimesh.intersections.mesh_plane(mesh, plane_normal=normal, plane_origin=origin)
    return np.asarray(segments, dtype=np.float64).reshape(-1, 3)


def _centred_in_section(mesh: trimesh.Trimesh, point: np.ndarray, name: str, tol: float) -> list[str]:
    """Check that ``point`` is at mid-width and mid-thickness of the x cross-section through it."""
    pts = _section_points(mesh, point, np.array([1.0, 0.0, 0.0]))
    if len(pts) == 0:
        return [f"{name}: the mesh has no cross-section at x={point[0]:.4f}"]
    problems = []
    for axis, label in ((1, "width (y)"), (2, "thickness (z)")):
        low, high = pts[:, axis].min(), pts[:, axis].max()
        if abs(point[axis] - (low + high) / 2) > tol * (high - low):
            problems.append(
                f"{name} is off the middle of the handle's {label}: {point[axis]:.4f} vs section "
                f"[{low:.4f}, {high:.4f}]"
            )
    return problems


def _butt_point(mesh: trimesh.Trimesh, size: float) -> np.ndarray:
    """The handle butt: the mean of the vertices within 0.5 % of the length of the minimum x."""
    v = np.asarray(mesh.vertices)
    near = v[v[:, 0] <= v[:, 0].min() + 0.005 * size]
    return near.mean(axis=0)


def _blade_base_centred(mesh: trimesh.Trimesh, base: np.ndarray, tip: np.ndarray, tol: float) -> list[str]:
    """The blade base should be halfway between spine and edge just in front of the handle."""
    reach = tip[0] - base[0]
    if reach <= 0:
        return [f"blade_tip x={tip[0]:.4f} must lie ahead of blade_base x={base[0]:.4f}"]
    probe = base + np.array([0.02 * reach, 0.0, 0.0])
    pts = _section_points(mesh, probe, np.array([1.0, 0.0, 0.0]))
    if len(pts) == 0:
        return [f"blade_base: no blade cross-section just ahead of it (x={probe[0]:.4f})"]
    low, high = pts[:, 1].min(), pts[:, 1].max()
    problems = []
    if abs(base[1] - (low + high) / 2) > max(tol, 0.1 * (high - low)):
        problems.append(
            f"blade_base y={base[1]:.4f} is not halfway between spine and edge ({low:.4f} .. {high:.4f})"
        )
    z_mid = (pts[:, 2].min() + pts[:, 2].max()) / 2
    if abs(base[2] - z_mid) > tol:
        problems.append(f"blade_base z={base[2]:.4f} is not at the blade's mid-thickness ({z_mid:.4f})")
    return problems


def _edge_direction_in_blade(
    mesh: trimesh.Trimesh, base: np.ndarray, tip: np.ndarray, edge: np.ndarray
) -> list[str]:
    """edge_direction lies in the blade's plane and points to its thinner (cutting) side.

    The blade plane comes from a cross-section a third of the way to the tip; the side check only
    speaks when the section clearly thins toward one side (a blade of even thickness says nothing).
    """
    probe = base + (tip - base) / 3
    pts = _section_points(mesh, probe, _unit(tip - base))
    if len(pts) < 3:
        return [f"edge_direction: no blade cross-section at {probe.round(4).tolist()}"]
    centred = pts - pts.mean(axis=0)
    # The section is planar: its largest spread is the blade's width, the second its thickness (the
    # third, zero, is the cutting plane's own normal).
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    width_dir, normal = vt[0], vt[1]
    problems = []
    if abs(np.dot(edge, normal)) > 0.2:
        problems.append(
            f"edge_direction leaves the blade plane (component {np.dot(edge, normal):.2f} along its normal)"
        )
    along = centred @ width_dir
    thick = centred @ normal
    span = along.max() - along.min()
    ends = [along >= along.max() - 0.2 * span, along <= along.min() + 0.2 * span]
    thickness = [np.ptp(thick[e]) for e in ends]  # at the +width_dir end, at the -width_dir end
    if min(thickness) < 0.8 * max(thickness):
        thin_side = width_dir if thickness[0] < thickness[1] else -width_dir
        if np.dot(edge, thin_side) < 0:
            problems.append("edge_direction points toward the spine (the thicker side of the blade)")
    return problems
