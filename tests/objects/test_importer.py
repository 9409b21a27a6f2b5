"""Mesh import: formats, repair, units, canonical frame and anchors, collision, refusal of bad input."""

import json
import logging
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from keygen.errors import InvalidParameterError, MeshImportError, MissingAnchorsError
from keygen.objects.asset import Anchor, Asset, MassProperties
from keygen.objects.importer import DEFAULT_DENSITY, export_for_import, import_mesh
from keygen.objects.meshing import hull_part, revolve_profile, sweep_tube, union

MUG_PROFILE = np.array([(0, 0), (0.04, 0), (0.04, 0.1), (0.036, 0.1), (0.036, 0.006), (0, 0.006)])


def mug_mesh(sections: int = 32, handle_points: int = 16, sides: int = 10) -> trimesh.Trimesh:
    """A watertight mug: a revolved cup (r 4 cm, h 10 cm) with a swept handle on +x."""
    body = revolve_profile(MUG_PROFILE, sections)
    t = np.linspace(-np.pi / 2, np.pi / 2, handle_points)
    path = np.stack([0.038 + 0.03 * np.cos(t), 0 * t, 0.055 + 0.028 * np.sin(t)], axis=1)
    return union([body, sweep_tube(path, 0.006, 0.004, sides)])


def mug_asset(mesh: trimesh.Trimesh) -> Asset:
    anchors = {
        "handle_grasp": Anchor("point", [0.068, 0.0, 0.055]),
        "grasp_approach": Anchor("direction", [0.0, 0.0, -1.0]),
        "handle_center": Anchor("point", [0.053, 0.0, 0.055]),
        "pour_point": Anchor("point", [-0.04, 0.0, 0.1]),
        "opening_center": Anchor("point", [0.0, 0.0, 0.1]),
        "bottom_center": Anchor("point", [0.0, 0.0, 0.0]),
    }
    return Asset(
        "mug", "mug-ref", mesh, [hull_part(mesh.vertices)], MassProperties.from_mesh(mesh, 2200.0), anchors
    )


@pytest.fixture(scope="module")
def mug() -> trimesh.Trimesh:
    return mug_mesh()


@pytest.fixture
def mug_ref(mug) -> Asset:
    return mug_asset(mug.copy())


