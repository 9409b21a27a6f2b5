"""Tests of the procedural mug family: validity, functional shape, collision model, anchors."""

from __future__ import annotations

import dataclasses
import json

import mujoco
import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull

from keygen.errors import InvalidParameterError
from keygen.objects import meshing
from keygen.objects.asset import CATEGORY_ANCHORS, Anchor, Asset
from keygen.objects.generators._mug_parts import RIMS, resample_polyline
from keygen.objects.generators.mug import MugGenerator, body_from_params
from keygen.objects.splits import get_generator

GEN = MugGenerator()
N_INSTANCES = 40
MM = 1e-3


def _rng(*key: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([2024, *key]))


@pytest.fixture(scope="module")
def instances() -> list[tuple[dict, Asset]]:
    out = []
    for i in range(N_INSTANCES):
        params = GEN.sample_params(_rng(i), style=GEN.styles[i % len(GEN.styles)])
        out.append((params, GEN.build(params, f"mug-test-{i:03d}")))
    return out


def _ray_hits(mesh: trimesh.Trimesh, origin, direction) -> np.ndarray:
    loc, _, _ = mesh.ray.intersects_location([np.asarray(origin, float)], [np.asarray(direction, float)])
    return loc[np.argsort(np.linalg.norm(loc - origin, axis=1))]


def _halfspaces(part) -> np.ndarray:
    """(F, 4) outward unit plane equations of a convex mesh part: n.x + d <= 0 inside."""
    return ConvexHull(part.vertices).equations


def _depth_outside(parts, points: np.ndarray) -> np.ndarray:
    """Per point, min over parts of the largest plane excess (< 0: inside that part by that much)."""
    best = np.full(len(points), np.inf)
    for part in parts:
        eq = _halfspaces(part)
        excess = (points @ eq[:, :3].T + eq[:, 3]).max(axis=1)
        best = np.minimum(best, excess)
    return best


# -- parameters -------------------------------------------------------------------------------------
def test_registry_returns_mug_generator():
    gen = get_generator("mug")
    assert isinstance(gen, MugGenerator)
    assert gen.category == "mug"
    assert set(gen.styles) == {"round", "d", "square", "angular", "ear"}


def test_params_are_plain_json_and_in_range():
    for i in range(60):
        params = GEN.sample_params(_rng(1000, i))
        assert json.loads(json.dumps(params)) == params
        assert all(type(v) in (float, str, int) for v in params.values())
        assert params["style"] in GEN.styles and params["rim"] in RIMS
        assert 0.030 <= params["radius_bottom"] <= 0.055
        assert 0.8 <= params["taper"] <= 1.3
        assert 0.065 <= params["height"] <= 0.125
        assert 0.003 <= params["wall"] <= 0.007
        assert 0.003 <= params["handle_half_depth"] <= 0.0065
        assert 0.003 <= params["handle_half_width"] <= 0.007
        assert 2000 <= params["density"] <= 2400


def test_sampling_is_seeded_and_style_can_be_forced():
    assert GEN.sample_params(_rng(7)) == GEN.sample_params(_rng(7))
    assert GEN.sample_params(_rng(7)) != GEN.sample_params(_rng(8))
    for style in GEN.styles:
        assert GEN.sample_params(_rng(9), style=style)["style"] == style
    with pytest.raises(InvalidParameterError, match="style"):
        GEN.sample_params(_rng(9), style="teacup")


def test_main_dimensions_span_wide_ranges():
    dims = [GEN.main_dimensions(GEN.sample_params(_rng(2000, i))) for i in range(200)]
    for name in ("height", "body_diameter", "handle_reach", "handle_height"):
        values = np.array([d[name] for d in dims])
        assert values.min() > 0
        assert values.max() / values.min() >= 1.5, (name, values.min(), values.max())


def test_build_rejects_incomplete_params():
    params = GEN.sample_params(_rng(3))
    del params["handle_gap"]
    with pytest.raises(InvalidParameterError, match="handle_gap"):
        GEN.build(params, "broken")


# -- assets -----------------------------------------------------------------------------------------
def test_every_instance_validates(instances):
    for params, asset in instances:
        assert GEN.validate(asset) == [], params


