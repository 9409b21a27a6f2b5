"""Tests of the knife generator: validity, collision fidelity, anchors, variation and functional shape."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull

from keygen.errors import InvalidParameterError, KeyGenError
from keygen.objects.asset import CATEGORY_ANCHORS, Anchor, Asset
from keygen.objects.generators.knife import HANDLE_SHAPES, PARAM_KEYS, KnifeGenerator
from keygen.objects.meshing import distance_to_solid
from keygen.objects.splits import get_generator

GEN = KnifeGenerator()
MM = 1e-3


def _sample(count: int, seed: int, cycle_styles: bool = True) -> list[dict]:
    rng = np.random.default_rng(seed)
    return [
        GEN.sample_params(rng, GEN.styles[i % len(GEN.styles)] if cycle_styles else None)
        for i in range(count)
    ]


PARAMS = _sample(40, seed=20240611)


@pytest.fixture(scope="module")
def assets() -> list[Asset]:
    return [GEN.build(p, f"knife-test-{i:03d}") for i, p in enumerate(PARAMS)]


def _section(mesh: trimesh.Trimesh, x: float) -> np.ndarray:
    """End points of the segments of the mesh's cross-section by the plane at ``x``."""
    seg = trimesh.intersections.mesh_plane(mesh, plane_normal=[1.0, 0, 0], plane_origin=[x, 0, 0])
    return np.asarray(seg).reshape(-1, 3)


def _halfspaces(asset: Asset) -> list[np.ndarray]:
    """Each collision part as hull facet equations (n . p + d <= 0 inside)."""
    return [ConvexHull(part.to_trimesh().vertices).equations for part in asset.collision]


def _outside_parts(asset: Asset, points: np.ndarray) -> np.ndarray:
    """For each point, the smallest over parts of its largest facet excess (<= 0: inside some part).

    A lower bound on the distance to the union of parts; exact when the nearest feature is a face.
    """
    excess = [np.max(points @ eq[:, :3].T + eq[:, 3], axis=1) for eq in _halfspaces(asset)]
    return np.min(np.stack(excess), axis=0)


# -- the generator and its parameters ---------------------------------------------------------------


def test_registry_loads_the_knife_generator():
    gen = get_generator("knife")
    assert isinstance(gen, KnifeGenerator)
    assert gen.category == "knife"
    assert set(gen.styles) == {"chef", "paring", "bread", "cleaver", "santoku", "utility"}


def test_params_are_plain_json_with_every_key():
    for style in GEN.styles:
        p = GEN.sample_params(np.random.default_rng(7), style=style)
        assert p["style"] == style
        assert tuple(sorted(p)) == tuple(sorted(PARAM_KEYS))
        assert all(type(v) in (float, int, str) for v in p.values())
        assert json.loads(json.dumps(p)) == p


def test_sampling_is_seeded_and_covers_styles_and_handle_shapes():
    assert _sample(40, seed=20240611) == PARAMS
    assert {p["style"] for p in PARAMS} == set(GEN.styles)
    assert {p["handle_shape"] for p in PARAMS} == set(HANDLE_SHAPES)
    assert any(p["bolster_length"] > 0 for p in PARAMS) and any(p["bolster_length"] == 0 for p in PARAMS)


def test_unknown_style_and_bad_params_raise_clear_errors():
    with pytest.raises(InvalidParameterError, match="style"):
        GEN.sample_params(np.random.default_rng(0), style="sword")
    good = PARAMS[0]
    with pytest.raises(InvalidParameterError, match="lack"):
        GEN.build({k: v for k, v in good.items() if k != "blade_width"}, "bad")
    with pytest.raises(KeyGenError, match="edge_thickness"):
        GEN.build({**good, "edge_thickness": good["spine_thickness"] * 2}, "bad")
    with pytest.raises(InvalidParameterError, match="rests on its handle"):
        GEN.build({**good, "handle_thickness": good["spine_thickness"]}, "bad")


def test_main_dimensions_span_wide_ratios():
    dims = [GEN.main_dimensions(p) for p in _sample(200, seed=99, cycle_styles=False)]
    for name in ("blade_length", "blade_width", "handle_length", "total_length"):
        values = np.array([d[name] for d in dims])
        assert values.max() / values.min() >= 1.5, name
    blade = np.array([d["blade_length"] for d in dims])
    handle = np.array([d["handle_length"] for d in dims])
    assert 0.065 <= blade.min() and blade.max() <= 0.245
    assert 0.078 <= handle.min() and handle.max() <= 0.142


# -- the built assets --------------------------------------------------------------------------------


def test_every_instance_validates(assets):
    for asset in assets:
        assert GEN.validate(asset) == [], asset.instance_id


