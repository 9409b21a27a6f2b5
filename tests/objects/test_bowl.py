"""Tests of the procedural bowl family: validity, collision fidelity, function, anchors."""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from functools import cache

import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull

from keygen.errors import InvalidParameterError
from keygen.objects.asset import CATEGORY_ANCHORS, Anchor, Asset
from keygen.objects.generators.bowl import BowlGenerator
from keygen.objects.meshing import distance_to_solid
from keygen.objects.splits import get_generator

GEN = BowlGenerator()
COUNT = 40  # instances, dealt out over the styles
MM = 1e-3


@cache
def _instances() -> tuple[tuple[dict, Asset], ...]:
    out = []
    for i in range(COUNT):
        rng = np.random.default_rng(np.random.SeedSequence([2024, i]))
        params = GEN.sample_params(rng, style=GEN.styles[i % len(GEN.styles)])
        out.append((params, GEN.build(params, f"bowl-test-{i:03d}")))
    return tuple(out)


@dataclass(frozen=True)
class _Parts:
    """An asset's collision parts, prepared once for fast point queries."""

    lo: list[np.ndarray]  # per part, (3,) bounds
    hi: list[np.ndarray]
    planes: list[np.ndarray]  # per part, (F, 4): x is inside when n . x + d <= 0
    meshes: list[trimesh.Trimesh]  # scipy's hulls as meshes (far cheaper than to_trimesh)


@cache
def _cached_parts(index: int) -> _Parts:
    return _prepare(_instances()[index][1])


def _parts(asset: Asset) -> _Parts:
    for i, (_, cached) in enumerate(_instances()):
        if cached is asset:
            return _cached_parts(i)
    return _prepare(asset)


def _prepare(asset: Asset) -> _Parts:
    lo, hi, planes, meshes = [], [], [], []
    for part in asset.collision:
        v = part.vertices  # every bowl part is a "mesh" part: the hull of its vertices
        hull = ConvexHull(v)
        lo.append(v.min(axis=0))
        hi.append(v.max(axis=0))
        planes.append(hull.equations)
        meshes.append(trimesh.Trimesh(v, hull.simplices, process=False))
    return _Parts(lo, hi, planes, meshes)


def _inside_parts(parts: _Parts, points: np.ndarray, slack: float = 1e-7) -> np.ndarray:
    inside = np.zeros(len(points), dtype=bool)
    for lo, hi, eq in zip(parts.lo, parts.hi, parts.planes, strict=True):
        # Only points in the part's box and not yet known to be inside are tested (speed).
        near = np.nonzero(~inside & np.all((points >= lo - slack) & (points <= hi + slack), axis=1))[0]
        inside[near] = np.all(points[near] @ eq[:, :3].T + eq[:, 3] <= slack, axis=1)
    return inside


def _distance_to_parts(parts: _Parts, points: np.ndarray) -> np.ndarray:
    """Distance from each point to the union of the collision parts (0 inside one)."""
    dist = np.zeros(len(points))
    outside = ~_inside_parts(parts, points)
    if outside.any():  # the costly surface query only for the few points outside every part
        surfaces = trimesh.util.concatenate(parts.meshes)
        dist[outside] = trimesh.proximity.closest_point(surfaces, points[outside])[1]
    return dist


# -- the family ---------------------------------------------------------------------------------
def test_registered_and_styles():
    gen = get_generator("bowl")
    assert isinstance(gen, BowlGenerator) and gen.category == "bowl"
    assert len(gen.styles) == 5 and len(set(gen.styles)) == 5


def test_params_are_json_plain_and_seeded():
    for style in GEN.styles:
        a = GEN.sample_params(np.random.default_rng(7), style)
        b = GEN.sample_params(np.random.default_rng(7), style)
        assert a == b and a["style"] == style
        assert json.loads(json.dumps(a)) == a
        assert all(type(v) in (float, str) for v in a.values())
    unforced = {GEN.sample_params(np.random.default_rng(s))["style"] for s in range(40)}
    assert unforced == set(GEN.styles)


def test_bad_style_and_params_are_rejected():
    with pytest.raises(InvalidParameterError, match="style"):
        GEN.sample_params(np.random.default_rng(0), style="teacup")
    params = GEN.sample_params(np.random.default_rng(0), "conical")
    with pytest.raises(InvalidParameterError, match="depth"):
        GEN.build({k: v for k, v in params.items() if k != "depth"}, "x")