def test_asset_fields_budget_and_mass(instances):
    for params, asset in instances:
        assert asset.category == "mug" and asset.source == "procedural" and asset.scale == 1.0
        assert asset.params == params
        assert set(CATEGORY_ANCHORS["mug"]) <= set(asset.anchors)
        assert asset.visual.is_volume and len(asset.visual.faces) <= 20000
        assert 10 <= len(asset.collision) <= 50
        assert asset.mass / asset.visual.volume == pytest.approx(params["density"], rel=1e-6)
        dims = GEN.main_dimensions(params)
        assert asset.bbox[1, 2] == pytest.approx(dims["height"], abs=0.2 * MM)
        assert asset.bbox[1, 1] * 2 == pytest.approx(dims["body_diameter"], abs=1 * MM)


def test_build_is_deterministic(instances):
    # Build time is measured by benchmarks, never asserted here: CI machines are noisy.
    params, asset = instances[3]
    again = GEN.build(params, "again")
    assert np.array_equal(again.visual.vertices, asset.visual.vertices)
    assert np.array_equal(again.visual.faces, asset.visual.faces)
    for a, b in zip(again.collision, asset.collision, strict=True):
        assert np.array_equal(a.vertices, b.vertices)


# -- functional shape -------------------------------------------------------------------------------
def test_handle_opening_fits_a_finger(instances):
    for params, asset in instances:
        mesh = asset.visual
        gx, _, gz = asset.anchor("handle_grasp")
        y = 0.3 * MM  # off the y = 0 seam, where rays would graze mesh edges
        body_r = np.abs(_ray_hits(mesh, [0, 0, gz], [0, 1, 0])[:, 1]).max()
        beyond = _ray_hits(mesh, [0, y, gz], [1, 0, 0])[:, 0]
        beyond = beyond[beyond > body_r + 0.5 * MM]
        inner, outer = beyond[0], beyond[1]
        assert inner - body_r >= 20 * MM, params  # clear gap for a finger, in x
        assert outer - inner <= 16 * MM, params  # the bar fits between the jaws' pads
        finger_x = inner - 5 * MM  # centre of an 8 mm finger touching the bar
        up = _ray_hits(mesh, [finger_x, y, gz], [0, 0, 1])[0, 2]
        down = _ray_hits(mesh, [finger_x, y, gz], [0, 0, -1])[0, 2]
        assert up - down >= 25 * MM, params
        assert not mesh.contains([[finger_x, y, gz]])[0]


def test_handle_merges_between_base_and_rim(instances):
    for params, asset in instances:
        mesh = asset.visual
        assert mesh.body_count == 1 and mesh.euler_number == 0  # one solid with one handle hole
        top = mesh.bounds[1, 2]
        body_r = mesh.bounds[1, 1]  # the handle lies at y = 0, so y extent is the body's
        handle = mesh.vertices[mesh.vertices[:, 0] > body_r + 0.5 * MM]
        assert handle[:, 2].min() > 1 * MM and handle[:, 2].max() < top - 1 * MM, params
        assert mesh.bounds[1, 0] - mesh.bounds[0, 0] <= 0.2


def test_cavity_is_open_and_holds_spheres(instances):
    sphere_volume = 4 / 3 * np.pi * (7 * MM) ** 3
    for params, asset in instances:
        mesh, top = asset.visual, asset.bbox[1, 2]
        floor = _ray_hits(mesh, [0.2 * MM, 0.1 * MM, top + 0.01], [0, 0, -1])[0, 2]
        assert floor == pytest.approx(params["bottom"], abs=0.1 * MM)
        assert not mesh.contains([[0, 0, (floor + top) / 2]])[0]
        body = body_from_params(params)
        r_in = min(body.r_in(body.bottom), body.r_in(body.height))
        assert np.pi * r_in**2 * (body.height - body.bottom) > 12 * sphere_volume / 0.5


