"""Import scanned or downloaded meshes (OBJ, STL, PLY, GLB/GLTF) as category assets.

:func:`import_mesh` reads a mesh file, repairs what can be repaired, converts it to metres in the
category's canonical frame, builds convex collision parts (CoACD or a single hull) and mass
properties, and returns an :class:`~keygen.objects.asset.Asset` (saved atomically when
``out_dir`` is given). Colours and textures are dropped: an asset stores geometry only.

Anchors file
------------
The canonical frame and the semantic anchors come from an optional JSON file written by the
user (:func:`export_for_import` writes one for any asset, as a template)::

    {
      "units": "mm",
      "frame": {"origin": [0, 0, 12.5], "up": [0, 0, 1], "front": [1, 0, 0]},
      "anchors": {
        "handle_grasp": [61.0, 0.0, 50.0],
        "grasp_approach": [0.0, 0.0, -1.0],
        "rim_radius": 45.0
      }
    }

Every key is optional; unknown keys are refused (they are usually typos).

- ``units``: the unit of every coordinate in the mesh file and in this JSON file, one of
  ``mm``, ``cm``, ``m``, ``in``. When the caller also passes ``units`` both must agree.
- ``frame``: where the canonical frame sits, in the mesh file's coordinates. ``origin`` is the
  canonical origin (default ``[0, 0, 0]``), ``up`` the file direction that becomes canonical +z
  (default ``[0, 0, 1]``), ``front`` the file direction that becomes canonical +x (default
  ``[1, 0, 0]``; orthogonalised against ``up``; it must not be parallel to it). Canonical +y is
  ``up x front``, so the frame is right-handed and nothing is mirrored. The frame is kept as
  given, even when the mesh does not rest on z = 0 in it (a warning says so).
- ``anchors``: every anchor of the category (``keygen.objects.asset.CATEGORY_ANCHORS``), in the
  mesh file's coordinates: a point is ``[x, y, z]`` (moved, rotated and scaled into the
  canonical frame), a direction is ``[dx, dy, dz]`` (rotated only, then normalised), a scalar is
  a length ``r`` or ``[r]`` (scaled only). Without ``anchors`` the asset has none.

Without a ``frame`` the file's own axes are used: +z up for OBJ, STL and PLY, and +y up, +z
front for GLB/GLTF (the glTF 2.0 convention), with the origin kept where the file has it. When
there is neither a ``frame`` nor ``anchors`` (no anchors file, say) the mesh is instead placed
with its base at z = 0 and its bounding box centred in x and y, and the asset has no anchors
(tasks that need them raise ``MissingAnchorsError``).
"""

from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import trimesh

from keygen.errors import InvalidParameterError, MeshImportError
from keygen.objects.asset import (
    CATEGORIES,
    CATEGORY_ANCHORS,
    OPTIONAL_ANCHORS,
    Anchor,
    Asset,
    ConvexPart,
    MassProperties,
)

log = logging.getLogger(__name__)

#: metres per file unit
UNITS: dict[str, float] = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "in": 0.0254}

#: file extensions read, mapped to trimesh's file type
FORMATS: dict[str, str] = {".obj": "obj", ".stl": "stl", ".ply": "ply", ".glb": "glb", ".gltf": "gltf"}

#: solid density (kg/m^3) per category: ceramic mugs and bowls, a steel-and-polymer knife
DEFAULT_DENSITY: dict[str, float] = {"mug": 2200.0, "bowl": 2200.0, "knife": 3000.0}

#: the plausible range of an object's largest extent, metres
SIZE_RANGE = (0.01, 2.0)

# A mesh whose thinnest principal extent is below this fraction of its largest has no volume.
_FLATNESS = 1e-4
_JSON_KEYS = {"units", "frame", "anchors"}
_FRAME_KEYS = {"origin", "up", "front"}
_ANCHORS_HELP = (
    'expected JSON like {"units": "mm", "frame": {"origin": [x, y, z], "up": [0, 0, 1], '
    '"front": [1, 0, 0]}, "anchors": {NAME: [x, y, z] or LENGTH}} (see keygen.objects.importer)'
)


@dataclass(frozen=True)
class _Frame:
    """Canonical coordinates of a file point p: ``rotation @ (p - origin)`` (before scaling)."""

    origin: np.ndarray
    rotation: np.ndarray  # rows: canonical x (front), y (left), z (up) in file coordinates
    given: bool  # True when the user's JSON set it (then it is kept, not re-centred)


