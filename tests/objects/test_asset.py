import json

import numpy as np
import pytest
import trimesh

from keygen.errors import AssetError, InvalidParameterError, MissingAnchorsError
from keygen.objects.asset import Anchor, Asset, ConvexPart, MassProperties


def test_save_load_round_trip(tmp_path, bowl_asset):
    folder = bowl_asset.save(tmp_path / "a")
    loaded = Asset.load(folder)
    assert loaded.instance_id == bowl_asset.instance_id
    assert loaded.visual.is_watertight
    np.testing.assert_allclose(loaded.bbox, bowl_asset.bbox, atol=1e-7)
    assert len(loaded.collision) == len(bowl_asset.collision)
    for a, b in zip(loaded.collision, bowl_asset.collision, strict=True):
        assert abs(a.to_trimesh().volume - b.to_trimesh().volume) < 1e-9
    for name, anchor in bowl_asset.anchors.items():
        np.testing.assert_allclose(loaded.anchors[name].value, anchor.value)
    assert loaded.mass == pytest.approx(bowl_asset.mass)
    meta = json.loads((folder / "meta.json").read_text())
    assert {"category", "instance_id", "params", "scale", "anchors", "bbox"} <= set(meta)
    # atomic write leaves no temporary folder behind
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a"]


def test_save_overwrites_existing_folder(tmp_path, bowl_asset):
    bowl_asset.save(tmp_path / "a")
    bowl_asset.scaled(2.0).save(tmp_path / "a")
    assert Asset.load(tmp_path / "a").scale == pytest.approx(2.0)


@pytest.mark.parametrize("s", [0.5, 1.2])
def test_scaled_scales_everything_together(bowl_asset, s):
    big = bowl_asset.scaled(s)
    np.testing.assert_allclose(big.bbox, bowl_asset.bbox * s, atol=1e-9)
    assert big.mass == pytest.approx(bowl_asset.mass * s**3)
    np.testing.assert_allclose(big.mass_properties.inertia, bowl_asset.mass_properties.inertia * s**5)
    # mass properties stay consistent with the scaled mesh
    direct = MassProperties.from_mesh(big.visual, 2000.0)
    assert big.mass == pytest.approx(direct.mass, rel=1e-6)
    np.testing.assert_allclose(big.mass_properties.inertia, direct.inertia, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(big.anchor("rim_grasp"), bowl_asset.anchor("rim_grasp") * s)
    assert big.anchor("rim_radius")[0] == pytest.approx(bowl_asset.anchor("rim_radius")[0] * s)
    for a, b in zip(big.collision, bowl_asset.collision, strict=True):
        assert a.to_trimesh().volume == pytest.approx(b.to_trimesh().volume * s**3, rel=1e-6)
    assert big.scale == pytest.approx(s)


@pytest.mark.parametrize("s", [0.0, -1.0, float("nan")])
def test_scaled_rejects_bad_factor(bowl_asset, s):
    with pytest.raises(InvalidParameterError):
        bowl_asset.scaled(s)


def test_missing_anchors_error_names_the_fix(bowl_asset):
    bare = Asset("bowl", "scan", bowl_asset.visual, bowl_asset.collision, bowl_asset.mass_properties, None)
    with pytest.raises(MissingAnchorsError, match="--anchors"):
        bare.require_anchors("stack")


def test_incomplete_anchor_set_is_refused(bowl_asset):
    anchors = dict(bowl_asset.anchors)
    del anchors["rim_radius"]
    with pytest.raises(AssetError, match="rim_radius"):
        Asset("bowl", "x", bowl_asset.visual, bowl_asset.collision, bowl_asset.mass_properties, anchors)


def test_anchor_validation_and_transform():
    d = Anchor("direction", [0, 0, 2])
    np.testing.assert_allclose(d.value, [0, 0, 1])
    with pytest.raises(InvalidParameterError):
        Anchor("direction", [0, 0, 0])
    with pytest.raises(InvalidParameterError):
        Anchor("point", [0, np.nan, 0])
    R = trimesh.transformations.rotation_matrix(np.pi / 2, [0, 0, 1])[:3, :3]
    p = Anchor("point", [1, 0, 0]).transformed(R, np.array([0, 0, 1.0]))
    np.testing.assert_allclose(p.value, [0, 1, 1], atol=1e-12)
    assert Anchor("direction", [1, 0, 0]).transformed(R, np.ones(3)).value == pytest.approx([0, 1, 0])
    assert Anchor("direction", [1, 0, 0]).scaled(3.0).value == pytest.approx([1, 0, 0])


def test_convex_parts_are_convex_and_transform_rigidly(capsule_part):
    box = ConvexPart("box", center=np.zeros(3), rotation=np.eye(3), half_extents=np.array([0.01, 0.02, 0.03]))
    sphere = ConvexPart("sphere", center=np.ones(3), radius=0.02)
    mesh = ConvexPart("mesh", vertices=np.random.default_rng(0).normal(size=(50, 3)))
    R = trimesh.transformations.random_rotation_matrix(np.random.default_rng(1).random(3))[:3, :3]
    for part in (capsule_part, box, sphere, mesh):
        m = part.to_trimesh()
        assert m.is_convex and m.is_watertight
        moved = part.transformed(R, np.array([0.1, 0.2, 0.3]), scale=2.0).to_trimesh()
        assert moved.volume == pytest.approx(m.volume * 8, rel=2e-2)
    assert box.to_trimesh().volume == pytest.approx(0.02 * 0.04 * 0.06)
    with pytest.raises(InvalidParameterError):
        ConvexPart("capsule", p0=np.zeros(3), p1=np.ones(3))
    with pytest.raises(InvalidParameterError):
        ConvexPart("cone")


def test_mass_properties_combine_matches_union():
    a = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    b = trimesh.creation.box(extents=[0.1, 0.1, 0.1]).apply_translation([0.1, 0, 0])
    whole = trimesh.creation.box(extents=[0.2, 0.1, 0.1]).apply_translation([0.05, 0, 0])
    combined = MassProperties.combine(
        [MassProperties.from_mesh(a, 1000.0), MassProperties.from_mesh(b, 1000.0)]
    )
    direct = MassProperties.from_mesh(whole, 1000.0)
    assert combined.mass == pytest.approx(direct.mass)
    np.testing.assert_allclose(combined.com, direct.com, atol=1e-12)
    np.testing.assert_allclose(combined.inertia, direct.inertia, atol=1e-10)


def test_load_errors(tmp_path):
    with pytest.raises(AssetError, match="meta.json"):
        Asset.load(tmp_path)
    (tmp_path / "meta.json").write_text("{not json")
    with pytest.raises(AssetError, match="JSON"):
        Asset.load(tmp_path)


def test_part_labels_survive_save_and_load(tmp_path, bowl_asset):
    from keygen.objects.meshing import with_label

    bowl_asset.collision = with_label(bowl_asset.collision[:-1], "wall") + with_label(
        bowl_asset.collision[-1:], "floor"
    )
    loaded = Asset.load(bowl_asset.save(tmp_path / "a"))
    assert [p.label for p in loaded.collision] == [p.label for p in bowl_asset.collision]
    assert loaded.collision[-1].label == "floor"