def test_cavity_collision_has_no_gaps(instances):
    """A closed cup surface through the middle of the wall and floor is covered by the parts.

    Each sample, and its neighbours 0.8 mm away across the surface, lies inside some part, so
    the parts' union holds a sheet at least 1.6 mm thick along the samples (3.2 mm apart or
    closer): nothing near 14 mm wide (a 7 mm sphere) can pass.
    """
    angles = np.linspace(0, 2 * np.pi, 150, endpoint=False)
    ring = np.column_stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)])
    for params, asset in instances:
        body = body_from_params(params)
        # The wall's mid line in (r, z), band after band, sampled every 1 mm.
        mid = np.vstack([np.column_stack([(r_in + r_out) / 2, z]) for z, r_in, r_out in body.wall_bands()])
        mid = resample_polyline(mid, 1 * MM)
        mid = mid[mid[:, 1] <= mid[-1, 1] - 1 * MM]  # the top face itself is not deep inside
        reach = body.max_outer_radius * 1.1  # wedges circumscribe the wall; handle hulls reach further
        parts = [p for p in asset.collision if np.hypot(*p.vertices[:, :2].T).max() < reach]
        z_floor = body.bottom / 2
        start = [np.interp(z_floor, mid[:, 1], mid[:, 0]), z_floor]  # where the wall meets the floor
        r_mid, z = np.vstack([start, mid[mid[:, 1] > z_floor]]).T
        r_floor = np.linspace(0, r_mid[0], 25)
        pieces = []
        for offsets, radii, heights in (
            (((0.8, 0), (-0.8, 0), (0, 0)), r_mid, z),  # wall: offsets across it (radial)
            (((0, 0.8), (0, -0.8), (0, 0)), r_floor, np.full_like(r_floor, z_floor)),  # floor
        ):
            for dr, dz in offsets:
                pts = (radii[:, None, None] + dr * MM) * ring[None] + np.array([0, 0, 1.0]) * (
                    heights[:, None, None] + dz * MM
                )
                pieces.append(pts.reshape(-1, 3))
        depth = _depth_outside(parts, np.vstack(pieces))
        assert depth.max() <= 1e-9, (params["style"], params["rim"], depth.max())  # seams: on a face


def test_spheres_stay_in_the_mug_in_mujoco(instances):
    """Twelve 7 mm spheres poured in stay in the cavity (the collision parts as MuJoCo geoms)."""
    for params, asset in instances[:5]:
        geoms, meshes = [], []
        for i, part in enumerate(asset.collision):
            meshes.append(f'<mesh name="p{i}" vertex="{" ".join(map(str, part.vertices.ravel()))}"/>')
            geoms.append(f'<geom type="mesh" mesh="p{i}"/>')
        body = body_from_params(params)
        # Start them at rest in layered rings inside the cup (dropped from high up, a 7 mm
        # sphere at ~5 mm per step would tunnel through any 5 mm floor in a discrete simulator).
        r_ring = max(0.0, min(body.r_in(body.bottom), body.r_in(body.height)) - 0.009)
        per_layer = max(1, int(2 * np.pi * r_ring / 0.016))
        balls = []
        for k in range(12):
            layer, slot = divmod(k, per_layer)
            a = 2 * np.pi * (slot + 0.5 * layer) / per_layer
            pos = (r_ring * np.cos(a), r_ring * np.sin(a), body.bottom + 0.008 + 0.016 * layer)
            balls.append(
                f'<body pos="{pos[0]} {pos[1]} {pos[2]}"><freejoint/>'
                '<geom type="sphere" size="0.007" density="1000"/></body>'
            )
        xml = (
            '<mujoco><option timestep="0.002"/><asset>'
            + "".join(meshes)
            + "</asset><worldbody>"
            + "".join(geoms)
            + "".join(balls)
            + "</worldbody></mujoco>"
        )
        model = mujoco.MjModel.from_xml_string(xml)
        data = mujoco.MjData(model)
        mujoco.mj_step(model, data, nstep=1000)
        centres = data.xpos[1:]
        radial = np.hypot(centres[:, 0], centres[:, 1])
        assert np.all(centres[:, 2] > body.bottom), params  # nothing fell through the floor
        assert np.all(centres[:, 2] < body.height), params  # nor spilled over the rim
        assert np.all(radial < body.r_in(np.clip(centres[:, 2], 0, body.height)) + 1 * MM), params