def test_asset_fields_and_budgets(assets):
    for p, asset in zip(PARAMS, assets, strict=True):
        assert asset.category == "knife" and asset.source == "procedural" and asset.scale == 1.0
        assert asset.params == p
        assert set(CATEGORY_ANCHORS["knife"]) <= set(asset.anchors)
        assert asset.visual.is_watertight and asset.visual.is_volume
        assert len(asset.visual.faces) <= 20_000
        assert 5 <= len(asset.collision) <= 24


def test_main_dimensions_match_the_geometry(assets):
    for p, asset in zip(PARAMS, assets, strict=True):
        dims = GEN.main_dimensions(p)
        lo, hi = asset.bbox
        assert hi[0] == pytest.approx(dims["blade_length"], abs=1e-6)
        assert lo[0] == pytest.approx(-dims["handle_length"], abs=1e-6)
        assert hi[0] - lo[0] == pytest.approx(dims["total_length"], abs=1e-6)
        heel = _section(asset.visual, 1 * MM)  # just ahead of the handle: blade only
        assert np.ptp(heel[:, 1]) == pytest.approx(dims["blade_width"], abs=0.5 * MM)


def test_collision_parts_cover_the_visual_closely(assets):
    for asset in assets[::2]:
        points, _ = trimesh.sample.sample_surface(asset.visual, 1500, seed=5)
        excess = _outside_parts(asset, points)
        assert np.max(excess) <= 3 * MM, asset.instance_id
        assert np.mean(excess <= 0.5 * MM) >= 0.99, asset.instance_id


def test_collision_parts_do_not_stick_out(assets):
    for asset in assets[::2]:
        points = np.vstack(
            [trimesh.sample.sample_surface(m, 60, seed=6)[0] for m in asset.collision_meshes()]
        )
        assert np.max(distance_to_solid(asset.visual, points)) <= 3 * MM, asset.instance_id


def test_collision_has_no_gaps_along_the_knife(assets):
    """The knife's mid-line (centre of each cross-section) runs inside the union of the parts."""
    for asset in assets[::3]:
        lo, hi = asset.bbox
        centres = []
        for x in np.linspace(lo[0] + 2 * MM, hi[0] - 2 * MM, 120):
            pts = _section(asset.visual, x)
            centres.append([x, (pts[:, 1].min() + pts[:, 1].max()) / 2, 0.0])
        assert np.max(_outside_parts(asset, np.array(centres))) <= 1e-6, asset.instance_id


def test_build_is_deterministic():
    for p in PARAMS[:6]:
        a, b = GEN.build(p, "a"), GEN.build(dict(p), "a")
        np.testing.assert_array_equal(a.visual.vertices, b.visual.vertices)
        np.testing.assert_array_equal(a.visual.faces, b.visual.faces)
        for pa, pb in zip(a.collision, b.collision, strict=True):
            np.testing.assert_array_equal(pa.vertices, pb.vertices)
        for name in a.anchors:
            np.testing.assert_array_equal(a.anchors[name].value, b.anchors[name].value)
        assert a.mass == b.mass


def test_scaled_assets_keep_their_anchors_on_the_geometry(assets):
    for asset in assets[:12:2]:
        for s in (0.5, 2.0):
            scaled = asset.scaled(s)
            assert GEN.validate(scaled) == [], (asset.instance_id, s)
            np.testing.assert_allclose(scaled.anchor("blade_tip"), s * asset.anchor("blade_tip"))


def test_saved_and_reloaded_asset_validates(assets, tmp_path):
    loaded = Asset.load(assets[3].save(tmp_path / "knife"))
    assert GEN.validate(loaded) == []


# -- anchors ------------------------------------------------------------------------------------------


def test_anchor_definitions(assets):
    for p, asset in zip(PARAMS, assets, strict=True):
        a = {k: v.value for k, v in asset.anchors.items()}
        np.testing.assert_allclose(a["blade_base"], 0.0, atol=1e-12)
        assert a["blade_tip"][0] == pytest.approx(p["blade_length"])
        tip_dir = a["blade_tip"] / np.linalg.norm(a["blade_tip"])
        np.testing.assert_allclose(a["blade_axis"], tip_dir, atol=1e-9)
        assert abs(np.dot(a["edge_direction"], a["blade_axis"])) < 1e-9
        assert a["edge_direction"][1] < -0.9 and abs(a["edge_direction"][2]) < 1e-12
        assert a["handle_grasp"][0] == pytest.approx(-p["handle_length"] / 2, abs=0.01)
        assert a["handle_axis"][0] > 0.99
        if p["handle_shape"] != "curved":
            np.testing.assert_allclose(a["handle_axis"], [1.0, 0, 0], atol=1e-9)
        assert distance_to_solid(asset.visual, a["handle_grasp"])[0] == 0.0