# -- public API -------------------------------------------------------------------------------


def import_mesh(
    path: str | os.PathLike,
    category: str,
    out_dir: str | os.PathLike | None = None,
    *,
    anchors_path: str | os.PathLike | None = None,
    units: str | None = None,
    scale: float = 1.0,
    target_size: float | None = None,
    collision: Literal["coacd", "hull"] = "coacd",
    coacd_threshold: float = 0.05,
    max_parts: int = 32,
    density: float | None = None,
    instance_id: str | None = None,
) -> Asset:
    """Import a mesh file as an asset of ``category``, saved to ``out_dir`` when given.

    ``units`` is the unit of the file's coordinates (``mm``, ``cm``, ``m``, ``in``); ``None``
    takes it from the anchors file, else metres. ``scale`` then multiplies the size, or
    ``target_size`` (metres) sets the largest bounding-box extent (not both). ``collision`` is
    ``"coacd"`` (approximate convex decomposition, at most ``max_parts`` parts, concavity
    ``coacd_threshold``) or ``"hull"`` (one convex hull, fast). ``density`` (kg/m^3) defaults per
    category. Raises :class:`MeshImportError` for files that cannot become an asset and
    :class:`InvalidParameterError` for bad arguments; on error nothing is written.
    """
    path = Path(path)
    _check_arguments(category, scale, target_size, collision, coacd_threshold, max_parts, density)
    spec = _read_anchors_file(Path(anchors_path)) if anchors_path is not None else None
    units = _resolve_units(units, spec)
    file_type = _check_file(path)

    mesh = _load(path, file_type)
    repairs = _repair(mesh, path)
    _check_has_volume(mesh, path)

    frame = _parse_frame(spec.get("frame") if spec else None, file_type)
    rotated = (mesh.vertices - frame.origin) @ frame.rotation.T
    raw_extent = float(np.ptp(rotated, axis=0).max())
    factor = target_size / raw_extent if target_size is not None else UNITS[units] * scale
    if target_size is None:
        _check_size(raw_extent, units, scale, path)

    canonical = factor * rotated
    has_anchors = spec is not None and "anchors" in spec
    # Anchors are given in file coordinates, so the mesh may only be moved when there are none.
    place_on_ground = not frame.given and not has_anchors
    if place_on_ground:
        # Rest the base on z = 0 and centre the footprint on the z axis.
        lo, hi = canonical.min(axis=0), canonical.max(axis=0)
        canonical = canonical - np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    else:
        _warn_if_floating(canonical, path)
    visual = trimesh.Trimesh(canonical, mesh.faces.copy(), process=False)

    anchors = None
    if has_anchors:
        anchors = _parse_anchors(spec["anchors"], category, frame, factor, anchors_path)
        _warn_if_anchors_outside(anchors, visual, path)

    parts = (
        _coacd_parts(visual, coacd_threshold, max_parts, path)
        if collision == "coacd"
        else [_hull_part(visual)]
    )
    rho = DEFAULT_DENSITY[category] if density is None else float(density)
    mass_properties = _mass_properties(visual, parts, rho, path)

    asset = Asset(
        category=category,
        instance_id=instance_id if instance_id is not None else path.stem,
        visual=visual,
        collision=parts,
        mass_properties=mass_properties,
        anchors=anchors,
        params={
            "source_file": path.name,
            "units": units,
            "scale_applied": float(factor),
            "frame": "anchors_file" if frame.given else ("auto" if place_on_ground else "file_axes"),
            "collision": collision,
            "density": rho,
            "repairs": repairs,
        },
        source="imported",
    )
    if out_dir is not None:
        asset.save(out_dir)
    return asset