def test_main_dimensions_span_wide_ranges():
    dims = []
    for i in range(200):
        params = GEN.sample_params(np.random.default_rng(np.random.SeedSequence([99, i])))
        dims.append(GEN.main_dimensions(params))
    for name in ("rim_diameter", "depth", "height", "base_diameter"):
        values = np.array([d[name] for d in dims])
        assert np.all(values > 0)
        assert values.max() / values.min() >= 1.5, name
    rim = np.array([d["rim_diameter"] for d in dims])
    depth = np.array([d["depth"] for d in dims])
    assert 0.09 <= rim.min() and rim.max() <= 0.235  # rim radius ~50-115 mm
    assert 0.029 <= depth.min() and depth.max() <= 0.095  # depth ~30-85 mm (+ rounded rim)


# -- validity -----------------------------------------------------------------------------------
def test_sampled_instances_are_valid():
    for params, asset in _instances():
        assert GEN.validate(asset) == [], asset.instance_id
        assert asset.category == "bowl" and asset.source == "procedural" and asset.scale == 1.0
        assert asset.params == params
        assert set(asset.anchors) == set(CATEGORY_ANCHORS["bowl"]) | {"inner_bottom_center"}
        assert asset.visual.is_volume and len(asset.visual.faces) <= 20_000
        assert 4 <= len(asset.collision) <= 96
        density = asset.mass / asset.visual.volume
        assert 2000 <= density <= 2400
        assert np.allclose(asset.mass_properties.com[:2], 0, atol=1e-6)  # symmetric about the axis


def test_build_is_deterministic():
    params, asset = _instances()[3]
    again = GEN.build(params, asset.instance_id)
    assert np.array_equal(asset.visual.vertices, again.visual.vertices)
    assert np.array_equal(asset.visual.faces, again.visual.faces)
    for p, q in zip(asset.collision, again.collision, strict=True):
        assert np.array_equal(p.vertices, q.vertices)
    for name, anchor in asset.anchors.items():
        assert np.array_equal(anchor.value, again.anchors[name].value)


@pytest.mark.parametrize("scale", [0.5, 1.4])
def test_scaled_assets_keep_anchors_on_the_geometry(scale):
    for _, asset in _instances()[:5]:  # one per style
        assert GEN.validate(asset.scaled(scale)) == [], (asset.instance_id, scale)


# -- collision fidelity -------------------------------------------------------------------------
def test_collision_parts_cover_the_visual_closely():
    for i, (_, asset) in enumerate(_instances()):
        surface, _ = trimesh.sample.sample_surface(asset.visual, 600, seed=i)
        assert _distance_to_parts(_parts(asset), surface).max() <= 3 * MM, asset.instance_id
        part_points = np.vstack(
            [trimesh.sample.sample_surface(m, 6, seed=i)[0] for m in _parts(asset).meshes]
        )
        assert distance_to_solid(asset.visual, part_points).max() <= 3 * MM, asset.instance_id


def test_wall_has_no_gaps():
    """Every point of the wall's mid-surface lies inside a part: nothing passes through the wall."""
    angles = np.linspace(0, 2 * np.pi, 181)[:-1]
    for params, asset in _instances():
        prof = GEN.profile(params)
        mid = (prof.inner + prof.outer) / 2  # (M, 2) mid-wall from the axis to the rim
        fine = np.vstack([mid, (mid[1:] + mid[:-1]) / 2])
        pts = np.concatenate(
            [np.column_stack([fine[:, 0] * np.cos(a), fine[:, 0] * np.sin(a), fine[:, 1]]) for a in angles]
        )
        assert _inside_parts(_parts(asset), pts, slack=1e-6).all(), asset.instance_id


def test_cavity_stays_hollow_so_a_smaller_bowl_nests():
    """A copy at 0.75 scale lowered into the bowl comes to rest deep inside the cavity."""
    for _, asset in _instances()[::4]:
        top = asset.anchor("opening_center")[2]
        floor = asset.anchor("inner_bottom_center")[2]
        parts = _parts(asset)
        # The axis above the floor is free all the way up to the opening.
        axis = np.column_stack([np.zeros(50), np.zeros(50), np.linspace(floor + 2 * MM, top, 50)])
        assert not _inside_parts(parts, axis).any()
        small = asset.scaled(0.75)
        probe = np.vstack([small.visual.vertices[::3]] + [p.vertices for p in small.collision])
        lo, hi = floor - 1.5 * MM, top + 0.01  # base heights: colliding at lo, clear at hi
        assert _inside_parts(parts, probe + (0, 0, lo)).any()
        for _ in range(16):  # to 0.1 mm
            mid = (lo + hi) / 2
            lo, hi = (mid, hi) if _inside_parts(parts, probe + (0, 0, mid)).any() else (lo, mid)
        # A filled cavity would hold the small bowl at the rim; it sinks to the lower part instead.
        assert hi - floor < 0.5 * (top - floor), asset.instance_id