def _moved(asset: Asset, name: str, value) -> Asset:
    anchors = dict(asset.anchors)
    anchors[name] = Anchor(anchors[name].kind, np.asarray(value, dtype=float))
    return replace(asset, anchors=anchors)


def test_moved_anchors_are_reported(assets):
    asset = assets[0]
    a = {k: v.value for k, v in asset.anchors.items()}
    grasp_section = _section(asset.visual, a["handle_grasp"][0])
    handle_width = np.ptp(grasp_section[:, 1])
    rot10 = np.array([[np.cos(0.17), -np.sin(0.17), 0], [np.sin(0.17), np.cos(0.17), 0], [0, 0, 1]])
    cases = {
        "blade_tip": a["blade_tip"] + [0.01, 0, 0],
        "blade_base": a["blade_base"] + [0, 0.015, 0],
        "handle_grasp": a["handle_grasp"] + [0, 0.4 * handle_width, 0],
        "edge_direction": -a["edge_direction"],
        "blade_axis": rot10 @ a["blade_axis"],
        "handle_axis": [0.0, 1.0, 0.0],
    }
    for name, value in cases.items():
        problems = GEN.validate_anchors(_moved(asset, name, value))
        assert any(name in msg for msg in problems), (name, problems)
    # A grasp inside the blade is in the solid but not behind the blade base.
    problems = GEN.validate_anchors(_moved(asset, "handle_grasp", [0.02, 0.0, 0.0]))
    assert any("behind the blade base" in msg for msg in problems)
    # At another scale the millimetre tolerances scale too: a 3 mm tip shift at scale 2 is fine,
    # a 3 mm shift at scale 1 is not.
    big = asset.scaled(2.0)
    assert GEN.validate_anchors(_moved(big, "blade_tip", big.anchor("blade_tip") + [-0.003, 0, 0])) == []
    assert GEN.validate_anchors(_moved(asset, "blade_tip", a["blade_tip"] + [-0.003, 0, 0])) != []


# -- functional shape ---------------------------------------------------------------------------------


def test_knife_rests_on_its_handle_and_the_blade_is_thin(assets):
    for p, asset in zip(PARAMS, assets, strict=True):
        v = asset.visual.vertices
        blade = v[v[:, 0] > 1 * MM]
        handle = v[v[:, 0] < -1 * MM]
        assert np.ptp(blade[:, 2]) <= p["spine_thickness"] + 1e-9 <= 4 * MM
        assert handle[:, 2].min() < blade[:, 2].min() - 4 * MM
        grip = _section(asset.visual, asset.anchor("handle_grasp")[0])
        assert 12 * MM * 0.85 <= np.ptp(grip[:, 2]) <= 24 * MM
        # Handle and bolster fit between the gripper's fingers (80 mm) with room to spare.
        assert np.ptp(handle[:, 1]) <= 40 * MM and np.ptp(handle[:, 2]) <= 25 * MM


def test_mass_is_plausible(assets):
    for asset in assets:
        assert 0.02 < asset.mass < 0.6
        lo, hi = asset.bbox
        assert lo[0] < asset.mass_properties.com[0] < hi[0]
        assert np.all(np.linalg.eigvalsh(asset.mass_properties.inertia) > 0)


def test_blade_outlines_follow_their_style(assets):
    for p, asset in zip(PARAMS, assets, strict=True):
        width, length = p["blade_width"], p["blade_length"]
        tip_y = asset.anchor("blade_tip")[1]
        near_tip = _section(asset.visual, 0.9 * length)
        style = p["style"]
        if style == "chef":  # pointed tip near the spine line, curved edge
            assert tip_y > 0.15 * width
            assert near_tip[:, 1].min() > -0.5 * width + 0.25 * width
        elif style == "santoku":  # sheep's foot: tip down near the edge line
            assert tip_y < -0.25 * width
        elif style == "paring":
            assert length <= 0.105 and width <= 0.024
        elif style == "cleaver":  # rectangular and tall
            assert np.ptp(near_tip[:, 1]) >= 0.85 * width and width >= 0.065
        elif style == "bread":  # long, straight edge, round tip in the middle of the front
            assert length >= 0.18
            mid = _section(asset.visual, 0.5 * length)
            assert mid[:, 1].min() == pytest.approx(-width / 2, abs=p["serration_depth"] + 0.2 * MM)
            front = _section(asset.visual, length - 1 * MM)
            assert abs(tip_y - (front[:, 1].min() + front[:, 1].max()) / 2) < 1 * MM