def export_for_import(
    asset: Asset,
    folder: str | os.PathLike,
    *,
    units: str = "m",
    transform: np.ndarray | None = None,
    mesh_format: str = "obj",
) -> tuple[Path, Path]:
    """Write ``asset``'s visual mesh and its frame + anchors JSON so :func:`import_mesh` reads them back.

    By default the mesh is written as OBJ in metres in the canonical frame (the JSON frame is the
    identity). ``transform`` (a 4x4 rigid transform, metres) moves the asset into other file
    coordinates first and ``units`` writes them in another unit; the JSON records the matching
    frame, so importing the pair gives the asset back. Returns ``(mesh_path, anchors_path)``.
    """
    if units not in UNITS:
        raise InvalidParameterError(f"units must be one of {sorted(UNITS)}, got {units!r}")
    suffix = "." + mesh_format.lower().lstrip(".")
    if suffix not in FORMATS:
        raise InvalidParameterError(f"mesh_format must be one of {sorted(FORMATS)}, got {mesh_format!r}")
    tf = np.eye(4) if transform is None else np.asarray(transform, dtype=np.float64)
    rotation, translation = tf[:3, :3], tf[:3, 3]
    if tf.shape != (4, 4) or not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-9):
        raise InvalidParameterError("transform must be a 4x4 rigid transform (orthonormal rotation block)")
    if np.linalg.det(rotation) < 0:
        raise InvalidParameterError("transform must not mirror (its rotation block needs determinant +1)")

    to_file = 1.0 / UNITS[units]
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    mesh = asset.visual.copy()
    mesh.apply_transform(tf)
    mesh.apply_scale(to_file)
    mesh_path = folder / f"{asset.instance_id}{suffix}"
    mesh.export(mesh_path)

    spec: dict[str, Any] = {
        "units": units,
        "frame": {
            "origin": (translation * to_file).tolist(),
            "up": rotation[:, 2].tolist(),
            "front": rotation[:, 0].tolist(),
        },
    }
    if asset.anchors is not None:
        spec["anchors"] = {
            name: _anchor_to_file(anchor, rotation, translation, to_file)
            for name, anchor in asset.anchors.items()
        }
    anchors_path = folder / f"{asset.instance_id}.anchors.json"
    anchors_path.write_text(json.dumps(spec, indent=1))
    return mesh_path, anchors_path


# -- arguments and files ----------------------------------------------------------------------


def _check_arguments(
    category: str,
    scale: float,
    target_size: float | None,
    collision: str,
    coacd_threshold: float,
    max_parts: int,
    density: float | None,
) -> None:
    if category not in CATEGORIES:
        raise InvalidParameterError(f"category must be one of {CATEGORIES}, got {category!r}")
    if not (math.isfinite(scale) and scale > 0):
        raise InvalidParameterError(f"scale must be a positive number, got {scale}")
    if target_size is not None:
        if scale != 1.0:
            raise InvalidParameterError(
                f"pass either scale ({scale}) or target_size ({target_size}), not both"
            )
        lo, hi = SIZE_RANGE
        if not (math.isfinite(target_size) and lo <= target_size <= hi):
            raise InvalidParameterError(f"target_size must be between {lo} and {hi} m, got {target_size}")
    if collision not in ("coacd", "hull"):
        raise InvalidParameterError(f"collision must be 'coacd' or 'hull', got {collision!r}")
    if not 0.01 <= coacd_threshold <= 1.0:
        raise InvalidParameterError(f"coacd_threshold must be in [0.01, 1], got {coacd_threshold}")
    if max_parts < 1:
        raise InvalidParameterError(f"max_parts must be >= 1, got {max_parts}")
    if density is not None and not (math.isfinite(density) and density > 0):
        raise InvalidParameterError(f"density must be a positive number (kg/m^3), got {density}")


def _resolve_units(units: str | None, spec: dict[str, Any] | None) -> str:
    file_units = spec.get("units") if spec else None
    if file_units is not None and (not isinstance(file_units, str) or file_units not in UNITS):
        raise MeshImportError(f"anchors file: units must be one of {sorted(UNITS)}, got {file_units!r}")
    if units is not None and (not isinstance(units, str) or units not in UNITS):
        raise InvalidParameterError(f"units must be one of {sorted(UNITS)}, got {units!r}")
    if units is not None and file_units is not None and units != file_units:
        raise MeshImportError(
            f"the anchors file says units {file_units!r} but units {units!r} was passed; "
            f'pass --units {file_units} or fix the file\'s "units"'
        )
    return units or file_units or "m"