def test_collision_parts_hug_the_visual(instances):
    for params, asset in instances[::4]:
        parts = asset.collision
        assert all(p.kind == "mesh" for p in parts)
        # Every visual surface point is within 3 mm of some part.
        pts, _ = trimesh.sample.sample_surface(asset.visual, 1500, seed=0)
        outside = pts[_depth_outside(parts, pts) > 0]
        dist = np.full(len(outside), np.inf)
        for part in parts:
            if len(outside):
                dist = np.minimum(dist, trimesh.proximity.closest_point(part.to_trimesh(), outside)[1])
        assert dist.max(initial=0) <= 3 * MM, (params["style"], dist.max())
        # No part sticks out of the visual solid by more than 3 mm.
        rng = np.random.default_rng(0)
        samples = np.vstack([trimesh.sample.sample_surface(p.to_trimesh(), 12, seed=rng)[0] for p in parts])
        stick_out = meshing.distance_to_solid(asset.visual, samples)
        assert stick_out.max() <= 3 * MM, (params["style"], params["rim"], stick_out.max())


# -- anchors ----------------------------------------------------------------------------------------
def test_anchor_values_follow_their_definitions(instances):
    for params, asset in instances:
        body = body_from_params(params)
        top = asset.bbox[1, 2]
        np.testing.assert_allclose(asset.anchor("bottom_center"), 0, atol=1e-12)
        np.testing.assert_allclose(asset.anchor("opening_center"), [0, 0, top], atol=1e-6)
        np.testing.assert_allclose(asset.anchor("grasp_approach"), [0, -1, 0])
        np.testing.assert_allclose(
            asset.anchor("pour_point"), [-(body.rim_outer_radius - params["wall"] / 2), 0, top], atol=1e-9
        )
        grasp, centre = asset.anchor("handle_grasp"), asset.anchor("handle_center")
        assert grasp[0] + params["handle_half_depth"] == pytest.approx(asset.bbox[1, 0], abs=0.5 * MM)
        assert body.r_out(centre[2]) < centre[0] < grasp[0]


@pytest.mark.parametrize("scale", [0.4, 2.5])
def test_scaled_asset_keeps_anchors_on_geometry(instances, scale):
    for params, asset in instances[:10:3]:
        scaled = asset.scaled(scale)
        assert scaled.scale == scale
        assert GEN.validate(scaled) == [], params
        for name, anchor in asset.anchors.items():
            expected = anchor.value if anchor.kind == "direction" else anchor.value * scale
            np.testing.assert_allclose(scaled.anchor(name), expected)


def test_saved_and_loaded_asset_still_validates(instances, tmp_path):
    _, asset = instances[1]
    loaded = Asset.load(asset.save(tmp_path / "mug"))
    assert GEN.validate(loaded) == []


def _moved(asset: Asset, name: str, value) -> Asset:
    anchors = dict(asset.anchors)
    anchors[name] = Anchor(anchors[name].kind, np.asarray(value, dtype=float))
    return dataclasses.replace(asset, anchors=anchors)


def test_moved_anchors_are_reported(instances):
    _, asset = instances[2]
    top = asset.bbox[1, 2]
    grasp, centre = asset.anchor("handle_grasp"), asset.anchor("handle_center")
    pour = asset.anchor("pour_point")
    cases = {
        "handle_grasp": [0.0, 0.0, grasp[2]],  # onto the body axis
        "handle_center": grasp,  # into the bar's material
        "pour_point": [-pour[0], 0.0, top],  # onto the handle side
        "opening_center": [0.0, 0.0, top / 2],  # down into the cup
        "bottom_center": [0.0, 0.0, 0.01],  # off the base
        "grasp_approach": [0.0, 0.0, 1.0],  # along the body axis
    }
    for name, value in cases.items():
        problems = GEN.validate_anchors(_moved(asset, name, value))
        assert any(name in p for p in problems), (name, problems)
    # A handle_center pushed out of the loop (beyond the bar) is caught too.
    assert GEN.validate_anchors(_moved(asset, "handle_center", centre + [0.06, 0, 0]))


def test_lifted_mesh_is_reported(instances):
    _, asset = instances[0]
    lifted = asset.visual.copy()
    lifted.apply_translation([0, 0, 0.005])
    problems = GEN.validate_anchors(dataclasses.replace(asset, visual=lifted))
    assert any("min z" in p for p in problems)