def rigid(seed: int, max_offset: float = 0.3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    tf = np.eye(4)
    tf[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    tf[:3, 3] = rng.uniform(-max_offset, max_offset, 3)
    return tf


def assert_same_anchors(a: Asset, b: Asset, atol: float = 1e-6) -> None:
    assert set(a.anchors) == set(b.anchors)
    for name, anchor in b.anchors.items():
        assert a.anchors[name].kind == anchor.kind
        np.testing.assert_allclose(a.anchors[name].value, anchor.value, atol=atol, err_msg=name)


# -- round trips ----------------------------------------------------------------------------


@pytest.mark.parametrize(("units", "fmt", "seed"), [("mm", "obj", 1), ("cm", "stl", 2), ("in", "ply", 3)])
def test_round_trip_through_rotated_frame_and_units(tmp_path, mug_ref, units, fmt, seed):
    mesh_path, anchors_path = export_for_import(
        mug_ref, tmp_path, units=units, transform=rigid(seed), mesh_format=fmt
    )
    spec = json.loads(anchors_path.read_text())
    assert spec["units"] == units and set(spec["anchors"]) == set(mug_ref.anchors)
    # the file really is in other coordinates: its box differs from the canonical one
    assert not np.allclose(trimesh.load(mesh_path, force="mesh").bounds, mug_ref.bbox, atol=1e-3)

    asset = import_mesh(mesh_path, "mug", anchors_path=anchors_path, collision="hull")
    np.testing.assert_allclose(asset.bbox, mug_ref.bbox, atol=1e-5)
    assert asset.visual.volume == pytest.approx(mug_ref.visual.volume, rel=0.01)
    assert asset.mass == pytest.approx(mug_ref.mass, rel=0.01)
    np.testing.assert_allclose(asset.mass_properties.com, mug_ref.mass_properties.com, atol=1e-5)
    assert_same_anchors(asset, mug_ref)
    assert asset.params["units"] == units and asset.params["frame"] == "anchors_file"


@settings(
    max_examples=8,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(seed=st.integers(0, 10_000), units=st.sampled_from(["mm", "cm", "m", "in"]))
def test_round_trip_property_scalar_anchor(tmp_path_factory, bowl_asset, seed, units):
    ref = bowl_asset  # from conftest; not modified here
    folder = tmp_path_factory.mktemp("bowl")
    mesh_path, anchors_path = export_for_import(ref, folder, units=units, transform=rigid(seed))
    asset = import_mesh(mesh_path, "bowl", anchors_path=anchors_path, collision="hull")
    assert_same_anchors(asset, ref)  # rim_radius is a scalar: scaled back, never rotated
    np.testing.assert_allclose(asset.bbox, ref.bbox, atol=1e-5)


def test_frame_written_by_hand_is_applied(tmp_path, mug_ref):
    """Independent of export_for_import: a y-up, -z-front file in cm with a shifted origin."""
    # columns: where canonical x (front), y (= up x front) and z (up) point in the file
    to_file = np.column_stack([[0.0, 0, -1], [-1, 0, 0], [0, 1, 0]])
    assert np.linalg.det(to_file) == pytest.approx(1.0)
    offset_cm = np.array([5.0, -2.0, 7.0])
    mesh = mug_ref.visual.copy()
    mesh.vertices = (mesh.vertices @ to_file.T) * 100 + offset_cm
    mesh.export(tmp_path / "mug.obj")
    handle_file = (to_file @ [0.068, 0, 0.055]) * 100 + offset_cm
    spec = {
        "units": "cm",
        "frame": {
            "origin": offset_cm.tolist(),
            "up": [0, 2, 0],
            "front": [0, 0.3, -1],
        },  # not unit, not orthogonal
        "anchors": {
            "handle_grasp": handle_file.tolist(),
            "grasp_approach": [0, -1, 0],
            "handle_center": ((to_file @ [0.053, 0, 0.055]) * 100 + offset_cm).tolist(),
            "pour_point": ((to_file @ [-0.04, 0, 0.1]) * 100 + offset_cm).tolist(),
            "opening_center": ((to_file @ [0, 0, 0.1]) * 100 + offset_cm).tolist(),
            "bottom_center": offset_cm.tolist(),
        },
    }
    (tmp_path / "mug.json").write_text(json.dumps(spec))
    asset = import_mesh(tmp_path / "mug.obj", "mug", anchors_path=tmp_path / "mug.json", collision="hull")
    np.testing.assert_allclose(asset.bbox, mug_ref.bbox, atol=1e-6)
    np.testing.assert_allclose(asset.anchor("handle_grasp"), [0.068, 0, 0.055], atol=1e-9)
    np.testing.assert_allclose(asset.anchor("grasp_approach"), [0, 0, -1], atol=1e-9)
    np.testing.assert_allclose(asset.anchor("bottom_center"), [0, 0, 0], atol=1e-9)


# -- formats, placement without anchors ---------------------------------------------------------


@pytest.mark.parametrize("fmt", ["obj", "stl", "ply", "glb"])
def test_each_format_loads_and_is_placed_on_the_ground(tmp_path, mug, fmt):
    mesh = mug.copy()
    mesh.apply_translation([0.3, -0.2, 0.5])  # off-centre and floating: placement must undo it
    if fmt == "glb":
        # glTF is y-up: write canonical z as file +y, canonical x as file +z
        mesh.vertices = mesh.vertices[:, [1, 2, 0]]
    path = tmp_path / f"cup_{fmt}.{fmt}"
    mesh.export(path)
    asset = import_mesh(path, "mug", collision="hull")

    lo, hi = asset.bbox
    assert lo[2] == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose((lo[:2] + hi[:2]) / 2, 0.0, atol=1e-9)
    np.testing.assert_allclose(hi - lo, np.ptp(mug.vertices, axis=0), atol=1e-6)
    assert asset.visual.is_watertight
    assert asset.anchors is None
    with pytest.raises(MissingAnchorsError, match="--anchors"):
        asset.require_anchors("pour")
    assert asset.instance_id == f"cup_{fmt}" and asset.source == "imported"
    assert asset.params["source_file"] == path.name and asset.params["frame"] == "auto"
    assert asset.mass == pytest.approx(mug.volume * DEFAULT_DENSITY["mug"], rel=1e-3)


def test_glb_scene_is_concatenated_and_components_warned(tmp_path, caplog):
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.creation.box(extents=[0.05, 0.05, 0.02]))
    scene.add_geometry(
        trimesh.creation.icosphere(radius=0.02),
        transform=trimesh.transformations.translation_matrix([0, 0.1, 0]),
    )
    scene.export(tmp_path / "two.glb")
    with caplog.at_level(logging.WARNING, logger="keygen.objects.importer"):
        asset = import_mesh(tmp_path / "two.glb", "bowl", collision="hull")
    assert asset.visual.body_count == 2
    assert asset.params["repairs"]["components"] == 2
    assert "2 separate components" in caplog.text
    # glTF +y (where the sphere sits) is canonical up: box from y -0.025, sphere up to y 0.12
    assert np.ptp(asset.visual.vertices[:, 2]) == pytest.approx(0.145, abs=1e-6)


def test_density_defaults_per_category_and_override(tmp_path):
    trimesh.creation.box(extents=[0.2, 0.03, 0.01]).export(tmp_path / "bar.stl")
    knife = import_mesh(tmp_path / "bar.stl", "knife", collision="hull")
    assert knife.mass == pytest.approx(0.2 * 0.03 * 0.01 * 3000.0, rel=1e-6)
    light = import_mesh(tmp_path / "bar.stl", "knife", collision="hull", density=1000.0)
    assert light.mass == pytest.approx(knife.mass / 3, rel=1e-6)


def test_scale_and_target_size(tmp_path, mug):
    mug.export(tmp_path / "m.obj")
    base = import_mesh(tmp_path / "m.obj", "mug", collision="hull")
    double = import_mesh(tmp_path / "m.obj", "mug", collision="hull", scale=2.0)
    np.testing.assert_allclose(double.bbox, base.bbox * 2, atol=1e-9)
    assert double.mass == pytest.approx(base.mass * 8, rel=1e-6)
    sized = import_mesh(tmp_path / "m.obj", "mug", collision="hull", units="mm", target_size=0.25)
    assert np.ptp(sized.bbox, axis=0).max() == pytest.approx(0.25)
    assert sized.params["scale_applied"] == pytest.approx(0.25 / np.ptp(mug.vertices, axis=0).max())
    with pytest.raises(InvalidParameterError, match="not both"):
        import_mesh(tmp_path / "m.obj", "mug", collision="hull", scale=2.0, target_size=0.2)


# -- repair -----------------------------------------------------------------------------------


def test_small_hole_and_duplicates_are_repaired(tmp_path, mug):
    faces = np.vstack([mug.faces[1:], mug.faces[5:7]])  # one face missing, two duplicated
    broken = trimesh.Trimesh(mug.vertices, faces, process=False)
    assert not broken.is_watertight
    broken.export(tmp_path / "holed.obj")
    asset = import_mesh(tmp_path / "holed.obj", "mug", collision="hull")
    assert asset.visual.is_watertight and asset.visual.is_volume
    repairs = asset.params["repairs"]
    assert repairs["filled_hole_faces"] == 1 and repairs["duplicate_faces"] == 2 and repairs["watertight"]
    assert asset.visual.volume == pytest.approx(mug.volume, rel=1e-3)


def test_inverted_winding_is_fixed(tmp_path, mug):
    inverted = mug.copy()
    inverted.invert()
    inverted.export(tmp_path / "inv.ply")
    asset = import_mesh(tmp_path / "inv.ply", "mug", collision="hull")
    assert asset.visual.volume == pytest.approx(mug.volume, rel=1e-6)


def test_large_hole_kept_open_mass_from_parts(tmp_path, caplog):
    body = revolve_profile(MUG_PROFILE, 32)
    rim = np.all(np.isclose(body.vertices[body.faces][:, :, 2], 0.1), axis=1)
    open_mesh = trimesh.Trimesh(body.vertices, body.faces[~rim], process=False)
    open_mesh.export(tmp_path / "open.obj")
    with caplog.at_level(logging.WARNING, logger="keygen.objects.importer"):
        asset = import_mesh(tmp_path / "open.obj", "mug", tmp_path / "out", collision="hull")
    assert "not watertight" in caplog.text
    assert not asset.visual.is_watertight
    hull_volume = asset.collision[0].to_trimesh().volume
    assert asset.mass == pytest.approx(hull_volume * DEFAULT_DENSITY["mug"], rel=1e-6)
    assert json.loads((tmp_path / "out" / "meta.json").read_text())["watertight"] is False


# -- broken input -----------------------------------------------------------------------------


def _write_nan(path: Path) -> None:
    path.write_text("v 0 0 0\nv 0.1 0 0\nv nan 0.1 0\nv 0 0 0.1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")


def _write_triangle(path: Path) -> None:
    path.write_text("v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nf 1 2 3\n")


def _write_plane(path: Path) -> None:
    # a closed but flat double-sided square: watertight after merging, yet no volume
    path.write_text("v 0 0 0\nv 0.1 0 0\nv 0.1 0.1 0\nv 0 0.1 0\nf 1 2 3\nf 1 3 4\nf 1 3 2\nf 1 4 3\n")


def _write_line(path: Path) -> None:
    path.write_text("v 0 0 0\nv 0.1 0 0\nv 0.2 0 0\nv 0.3 0 1e-9\nf 1 2 3\nf 2 3 4\n")


BROKEN = {
    "empty.obj": (lambda p: p.write_text(""), "empty"),
    "empty.glb": (lambda p: p.write_bytes(b""), "empty"),
    "garbage.ply": (lambda p: p.write_text("this is not a ply file\n"), "cannot read"),
    "nan.obj": (_write_nan, "not finite"),
    "triangle.obj": (_write_triangle, "no volume"),
    "plane.obj": (_write_plane, "no volume"),
    "line.obj": (_write_line, "no volume|degenerate"),
    "points.obj": (lambda p: p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n"), "no faces"),
    "model.fbx": (lambda p: p.write_text("fbx"), "unknown mesh extension"),
    "missing.stl": (lambda p: None, "no such file"),
}


@pytest.mark.parametrize("name", sorted(BROKEN))
def test_broken_files_raise_and_write_nothing(tmp_path, name):
    write, message = BROKEN[name]
    path = tmp_path / name
    write(path)
    out = tmp_path / "out"
    with pytest.raises(MeshImportError, match=message):
        import_mesh(path, "mug", out, collision="hull")
    assert not out.exists()
    # an existing asset folder is left untouched
    out.mkdir()
    (out / "keep.txt").write_text("x")
    with pytest.raises(MeshImportError):
        import_mesh(path, "mug", out, collision="hull")
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    # and no half-written temporary folder is left beside it
    assert {p.name for p in tmp_path.iterdir()} <= {name, "out"}


def _good_spec() -> dict:
    return {
        "units": "m",
        "anchors": {
            "handle_grasp": [0.068, 0, 0.055],
            "grasp_approach": [0, 0, -1],
            "handle_center": [0.053, 0, 0.055],
            "pour_point": [-0.04, 0, 0.1],
            "opening_center": [0, 0, 0.1],
            "bottom_center": [0, 0, 0],
        },
    }


def _spec_without(key: str) -> dict:
    spec = _good_spec()
    del spec["anchors"][key]
    return spec


def _spec_with(path: tuple, value) -> dict:
    spec = _good_spec()
    target = spec
    for key in path[:-1]:
        target = target.setdefault(key, {})
    target[path[-1]] = value
    return spec


BAD_ANCHORS = {
    "not_json": ("{units: mm", "not valid JSON"),
    "list": ([1, 2, 3], "expected a JSON object"),
    "missing": (
        _spec_without("pour_point"),
        r"needs exactly the anchors handle_grasp \(point\).*missing \['pour_point'\]",
    ),
    "unknown": (_spec_with(("anchors", "spout"), [0, 0, 0]), r"unknown \['spout'\]"),
    "short": (_spec_with(("anchors", "handle_grasp"), [0.1, 0.2]), "needs \\[x, y, z\\]"),
    "zero_dir": (_spec_with(("anchors", "grasp_approach"), [0, 0, 0]), "zero vector"),
    "typo_key": (_spec_with(("anchor",), {}), r"unknown keys \['anchor'\]"),
    "bad_units": (_spec_with(("units",), "furlong"), "units must be one of"),
    "front_up": (_spec_with(("frame",), {"up": [0, 0, 1], "front": [0, 0, 2]}), "parallel"),
    "frame_key": (_spec_with(("frame",), {"centre": [0, 0, 0]}), r"unknown frame keys \['centre'\]"),
    "units_conflict": (_spec_with(("units",), "mm"), "pass --units mm"),
}


@pytest.mark.parametrize("case", sorted(BAD_ANCHORS))
def test_bad_anchors_file_raises_and_writes_nothing(tmp_path, mug, case):
    spec, message = BAD_ANCHORS[case]
    mug.export(tmp_path / "m.obj")
    anchors = tmp_path / "a.json"
    anchors.write_text(spec if isinstance(spec, str) else json.dumps(spec))
    units = "m" if case == "units_conflict" else None
    with pytest.raises(MeshImportError, match=message):
        import_mesh(
            tmp_path / "m.obj", "mug", tmp_path / "out", anchors_path=anchors, units=units, collision="hull"
        )
    assert not (tmp_path / "out").exists()


def test_good_anchors_spec_passes(tmp_path, mug):
    """The control for the cases above: the unmodified spec imports."""
    mug.export(tmp_path / "m.obj")
    (tmp_path / "a.json").write_text(json.dumps(_good_spec()))
    asset = import_mesh(tmp_path / "m.obj", "mug", anchors_path=tmp_path / "a.json", collision="hull")
    np.testing.assert_allclose(asset.anchor("pour_point"), [-0.04, 0, 0.1])


@pytest.mark.parametrize(
    ("factor", "units", "hint"),
    [(1000.0, "m", "--units mm"), (1.0, "mm", "--units m"), (100, "m", "--units cm")],
)
def test_size_check_suggests_units(tmp_path, mug, factor, units, hint):
    mesh = mug.copy()
    mesh.apply_scale(factor)
    mesh.export(tmp_path / "m.stl")
    with pytest.raises(MeshImportError, match="largest extent is") as err:
        import_mesh(tmp_path / "m.stl", "mug", units=units, collision="hull")
    assert hint in str(err.value)


def test_bad_arguments(tmp_path, mug):
    mug.export(tmp_path / "m.obj")
    for kwargs in (
        {"units": "furlong"},
        {"scale": -1.0},
        {"collision": "vhacd"},
        {"density": 0.0},
        {"max_parts": 0},
    ):
        with pytest.raises(InvalidParameterError):
            import_mesh(tmp_path / "m.obj", "mug", **kwargs)
    with pytest.raises(InvalidParameterError):
        import_mesh(tmp_path / "m.obj", "spoon")


def test_user_frame_kept_when_mesh_floats(tmp_path, mug, caplog):
    mug.copy().apply_translation([0, 0, 0.05]).export(tmp_path / "m.obj")
    (tmp_path / "a.json").write_text(json.dumps({"frame": {"origin": [0, 0, 0]}}))
    with caplog.at_level(logging.WARNING, logger="keygen.objects.importer"):
        asset = import_mesh(tmp_path / "m.obj", "mug", anchors_path=tmp_path / "a.json", collision="hull")
    assert asset.bbox[0, 2] == pytest.approx(0.05)
    assert asset.anchors is None  # a frame-only file sets the frame, not anchors
    assert "lowest point" in caplog.text


def test_anchors_without_frame_keep_file_coordinates(tmp_path, mug):
    """No frame: file axes and origin are kept, so anchors given in file coordinates still fit the mesh."""
    mug.copy().apply_translation([0.1, 0.0, 0.0]).export(tmp_path / "m.obj")
    spec = _good_spec()
    spec["anchors"]["bottom_center"] = [0.1, 0, 0]
    (tmp_path / "a.json").write_text(json.dumps(spec))
    asset = import_mesh(tmp_path / "m.obj", "mug", anchors_path=tmp_path / "a.json", collision="hull")
    assert asset.params["frame"] == "file_axes"
    np.testing.assert_allclose(asset.bbox, mug.bounds + [0.1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(asset.anchor("bottom_center"), [0.1, 0, 0])


# -- storage and collision --------------------------------------------------------------------


def test_saved_asset_loads_back(tmp_path, mug_ref):
    mesh_path, anchors_path = export_for_import(mug_ref, tmp_path / "export")
    asset = import_mesh(
        mesh_path, "mug", tmp_path / "lib" / "mug-1", anchors_path=anchors_path, collision="hull"
    )
    loaded = Asset.load(tmp_path / "lib" / "mug-1")
    assert loaded.source == "imported" and loaded.instance_id == "mug-ref"
    assert loaded.params["source_file"] == "mug-ref.obj"
    assert loaded.mass == pytest.approx(asset.mass)
    np.testing.assert_allclose(loaded.bbox, asset.bbox, atol=1e-7)
    assert_same_anchors(loaded, mug_ref)
    assert json.loads((tmp_path / "lib" / "mug-1" / "meta.json").read_text())["watertight"] is True


def test_coacd_decomposition(tmp_path):
    mesh = mug_mesh(sections=24, handle_points=10, sides=8)
    mesh.export(tmp_path / "mug.obj")
    asset = import_mesh(tmp_path / "mug.obj", "mug", collision="coacd", coacd_threshold=0.5, max_parts=6)
    assert 2 <= len(asset.collision) <= 6
    parts = asset.collision_meshes()
    assert all(p.is_convex and p.volume > 0 for p in parts)
    # the parts cover the object: together they span its box and hold at least its volume
    lo = np.min([p.bounds[0] for p in parts], axis=0)
    hi = np.max([p.bounds[1] for p in parts], axis=0)
    np.testing.assert_allclose(lo, asset.bbox[0], atol=0.005)
    np.testing.assert_allclose(hi, asset.bbox[1], atol=0.005)
    assert sum(p.volume for p in parts) > 0.9 * asset.visual.volume
    assert asset.mass == pytest.approx(mesh.volume * DEFAULT_DENSITY["mug"], rel=1e-3)  # from the mesh
    # CoACD runs seeded: the same file gives the same parts
    again = import_mesh(tmp_path / "mug.obj", "mug", collision="coacd", coacd_threshold=0.5, max_parts=6)
    assert len(again.collision) == len(asset.collision)
    for a, b in zip(again.collision, asset.collision, strict=True):
        np.testing.assert_allclose(a.vertices, b.vertices)


def test_export_refuses_mirroring_transform(tmp_path, mug_ref):
    with pytest.raises(InvalidParameterError, match="mirror"):
        export_for_import(mug_ref, tmp_path, transform=np.diag([1.0, 1.0, -1.0, 1.0]))