def _check_file(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise MeshImportError(
            f"{path}: unknown mesh extension {path.suffix!r}; expected one of {sorted(FORMATS)} "
            "(convert the file, e.g. with Blender or meshlab)"
        )
    if not path.is_file():
        raise MeshImportError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise MeshImportError(f"{path}: the file is empty; expected a {suffix[1:].upper()} mesh")
    return FORMATS[suffix]


def _load(path: Path, file_type: str) -> trimesh.Trimesh:
    """Read the file as one triangle mesh (scenes are concatenated), geometry only."""
    try:
        # process=False: keep the raw data so non-finite vertices are seen, not silently dropped.
        loaded = trimesh.load(path, file_type=file_type, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for malformed files
        raise MeshImportError(
            f"{path}: cannot read it as {file_type.upper()} ({type(exc).__name__}: {exc}); "
            "check that the file is complete and has the right extension"
        ) from exc
    faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))))
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64)
    if not isinstance(loaded, trimesh.Trimesh) or len(faces) == 0:
        raise MeshImportError(
            f"{path}: expected a triangle mesh, found no faces (a point cloud or an empty scene?); "
            "export the object as a surface mesh"
        )
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise MeshImportError(
            f"{path}: {int(bad.sum())} of {len(vertices)} vertices are not finite (NaN or inf), "
            f"e.g. vertex {int(np.argmax(bad))}; repair or re-export the mesh"
        )
    return trimesh.Trimesh(vertices, faces, process=False)


# -- repair and checks ------------------------------------------------------------------------


def _repair(mesh: trimesh.Trimesh, path: Path) -> dict[str, Any]:
    """Repair in place what can be repaired; returns what was done (recorded in the asset's params)."""
    n_vertices, n_faces = len(mesh.vertices), len(mesh.faces)
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    merged = n_vertices - len(mesh.vertices)

    before = len(mesh.faces)
    mesh.update_faces(mesh.nondegenerate_faces())
    degenerate = before - len(mesh.faces)
    before = len(mesh.faces)
    mesh.update_faces(mesh.unique_faces())
    duplicate = before - len(mesh.faces)
    before = len(mesh.vertices)
    mesh.remove_unreferenced_vertices()
    unreferenced = before - len(mesh.vertices)
    if len(mesh.faces) == 0:
        raise MeshImportError(f"{path}: all {n_faces} faces are degenerate (zero area); nothing to import")

    before = len(mesh.faces)
    trimesh.repair.fill_holes(mesh)  # triangle and quad holes only: larger ones are not guessed at
    filled = len(mesh.faces) - before
    # Consistent winding, outward normals, per connected body (a mug may come as several shells).
    trimesh.repair.fix_normals(mesh, multibody=True)
    if mesh.is_watertight and mesh.volume < 0:
        mesh.invert()

    if mesh.body_count > 1:
        log.warning(
            "%s: the mesh has %d separate components; all are kept (check for stray fragments)",
            path,
            mesh.body_count,
        )
    if not mesh.is_watertight:
        log.warning(
            "%s: the mesh is not watertight after repair (holes larger than a quad?); it is kept as "
            "the visual mesh, and mass properties come from the convex collision parts",
            path,
        )
    return {
        "merged_vertices": merged,
        "degenerate_faces": degenerate,
        "duplicate_faces": duplicate,
        "unreferenced_vertices": unreferenced,
        "filled_hole_faces": filled,
        "components": int(mesh.body_count),
        "watertight": bool(mesh.is_watertight),
    }


def _check_has_volume(mesh: trimesh.Trimesh, path: Path) -> None:
    """Refuse flat (coplanar) or thin (collinear) meshes: no object to grasp, no mass."""
    centred = mesh.vertices - mesh.vertices.mean(axis=0)
    _, _, axes = np.linalg.svd(centred, full_matrices=False)
    extents = np.ptp(centred @ axes.T, axis=0)
    flat = extents.max() <= 0 or extents.min() < _FLATNESS * extents.max()
    if not flat:
        try:
            hull_volume = trimesh.convex.convex_hull(mesh.vertices).volume
        except Exception:  # qhull refuses degenerate input: that is a flat mesh too
            hull_volume = 0.0
        flat = hull_volume <= 1e-10 * extents.max() ** 3
    if flat:
        raise MeshImportError(
            f"{path}: the mesh has no volume (principal extents {np.round(extents, 6).tolist()} in file "
            "units: all points are nearly coplanar or collinear); expected a solid object, not a "
            "plane, a single face or a wire"
        )


def _check_size(raw_extent: float, units: str, scale: float, path: Path) -> None:
    """The largest extent must be object-sized; suggest the unit that would make it so."""
    lo, hi = SIZE_RANGE
    size = raw_extent * UNITS[units] * scale
    if lo <= size <= hi:
        return
    plausible = [u for u in UNITS if lo <= raw_extent * UNITS[u] * scale <= hi]
    if plausible:
        # Of the units that fit, prefer the one giving the size closest to a typical 15 cm object.
        best = min(plausible, key=lambda u: abs(math.log(raw_extent * UNITS[u] * scale / 0.15)))
        hint = f"is the file in {best}? pass --units {best}"
    else:
        hint = "pass --scale or --target-size to set the size"
    raise MeshImportError(
        f"{path}: largest extent is {size:.4g} m with units {units!r} and scale {scale}, expected "
        f"between {lo} and {hi} m; {hint}"
    )


