"""The object asset: meshes, convex collision parts, mass, canonical frame and semantic anchors.

An asset is a folder::

    meta.json            category, instance_id, split, source, params, scale, anchors, bbox,
                         mass properties and the list of collision parts
    visual.obj           the visual mesh in the canonical frame (metres)
    collision/part_NNN.obj   convex parts of kind "mesh" (primitives live in meta.json)

Geometry is stored already scaled: ``scale`` records the factor relative to the generator's
nominal size, and :meth:`Asset.scaled` multiplies meshes, collision parts, anchors and mass
properties together (mass by s^3, inertia by s^5) so that they never disagree.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import trimesh

from keygen.errors import AssetError, InvalidParameterError, MissingAnchorsError

CATEGORIES = ("mug", "knife", "bowl")

AnchorKind = Literal["point", "direction", "scalar"]

# The anchors each category must carry, with their kind. Documented in docs/objects.md.
CATEGORY_ANCHORS: dict[str, dict[str, AnchorKind]] = {
    "mug": {
        "handle_grasp": "point",
        "grasp_approach": "direction",
        "handle_center": "point",
        "pour_point": "point",
        "opening_center": "point",
        "bottom_center": "point",
    },
    "knife": {
        "handle_grasp": "point",
        "handle_axis": "direction",
        "blade_base": "point",
        "blade_tip": "point",
        "blade_axis": "direction",
        "edge_direction": "direction",
    },
    "bowl": {
        "rim_grasp": "point",
        "opening_center": "point",
        "bottom_center": "point",
        "rim_radius": "scalar",
    },
}

# Anchors a category may carry beyond the required ones (e.g. made by its generator).
OPTIONAL_ANCHORS: dict[str, dict[str, AnchorKind]] = {
    "mug": {},
    "knife": {},
    "bowl": {"inner_bottom_center": "point"},
}

META_VERSION = 1


@dataclass(frozen=True)
class Anchor:
    """A named semantic anchor in the canonical frame: a point, a unit direction or a length."""

    kind: AnchorKind
    value: np.ndarray  # (3,) for point/direction, (1,) for scalar

    def __post_init__(self) -> None:
        value = np.asarray(self.value, dtype=np.float64).reshape(-1)
        expected = 1 if self.kind == "scalar" else 3
        if self.kind not in ("point", "direction", "scalar"):
            raise InvalidParameterError(f"anchor kind must be point, direction or scalar, got {self.kind!r}")
        if value.shape != (expected,) or not np.all(np.isfinite(value)):
            raise InvalidParameterError(
                f"a {self.kind} anchor needs {expected} finite numbers, got {value.tolist()}"
            )
        if self.kind == "direction":
            norm = np.linalg.norm(value)
            if norm < 1e-9:
                raise InvalidParameterError("a direction anchor cannot be the zero vector")
            value = value / norm
        object.__setattr__(self, "value", value)

    def scaled(self, s: float) -> Anchor:
        return self if self.kind == "direction" else Anchor(self.kind, self.value * s)

    def transformed(self, rotation: np.ndarray, translation: np.ndarray) -> Anchor:
        """The anchor under x -> R x + t (directions rotate only, scalars are unchanged)."""
        if self.kind == "point":
            return Anchor("point", rotation @ self.value + translation)
        if self.kind == "direction":
            return Anchor("direction", rotation @ self.value)
        return self

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "value": self.value.tolist()}

    @staticmethod
    def from_json(d: dict[str, Any]) -> Anchor:
        return Anchor(d["kind"], np.asarray(d["value"], dtype=np.float64))


@dataclass(frozen=True)
class ConvexPart:
    """One convex collision part.

    kinds and their fields:
      - ``box``: ``center`` (3), ``rotation`` (3, 3), ``half_extents`` (3)
      - ``capsule``: ``p0`` (3), ``p1`` (3), ``radius``
      - ``sphere``: ``center`` (3), ``radius``
      - ``mesh``: ``vertices`` (V, 3), the part is their convex hull

    ``label`` optionally names the functional region the part belongs to (mug: "handle",
    "body"; knife: "blade", "bolster", "handle"; bowl: "wall", "floor", "foot"), so tasks can
    tell, e.g., a grasp on a mug's handle from one on its body.
    """

    kind: Literal["box", "capsule", "sphere", "mesh"]
    center: np.ndarray | None = None
    rotation: np.ndarray | None = None
    half_extents: np.ndarray | None = None
    p0: np.ndarray | None = None
    p1: np.ndarray | None = None
    radius: float | None = None
    vertices: np.ndarray | None = None
    label: str | None = None
    # True once ``vertices`` are known to be exactly hull vertices (an affine map keeps them so);
    # skips recomputing the hull, which dominates the cost of scaling an asset.
    hull_vertices: bool = field(default=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        needed = {
            "box": ("center", "rotation", "half_extents"),
            "capsule": ("p0", "p1", "radius"),
            "sphere": ("center", "radius"),
            "mesh": ("vertices",),
        }
        if self.kind not in needed:
            raise InvalidParameterError(f"unknown collision part kind {self.kind!r}")
        for name in needed[self.kind]:
            if getattr(self, name) is None:
                raise InvalidParameterError(f"a {self.kind} collision part needs {name!r}")
        if self.kind == "mesh":
            v = np.asarray(self.vertices, dtype=np.float64)
            if v.ndim != 2 or v.shape[1] != 3 or len(v) < 4 or not np.all(np.isfinite(v)):
                raise InvalidParameterError(f"mesh part needs (V>=4, 3) finite vertices, got {v.shape}")
            if not self.hull_vertices:  # keep only the hull's vertices: the part *is* the hull
                v = np.asarray(trimesh.convex.convex_hull(v).vertices, dtype=np.float64)
                object.__setattr__(self, "hull_vertices", True)
            object.__setattr__(self, "vertices", v)

    # -- geometry -------------------------------------------------------------------------
    def to_trimesh(self) -> trimesh.Trimesh:
        if self.kind == "box":
            tf = np.eye(4)
            tf[:3, :3] = self.rotation
            tf[:3, 3] = self.center
            return trimesh.creation.box(extents=2 * np.asarray(self.half_extents), transform=tf)
        if self.kind == "capsule":
            p0, p1 = np.asarray(self.p0), np.asarray(self.p1)
            return trimesh.creation.capsule(
                height=float(np.linalg.norm(p1 - p0)), radius=self.radius, count=[16, 16]
            ).apply_transform(_segment_transform(p0, p1))
        if self.kind == "sphere":
            return trimesh.creation.icosphere(subdivisions=2, radius=self.radius).apply_translation(
                self.center
            )
        return trimesh.convex.convex_hull(self.vertices)

    def scaled(self, s: float) -> ConvexPart:
        return self.transformed(np.eye(3) * 1.0, np.zeros(3), scale=s)

    def transformed(self, rotation: np.ndarray, translation: np.ndarray, scale: float = 1.0) -> ConvexPart:
        """The part under x -> R (s x) + t."""
        R = np.asarray(rotation, dtype=np.float64)
        t = np.asarray(translation, dtype=np.float64)

        def pt(p: np.ndarray) -> np.ndarray:
            return R @ (scale * np.asarray(p)) + t

        if self.kind == "box":
            return replace(
                self,
                center=pt(self.center),
                rotation=R @ np.asarray(self.rotation),
                half_extents=np.asarray(self.half_extents) * scale,
            )
        if self.kind == "capsule":
            return replace(self, p0=pt(self.p0), p1=pt(self.p1), radius=self.radius * scale)
        if self.kind == "sphere":
            return replace(self, center=pt(self.center), radius=self.radius * scale)
        return replace(self, vertices=(scale * np.asarray(self.vertices)) @ R.T + t)

    def to_json(self, mesh_file: str | None = None) -> dict[str, Any]:
        d = self._geometry_json(mesh_file)
        if self.label is not None:
            d["label"] = self.label
        return d

    def _geometry_json(self, mesh_file: str | None) -> dict[str, Any]:
        if self.kind == "box":
            return {
                "kind": "box",
                "center": np.asarray(self.center).tolist(),
                "rotation": np.asarray(self.rotation).tolist(),
                "half_extents": np.asarray(self.half_extents).tolist(),
            }
        if self.kind == "capsule":
            return {
                "kind": "capsule",
                "p0": np.asarray(self.p0).tolist(),
                "p1": np.asarray(self.p1).tolist(),
                "radius": float(self.radius),
            }
        if self.kind == "sphere":
            return {
                "kind": "sphere",
                "center": np.asarray(self.center).tolist(),
                "radius": float(self.radius),
            }
        return {"kind": "mesh", "file": mesh_file}

    @staticmethod
    def from_json(d: dict[str, Any], folder: Path) -> ConvexPart:
        kind = d.get("kind")
        if kind == "mesh":
            mesh = trimesh.load(folder / d["file"], force="mesh", process=False)
            return ConvexPart("mesh", vertices=np.asarray(mesh.vertices), label=d.get("label"))
        arrays = {k: (np.asarray(v, dtype=np.float64) if isinstance(v, list) else v) for k, v in d.items()}
        arrays.pop("kind", None)
        return ConvexPart(kind, **arrays)


def _segment_transform(p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """A transform taking trimesh's z-aligned, origin-centred primitive onto segment p0-p1."""
    axis = p1 - p0
    length = np.linalg.norm(axis)
    tf = np.eye(4)
    if length > 1e-12:
        tf[:3, :3] = trimesh.geometry.align_vectors([0, 0, 1], axis / length)[:3, :3]
    tf[:3, 3] = (p0 + p1) / 2
    return tf


