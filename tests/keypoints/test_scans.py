"""Single-object scans for the keypoint stage: geometry, poses, determinism, storage, arguments."""

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

import keygen  # noqa: F401  (sets MUJOCO_GL before mujoco is imported)
from keygen.errors import InvalidParameterError
from keygen.keypoints import Scan, ScanGenerator, load_scans, save_scans


@pytest.fixture(scope="module")
def mug_gen():
    with ScanGenerator("mug", num_instances=2, num_points=512, views=(1, 4)) as gen:
        yield gen


@pytest.fixture(scope="module")
def knife_gen():
    with ScanGenerator("knife", num_instances=2, num_points=512) as gen:
        yield gen


def _surface_distances(gen: ScanGenerator, index: int, scan: Scan) -> np.ndarray:
    mesh = gen.asset(index).visual.copy()
    mesh.apply_transform(scan.transform)
    _, dist, _ = trimesh.proximity.closest_point(mesh, scan.points.astype(np.float64))
    return dist


def _coverage(gen: ScanGenerator, index: int, scan: Scan, radius: float = 0.005) -> float:
    """Fraction of the object's surface (uniform samples) within ``radius`` of a scan point."""
    mesh = gen.asset(index).visual
    samples, _ = trimesh.sample.sample_surface_even(mesh, 3000, seed=0)
    world = samples @ scan.rotation.T + scan.translation
    dist, _ = cKDTree(scan.points).query(world)
    return float(np.mean(dist < radius))


def test_scan_shapes_and_dtypes(mug_gen):
    scan = mug_gen.scan(0, np.random.default_rng(0))
    assert scan.points.shape == (512, 3) and scan.points.dtype == np.float32
    assert scan.rotation.shape == (3, 3) and scan.translation.shape == (3,)
    np.testing.assert_allclose(scan.rotation @ scan.rotation.T, np.eye(3), atol=1e-9)
    assert np.isclose(np.linalg.det(scan.rotation), 1.0)
    assert scan.instance_id == "mug-train-000" and scan.scale == 1.0
    assert 1 <= scan.num_views <= 4
    asset = mug_gen.asset(0)
    assert set(scan.anchors_world) == set(asset.anchors)
    expected = scan.rotation @ asset.anchor("opening_center") + scan.translation
    np.testing.assert_allclose(scan.anchors_world["opening_center"], expected)
    # The bounding sphere covers the mesh and is not much larger than its bounding box diagonal.
    extent = np.ptp(asset.visual.vertices, axis=0)
    assert extent.max() <= scan.diameter <= np.linalg.norm(extent) + 1e-9


@pytest.mark.parametrize("pose_mode", ["table", "any"])
def test_points_lie_on_the_object_surface(pose_mode):
    with ScanGenerator("bowl", num_instances=1, num_points=512, pose_mode=pose_mode) as gen:
        rng = np.random.default_rng(1)
        for _ in range(3):
            scan = gen.scan(0, rng)
            dist = _surface_distances(gen, 0, scan)
            assert np.mean(dist < 0.003) >= 0.99, np.quantile(dist, [0.5, 0.99])


def test_knife_points_lie_on_surface(knife_gen):
    scan = knife_gen.scan(1, np.random.default_rng(5))
    assert np.mean(_surface_distances(knife_gen, 1, scan) < 0.003) >= 0.99


def test_table_pose_keeps_mug_upright_and_resting(mug_gen):
    rng = np.random.default_rng(2)
    yaws = []
    for _ in range(8):
        scan = mug_gen.scan(0, rng)
        np.testing.assert_allclose(scan.rotation[:, 2], [0, 0, 1], atol=1e-9)
        # Rests on z = 0 like on the table, within the horizontal offset.
        assert abs(scan.points[:, 2].min()) < 0.004
        assert np.all(np.abs(scan.translation[:2]) <= 0.05)
        yaws.append(np.arctan2(scan.rotation[1, 0], scan.rotation[0, 0]))
    assert np.ptp(yaws) > 1.0  # yaw varies


def test_table_pose_keeps_knife_flat_both_faces(knife_gen):
    rng = np.random.default_rng(3)
    signs = []
    for _ in range(12):
        scan = knife_gen.scan(0, rng)
        z_axis = scan.rotation[:, 2]
        np.testing.assert_allclose(abs(z_axis[2]), 1.0, atol=1e-9)
        signs.append(np.sign(z_axis[2]))
    assert set(signs) == {-1.0, 1.0}  # face up and face down both occur


def test_any_pose_spreads_rotations():
    with ScanGenerator("mug", num_instances=1, num_points=256, pose_mode="any", views=1) as gen:
        rng = np.random.default_rng(4)
        ups = np.array([gen.scan(0, rng).rotation[:, 2] for _ in range(10)])
    assert ups[:, 2].min() < 0.0 < ups[:, 2].max()  # upside-down poses occur