def _warn_if_floating(canonical: np.ndarray, path: Path) -> None:
    height = float(np.ptp(canonical, axis=0).max())
    min_z = float(canonical[:, 2].min())
    if abs(min_z) > max(0.002, 0.02 * height):
        log.warning(
            "%s: in the given frame the mesh's lowest point is at z = %.4f m, not 0; the frame is kept "
            "as given (move the frame origin to the base if the object should rest on z = 0)",
            path,
            min_z,
        )


# -- frame and anchors ------------------------------------------------------------------------


def _read_anchors_file(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise MeshImportError(f"anchors file {path} does not exist; {_ANCHORS_HELP}")
    try:
        spec = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise MeshImportError(f"anchors file {path} is not valid JSON ({exc}); {_ANCHORS_HELP}") from exc
    if not isinstance(spec, dict):
        raise MeshImportError(f"anchors file {path}: expected a JSON object, got {type(spec).__name__}")
    unknown = sorted(set(spec) - _JSON_KEYS)
    if unknown:
        raise MeshImportError(
            f"anchors file {path}: unknown keys {unknown}; expected only {sorted(_JSON_KEYS)}; "
            f"{_ANCHORS_HELP}"
        )
    return spec


def _vector(value: Any, what: str) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        v = np.zeros(0)
    if v.shape != (3,) or not np.isfinite(v).all():
        raise MeshImportError(f"anchors file: {what} must be 3 finite numbers [x, y, z], got {value!r}")
    return v


def _default_frame(file_type: str) -> _Frame:
    if file_type in ("glb", "gltf"):
        # glTF 2.0: +y up, +z front; canonical y = up x front = +x.
        rotation = np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]])
    else:
        rotation = np.eye(3)
    return _Frame(np.zeros(3), rotation, given=False)


def _parse_frame(frame: Any, file_type: str) -> _Frame:
    if frame is None:
        return _default_frame(file_type)
    if not isinstance(frame, dict):
        raise MeshImportError(f"anchors file: frame must be an object; {_ANCHORS_HELP}")
    unknown = sorted(set(frame) - _FRAME_KEYS)
    if unknown:
        raise MeshImportError(f"anchors file: unknown frame keys {unknown}; expected {sorted(_FRAME_KEYS)}")
    origin = _vector(frame.get("origin", [0, 0, 0]), "frame.origin")
    up = _vector(frame.get("up", [0, 0, 1]), "frame.up")
    front = _vector(frame.get("front", [1, 0, 0]), "frame.front")
    if np.linalg.norm(up) < 1e-9:
        raise MeshImportError("anchors file: frame.up cannot be the zero vector")
    up = up / np.linalg.norm(up)
    front = front - np.dot(front, up) * up  # orthogonalise against up
    if np.linalg.norm(front) < 1e-6:
        raise MeshImportError(
            f"anchors file: frame.front {frame.get('front')} is zero or parallel to frame.up "
            f"{frame.get('up')}; give a front direction perpendicular to up"
        )
    front = front / np.linalg.norm(front)
    rotation = np.stack([front, np.cross(up, front), up])
    return _Frame(origin, rotation, given=True)


def _parse_anchors(
    raw: Any, category: str, frame: _Frame, factor: float, path: str | os.PathLike | None
) -> dict[str, Anchor]:
    expected = CATEGORY_ANCHORS[category]
    listing = ", ".join(f"{name} ({kind})" for name, kind in expected.items())
    if not isinstance(raw, dict):
        raise MeshImportError(
            f"anchors file {path}: anchors must be an object {{name: value}}; expected {listing}"
        )
    optional = OPTIONAL_ANCHORS.get(category, {})
    missing = [name for name in expected if name not in raw]
    unknown = sorted(set(raw) - set(expected) - set(optional))
    if missing or unknown:
        extra = f" (optional: {', '.join(optional)})" if optional else ""
        raise MeshImportError(
            f"anchors file {path}: a {category} needs exactly the anchors {listing}{extra}; "
            f"missing {missing}, unknown {unknown}"
        )
    anchors = {}
    for name, kind in {**expected, **optional}.items():
        if name in raw:
            anchors[name] = _anchor_from_file(name, kind, raw[name], frame, factor, path)
    return anchors