@dataclass(frozen=True)
class MassProperties:
    mass: float  # kg
    com: np.ndarray  # (3,) canonical frame, metres
    inertia: np.ndarray  # (3, 3) about the centre of mass, kg m^2

    def scaled(self, s: float) -> MassProperties:
        return MassProperties(self.mass * s**3, self.com * s, self.inertia * s**5)

    @staticmethod
    def from_mesh(mesh: trimesh.Trimesh, density: float) -> MassProperties:
        """Solid mass properties of a watertight mesh at uniform density (kg/m^3)."""
        if density <= 0:
            raise InvalidParameterError(f"density must be positive, got {density}")
        m = mesh.copy()
        m.density = density
        if not m.is_volume or m.volume <= 0:
            raise AssetError("mass properties need a closed mesh with positive volume")
        return MassProperties(float(m.mass), np.asarray(m.center_mass), np.asarray(m.moment_inertia))

    @staticmethod
    def combine(parts: list[MassProperties]) -> MassProperties:
        """Mass properties of a rigid union of bodies (parallel-axis theorem)."""
        mass = sum(p.mass for p in parts)
        com = sum(p.mass * p.com for p in parts) / mass
        inertia = np.zeros((3, 3))
        for p in parts:
            d = p.com - com
            inertia += p.inertia + p.mass * (np.dot(d, d) * np.eye(3) - np.outer(d, d))
        return MassProperties(float(mass), com, inertia)