def test_deterministic_for_a_seed(mug_gen):
    a = mug_gen.dataset(3, seed=7)
    b = mug_gen.dataset(3, seed=7)
    c = mug_gen.dataset(3, seed=8)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.points, y.points)
        np.testing.assert_array_equal(x.rotation, y.rotation)
        assert x.instance_id == y.instance_id
    assert not np.array_equal(a[0].points, c[0].points)


def test_pairs_are_independent_scans_of_one_object(mug_gen):
    batches = list(mug_gen.iterate_pairs(batch_size=2, seed=3, num_batches=2))
    assert len(batches) == 2 and all(len(batch) == 2 for batch in batches)
    for first, second in batches[0]:
        assert first.instance_id == second.instance_id
        assert not np.allclose(first.rotation, second.rotation)
    again = next(mug_gen.iterate_pairs(batch_size=2, seed=3))
    np.testing.assert_array_equal(again[0][0].points, batches[0][0][0].points)


def test_one_view_sees_less_than_four():
    cover = {}
    for views in (1, 4):
        with ScanGenerator("mug", num_instances=1, num_points=1024, views=(views, views)) as gen:
            rng = np.random.default_rng(11)
            cover[views] = np.mean([_coverage(gen, 0, gen.scan(0, rng)) for _ in range(4)])
    assert cover[1] + 0.15 < cover[4], cover


def test_noise_and_dropout_change_points_but_keep_shape():
    kwargs = dict(category="bowl", num_instances=1, num_points=512, views=(2, 2))
    with (
        ScanGenerator(**kwargs) as clean_gen,
        ScanGenerator(**kwargs, depth_noise=0.002, dropout=0.3) as noisy_gen,
    ):
        clean = clean_gen.scan(0, 9)
        noisy = noisy_gen.scan(0, 9)
        np.testing.assert_array_equal(clean.rotation, noisy.rotation)  # same pose draws
        assert noisy.points.shape == clean.points.shape
        assert not np.allclose(noisy.points, clean.points)
        dist = _surface_distances(noisy_gen, 0, noisy)
        assert np.median(dist) < 0.004 and np.mean(dist < 0.01) > 0.95
        # The noisy cloud still covers the same object: bounding boxes agree to a centimetre.
        np.testing.assert_allclose(noisy.points.min(0), clean.points.min(0), atol=0.01)
        np.testing.assert_allclose(noisy.points.max(0), clean.points.max(0), atol=0.01)


def test_npz_round_trip(tmp_path, mug_gen, knife_gen):
    scans = mug_gen.dataset(2, seed=1) + knife_gen.dataset(1, seed=1)
    path = save_scans(tmp_path / "scans.npz", scans)
    loaded = load_scans(path)
    assert len(loaded) == 3
    for a, b in zip(scans, loaded, strict=True):
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.rotation, b.rotation)
        np.testing.assert_array_equal(a.translation, b.translation)
        assert (a.instance_id, a.scale, a.diameter, a.num_views) == (
            b.instance_id,
            b.scale,
            b.diameter,
            b.num_views,
        )
        assert set(a.anchors_world) == set(b.anchors_world)
        for name, value in a.anchors_world.items():
            np.testing.assert_array_equal(value, b.anchors_world[name])
    with np.load(path, allow_pickle=False) as f:  # plain arrays only
        assert "points" in f.files
    assert load_scans(save_scans(tmp_path / "empty.npz", [])) == []


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(category="cup"),
        dict(category="mug", split="val"),
        dict(category="mug", num_points=0),
        dict(category="mug", image_size=4),
        dict(category="mug", views=(0, 2)),
        dict(category="mug", views=(3, 2)),
        dict(category="mug", views=(1, 99)),
        dict(category="mug", pose_mode="upright"),
        dict(category="mug", depth_noise=-0.001),
        dict(category="mug", dropout=1.0),
        dict(category="mug", voxel_size=0.0),
    ],
)
def test_bad_arguments_raise(kwargs):
    with pytest.raises(InvalidParameterError):
        ScanGenerator(**kwargs)


def test_bad_calls_raise(mug_gen, tmp_path):
    with pytest.raises(InvalidParameterError):
        mug_gen.scan(5, 0)
    with pytest.raises(InvalidParameterError):
        mug_gen.scan(-1, 0)
    with pytest.raises(InvalidParameterError):
        next(mug_gen.iterate_pairs(batch_size=0, seed=0))
    with pytest.raises(InvalidParameterError):
        save_scans(tmp_path / "scans.pkl", [])