def _anchor_from_file(
    name: str, kind: str, value: Any, frame: _Frame, factor: float, path: str | os.PathLike | None
) -> Anchor:
    try:
        v = np.atleast_1d(np.asarray(value, dtype=np.float64))
    except (TypeError, ValueError):
        v = np.zeros(0)
    length = 1 if kind == "scalar" else 3
    shape = "a length r or [r]" if kind == "scalar" else "[x, y, z]"
    if v.shape != (length,) or not np.isfinite(v).all():
        raise MeshImportError(
            f"anchors file {path}: anchor {name!r} is a {kind} and needs {shape} ({length} finite "
            f"number{'s' if length > 1 else ''}), got {value!r}"
        )
    if kind == "point":
        return Anchor("point", factor * (frame.rotation @ (v - frame.origin)))
    if kind == "direction":
        if np.linalg.norm(v) < 1e-9:
            raise MeshImportError(f"anchors file {path}: direction anchor {name!r} cannot be the zero vector")
        return Anchor("direction", frame.rotation @ v)
    if v[0] <= 0:
        raise MeshImportError(
            f"anchors file {path}: scalar anchor {name!r} is a length and must be > 0, got {v[0]}"
        )
    return Anchor("scalar", factor * v)


def _anchor_to_file(anchor: Anchor, rotation: np.ndarray, translation: np.ndarray, to_file: float) -> Any:
    if anchor.kind == "point":
        return ((rotation @ anchor.value + translation) * to_file).tolist()
    if anchor.kind == "direction":
        return (rotation @ anchor.value).tolist()
    return float(anchor.value[0] * to_file)


def _warn_if_anchors_outside(anchors: dict[str, Anchor], visual: trimesh.Trimesh, path: Path) -> None:
    """Points far outside the mesh's box usually mean a wrong frame or unit in the anchors file."""
    lo, hi = visual.bounds
    margin = 0.5 * float(np.max(hi - lo))
    for name, anchor in anchors.items():
        if anchor.kind == "point" and (
            np.any(anchor.value < lo - margin) or np.any(anchor.value > hi + margin)
        ):
            log.warning(
                "%s: anchor %r at %s m lies far outside the mesh's bounding box %s; check the anchors "
                "file's units and frame",
                path,
                name,
                np.round(anchor.value, 4).tolist(),
                np.round(visual.bounds, 4).tolist(),
            )


# -- collision and mass -----------------------------------------------------------------------


def _hull_part(mesh: trimesh.Trimesh) -> ConvexPart:
    return ConvexPart("mesh", vertices=np.asarray(mesh.convex_hull.vertices))


def _coacd_parts(mesh: trimesh.Trimesh, threshold: float, max_parts: int, path: Path) -> list[ConvexPart]:
    """Approximate convex decomposition with CoACD (seeded, so the parts are reproducible)."""
    import coacd  # imported here: it loads a native library, and "hull" imports do not need it

    coacd.set_log_level("error")
    pieces = coacd.run_coacd(
        coacd.Mesh(np.asarray(mesh.vertices), np.asarray(mesh.faces)),
        threshold=threshold,
        max_convex_hull=max_parts,
        preprocess_mode="auto",
        seed=0,
    )
    parts = []
    for vertices, _faces in pieces:
        try:
            parts.append(ConvexPart("mesh", vertices=np.asarray(vertices, dtype=np.float64)))
        except Exception:  # a flat sliver: qhull or ConvexPart refuses it, and it adds no volume
            continue
    if not parts:
        log.warning("%s: CoACD returned no usable parts; using the convex hull as the collision shape", path)
        return [_hull_part(mesh)]
    return parts


def _mass_properties(
    visual: trimesh.Trimesh, parts: list[ConvexPart], density: float, path: Path
) -> MassProperties:
    if visual.is_volume:
        return MassProperties.from_mesh(visual, density)
    # Not a closed volume: the convex parts are the best solid we have (overlaps count twice).
    log.warning(
        "%s: mass properties come from %d convex collision parts (mesh not watertight)", path, len(parts)
    )
    return MassProperties.combine([MassProperties.from_mesh(p.to_trimesh(), density) for p in parts])