@dataclass
class Asset:
    """A category object instance in its canonical frame (see docs/objects.md)."""

    category: str
    instance_id: str
    visual: trimesh.Trimesh
    collision: list[ConvexPart]
    mass_properties: MassProperties
    anchors: dict[str, Anchor] | None = None
    params: dict[str, Any] = field(default_factory=dict)
    scale: float = 1.0
    split: str | None = None
    source: str = "procedural"

    def __post_init__(self) -> None:
        if self.category not in CATEGORIES:
            raise InvalidParameterError(f"category must be one of {CATEGORIES}, got {self.category!r}")
        if not self.collision:
            raise AssetError(f"asset {self.instance_id} has no collision parts")
        if self.anchors is not None:
            expected = CATEGORY_ANCHORS[self.category]
            missing = sorted(set(expected) - set(self.anchors))
            if missing:
                raise AssetError(f"{self.category} asset {self.instance_id} lacks anchors {missing}")
            for name, kind in expected.items():
                if self.anchors[name].kind != kind:
                    raise AssetError(f"anchor {name!r} must be a {kind}, got {self.anchors[name].kind}")

    # -- derived ----------------------------------------------------------------------------
    @property
    def bbox(self) -> np.ndarray:
        """(2, 3) axis-aligned bounds of the visual mesh in the canonical frame."""
        return np.asarray(self.visual.bounds, dtype=np.float64)

    @property
    def mass(self) -> float:
        return self.mass_properties.mass

    def anchor(self, name: str) -> np.ndarray:
        return self.require_anchors()[name].value

    def require_anchors(self, task: str | None = None) -> dict[str, Anchor]:
        """The anchors, or a clear error for assets imported without an anchor file."""
        if self.anchors is None:
            who = f"task {task!r}" if task else "this operation"
            raise MissingAnchorsError(
                f"{who} needs semantic anchors, but asset {self.instance_id!r} has none; "
                "re-import it with --anchors ANCHORS.json (see docs/objects.md)"
            )
        return self.anchors

    def scaled(self, s: float) -> Asset:
        """A uniformly scaled copy: meshes, collision parts, anchors and mass properties alike."""
        if not np.isfinite(s) or s <= 0:
            raise InvalidParameterError(f"scale must be a positive number, got {s}")
        visual = self.visual.copy()
        visual.apply_scale(s)
        return replace(
            self,
            visual=visual,
            collision=[p.scaled(s) for p in self.collision],
            mass_properties=self.mass_properties.scaled(s),
            anchors=None if self.anchors is None else {k: a.scaled(s) for k, a in self.anchors.items()},
            scale=self.scale * s,
        )

    def collision_meshes(self) -> list[trimesh.Trimesh]:
        return [p.to_trimesh() for p in self.collision]

    # -- storage ----------------------------------------------------------------------------
    def meta(self) -> dict[str, Any]:
        lo, hi = self.bbox
        return {
            "version": META_VERSION,
            "category": self.category,
            "instance_id": self.instance_id,
            "split": self.split,
            "source": self.source,
            "params": self.params,
            "scale": self.scale,
            "anchors": None if self.anchors is None else {k: a.to_json() for k, a in self.anchors.items()},
            "bbox": [lo.tolist(), hi.tolist()],
            "mass": self.mass_properties.mass,
            "com": self.mass_properties.com.tolist(),
            "inertia": self.mass_properties.inertia.tolist(),
            "watertight": bool(self.visual.is_watertight),
        }

    def save(self, folder: str | os.PathLike) -> Path:
        """Write the asset atomically: a crash leaves either the old folder or the new one."""
        folder = Path(folder)
        folder.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
        try:
            (tmp / "collision").mkdir()
            meta = self.meta()
            parts = []
            for i, part in enumerate(self.collision):
                file = None
                if part.kind == "mesh":
                    file = f"collision/part_{i:03d}.obj"
                    part.to_trimesh().export(tmp / file)
                parts.append(part.to_json(file))
            meta["collision"] = parts
            self.visual.export(tmp / "visual.obj")
            (tmp / "meta.json").write_text(json.dumps(meta, indent=1))
            if folder.exists():
                shutil.rmtree(folder)
            os.replace(tmp, folder)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return folder

    @staticmethod
    def load(folder: str | os.PathLike) -> Asset:
        folder = Path(folder)
        meta_file = folder / "meta.json"
        if not meta_file.is_file():
            raise AssetError(
                f"{folder} is not an asset folder: no meta.json (make one with `keygen objects`)"
            )
        try:
            meta = json.loads(meta_file.read_text())
        except json.JSONDecodeError as exc:
            raise AssetError(f"{meta_file} is not valid JSON: {exc}") from exc
        visual = trimesh.load(folder / "visual.obj", force="mesh", process=False)
        anchors = meta.get("anchors")
        return Asset(
            category=meta["category"],
            instance_id=meta["instance_id"],
            visual=visual,
            collision=[ConvexPart.from_json(p, folder) for p in meta["collision"]],
            mass_properties=MassProperties(
                float(meta["mass"]), np.asarray(meta["com"]), np.asarray(meta["inertia"])
            ),
            anchors=None if anchors is None else {k: Anchor.from_json(v) for k, v in anchors.items()},
            params=meta.get("params", {}),
            scale=float(meta.get("scale", 1.0)),
            split=meta.get("split"),
            source=meta.get("source", "procedural"),
        )