# -- function -----------------------------------------------------------------------------------
def test_rim_is_thin_enough_to_pinch():
    """Horizontal wall width near the rim fits a parallel gripper pinching from above (<= 10 mm)."""
    for _, asset in _instances():
        top = asset.visual.bounds[1, 2]
        for depth in np.linspace(0.5, 12, 8) * MM:
            section = asset.visual.section(plane_origin=(0, 0, top - depth), plane_normal=(0, 0, 1))
            radii = np.hypot(*section.vertices[:, :2].T)
            assert radii.max() - radii.min() <= 10 * MM, (asset.instance_id, depth)


def test_functional_shape():
    for _, asset in _instances():
        a = {k: v.value for k, v in asset.anchors.items()}
        top, floor = a["opening_center"][2], a["inner_bottom_center"][2]
        assert top - floor >= 0.029  # a real cavity
        # rim_grasp: mid-wall (inside the material) 8 mm under the rim top, on +x.
        assert distance_to_solid(asset.visual, a["rim_grasp"])[0] == 0.0
        assert a["rim_grasp"][2] == pytest.approx(top - 8 * MM, abs=1e-9)
        assert a["rim_grasp"][0] > 0.5 * a["rim_radius"][0]
        # Stands on a wide support: the contact points at z ~ 0 spread around the axis.
        v = asset.visual.vertices
        support = np.hypot(*v[v[:, 2] < 1e-6, :2].T)
        assert support.max() >= 0.15 * a["rim_radius"][0]
        # The centre of mass is low and on the axis, inside the footprint.
        assert asset.mass_properties.com[2] < 0.6 * top


def test_every_style_is_built():
    styles = {params["style"] for params, _ in _instances()}
    assert styles == set(GEN.styles)
    feet = [params["foot_height"] > 0 for params, _ in _instances()]
    assert any(feet) and not all(feet)
    lips = [params["lip_radius"] > 0 for params, _ in _instances()]
    assert any(lips) and not all(lips)


# -- anchors: negative tests --------------------------------------------------------------------
def _moved(asset: Asset, name: str, delta) -> Asset:
    anchors = dict(asset.anchors)
    old = anchors[name]
    anchors[name] = Anchor(old.kind, old.value + np.asarray(delta, dtype=float))
    return replace(asset, anchors=anchors)


@pytest.mark.parametrize(
    ("name", "delta", "message"),
    [
        ("rim_grasp", (0, 0, 0.02), "rim_grasp"),
        ("rim_grasp", (0.012, 0, 0), "rim_grasp"),
        ("rim_grasp", (0, 0.03, 0), "rim_grasp"),
        ("opening_center", (0, 0, -0.01), "opening_center"),
        ("opening_center", (0.01, 0, 0), "opening_center"),
        ("bottom_center", (0, 0, 0.005), "bottom_center"),
        ("rim_radius", (0.005,), "rim_radius"),
        ("inner_bottom_center", (0, 0, 0.004), "inner_bottom_center"),
    ],
)
def test_moved_anchor_is_reported(name, delta, message):
    _, asset = _instances()[1]
    problems = GEN.validate_anchors(_moved(asset, name, delta))
    assert any(message in p for p in problems), problems
    # The same move at half scale (tolerances shrink with the asset) is still caught.
    small = asset.scaled(0.5)
    assert any(message in p for p in GEN.validate_anchors(_moved(small, name, np.asarray(delta) * 0.5)))


def test_filled_or_lifted_bowl_is_reported():
    _, asset = _instances()[2]
    filled = replace(asset, visual=asset.visual.convex_hull)
    assert any("cavity" in p for p in GEN.validate_anchors(filled))
    lifted = replace(asset, visual=asset.visual.copy().apply_translation((0, 0, 0.004)))
    assert any("min z" in p for p in GEN.validate_anchors(lifted))
