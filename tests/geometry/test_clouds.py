import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

import keygen.geometry.clouds as clouds
from keygen.errors import InvalidParameterError
from keygen.geometry import (
    chamfer_distance,
    crop_box,
    farthest_point_sample,
    nearest_distances,
    normalize_cloud,
    random_subset,
    voxel_downsample,
)

SETTINGS = settings(max_examples=50, deadline=None)
seeds = st.integers(0, 2**32 - 1)


def cloud(seed: int = 0, n: int = 1000) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1.0, 1.0, (n, 3))


# -- crop_box -----------------------------------------------------------------------------
def test_crop_box_keeps_inside_points_in_order():
    pts = cloud(0)
    lo, hi = np.array([-0.5, -0.2, 0.0]), np.array([0.5, 0.8, 1.0])
    out, idx = crop_box(pts, lo, hi, return_index=True)
    inside = np.all((pts >= lo) & (pts <= hi), axis=1)
    np.testing.assert_array_equal(idx, np.flatnonzero(inside))
    np.testing.assert_array_equal(out, pts[idx])
    assert np.all(np.diff(idx) > 0)


def test_crop_box_inclusive_bounds_and_empty_results():
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]])
    np.testing.assert_array_equal(crop_box(pts, [0, 0, 0], [1, 1, 1]), pts[:2])
    assert crop_box(pts, [5, 5, 5], [6, 6, 6]).shape == (0, 3)
    out, idx = crop_box(np.zeros((0, 3)), [0, 0, 0], [1, 1, 1], return_index=True)
    assert out.shape == (0, 3) and idx.shape == (0,)


def test_crop_box_validation():
    with pytest.raises(InvalidParameterError, match="lo <= hi"):
        crop_box(cloud(), [1, 0, 0], [0, 1, 1])
    with pytest.raises(InvalidParameterError, match=r"\(3,\)"):
        crop_box(cloud(), [0, 0], [1, 1])


# -- voxel_downsample ---------------------------------------------------------------------
@SETTINGS
@given(seed=seeds, voxel=st.floats(0.05, 1.0))
def test_voxel_downsample_one_point_per_voxel(seed, voxel):
    pts = cloud(seed, 500)
    out, idx = voxel_downsample(pts, voxel, return_index=True)
    np.testing.assert_array_equal(out, pts[idx])
    assert np.all(np.diff(idx) > 0)  # input order, no duplicates
    keys_all = {tuple(k) for k in np.floor(pts / voxel).astype(int)}
    keys_out = [tuple(k) for k in np.floor(out / voxel).astype(int)]
    assert len(keys_out) == len(set(keys_out)) == len(keys_all)


def test_voxel_representative_is_nearest_to_centroid():
    # Three points in one voxel: the middle one is nearest the centroid.
    pts = np.array([[0.01, 0.01, 0.01], [0.05, 0.05, 0.05], [0.08, 0.08, 0.08], [0.5, 0.5, 0.5]])
    out, idx = voxel_downsample(pts, 0.1, return_index=True)
    np.testing.assert_array_equal(idx, [1, 3])
    # Exact ties go to the lower index (dyadic values keep the centroid exactly half-way).
    tie = np.array([[0.75, 0.5, 0.5], [0.25, 0.5, 0.5]])
    np.testing.assert_array_equal(voxel_downsample(tie, 1.0, return_index=True)[1], [0])


def test_voxel_grid_is_anchored_at_origin_and_deterministic():
    pts = cloud(3, 2000)
    a = voxel_downsample(pts, 0.2)
    np.testing.assert_array_equal(a, voxel_downsample(pts.copy(), 0.2))
    # Adding far-away points does not change the selection near the origin.
    extra = np.vstack([pts, [[50.0, 50.0, 50.0]]])
    np.testing.assert_array_equal(voxel_downsample(extra, 0.2)[:-1], a)
    # A voxel larger than the cloud leaves one point per occupied octant-aligned cell.
    assert len(voxel_downsample(pts, 10.0)) == 8


def test_voxel_downsample_huge_extent_falls_back():
    pts = np.array([[0.0, 0.0, 0.0], [1e15, 1e15, 1e15], [1e-4, 0.0, 0.0]])
    np.testing.assert_array_equal(voxel_downsample(pts, 1e-3, return_index=True)[1], [0, 1])


def test_voxel_downsample_keeps_float32_on_a_large_cloud():
    pts = np.random.default_rng(0).uniform(-0.5, 0.5, (100_000, 3)).astype(np.float32)
    out = voxel_downsample(pts, 0.01)
    assert out.dtype == np.float32 and 50_000 < len(out) < 100_000


@pytest.mark.parametrize("size", [0.0, -0.1, np.nan, np.inf])
def test_voxel_size_must_be_positive(size):
    with pytest.raises(InvalidParameterError, match="voxel_size"):
        voxel_downsample(cloud(), size)


# -- farthest_point_sample ----------------------------------------------------------------
def brute_force_fps(pts: np.ndarray, n: int, start: int) -> np.ndarray:
    chosen = [start]
    d = np.linalg.norm(pts - pts[start], axis=1)
    for _ in range(n - 1):
        chosen.append(int(np.argmax(d)))
        d = np.minimum(d, np.linalg.norm(pts - pts[chosen[-1]], axis=1))
    return np.array(chosen)


def test_fps_matches_greedy_definition():
    pts = cloud(1, 300)
    out, idx = farthest_point_sample(pts, 32, return_index=True)
    np.testing.assert_array_equal(idx, brute_force_fps(pts, 32, 0))
    np.testing.assert_array_equal(out, pts[idx])
    idx5 = farthest_point_sample(pts, 32, start_index=5, return_index=True)[1]
    np.testing.assert_array_equal(idx5, brute_force_fps(pts, 32, 5))


def test_fps_numpy_fallback_matches_library(monkeypatch):
    pts = cloud(2, 400)
    expected = farthest_point_sample(pts, 50, start_index=7, return_index=True)[1]
    monkeypatch.setattr(clouds, "fpsample", None)
    np.testing.assert_array_equal(
        farthest_point_sample(pts, 50, start_index=7, return_index=True)[1], expected
    )


def test_fps_seed_is_deterministic():
    pts = cloud(4, 500)
    a = farthest_point_sample(pts, 20, seed=123, return_index=True)[1]
    b = farthest_point_sample(pts, 20, seed=np.random.default_rng(123), return_index=True)[1]
    np.testing.assert_array_equal(a, b)
    start = int(np.random.default_rng(123).integers(500))
    assert a[0] == start
    with pytest.raises(InvalidParameterError, match="not both"):
        farthest_point_sample(pts, 20, start_index=1, seed=1)


@SETTINGS
@given(n_pts=st.integers(1, 40), n=st.integers(1, 100))
def test_fps_always_returns_n_rows_and_pads_cyclically(n_pts, n):
    pts = cloud(n_pts, n_pts)
    out, idx = farthest_point_sample(pts, n, return_index=True)
    assert out.shape == (n, 3) and idx.shape == (n,)
    np.testing.assert_array_equal(out, pts[idx])
    if n <= n_pts:
        assert len(set(idx.tolist())) == n
    else:
        base = farthest_point_sample(pts, n_pts, return_index=True)[1]
        assert sorted(base.tolist()) == list(range(n_pts))  # every point once
        np.testing.assert_array_equal(idx, base[np.arange(n) % n_pts])


def test_fps_fast_method_spreads_points():
    pts = cloud(5, 20_000)
    exact, idx_exact = farthest_point_sample(pts, 256, return_index=True)
    fast, idx_fast = farthest_point_sample(pts, 256, method="fast", return_index=True)
    assert fast.shape == (256, 3) and len(set(idx_fast.tolist())) == 256
    np.testing.assert_array_equal(
        idx_fast, farthest_point_sample(pts, 256, method="fast", return_index=True)[1]
    )
    # Covering radius: the fast sampler is nearly as even as exact FPS, far better than random.
    cover = {name: cKDTree(s).query(pts)[0].max() for name, s in [("exact", exact), ("fast", fast)]}
    rand = cKDTree(random_subset(pts, 256, rng=0)).query(pts)[0].max()
    assert cover["fast"] < 1.1 * cover["exact"] < rand


def test_fps_validation():
    with pytest.raises(InvalidParameterError, match=">= 1"):
        farthest_point_sample(cloud(), 0)
    with pytest.raises(InvalidParameterError, match="start_index"):
        farthest_point_sample(cloud(n=10), 3, start_index=10)
    with pytest.raises(InvalidParameterError, match="method"):
        farthest_point_sample(cloud(), 3, method="approximate")


# -- validation shared by the cloud functions ---------------------------------------------
@pytest.mark.parametrize(
    "bad, message",
    [(np.zeros((0, 3)), "empty"), (np.zeros((5, 2)), r"\(N, 3\)"), (np.array([[0.0, np.nan, 0.0]]), "NaN")],
)
@pytest.mark.parametrize(
    "fn",
    [
        lambda p: voxel_downsample(p, 0.1),
        lambda p: farthest_point_sample(p, 4),
        lambda p: random_subset(p, 1, rng=0),
        normalize_cloud,
        lambda p: chamfer_distance(p, cloud()),
        lambda p: nearest_distances(cloud(), p),
    ],
)
def test_bad_clouds_rejected(fn, bad, message):
    with pytest.raises(InvalidParameterError, match=message):
        fn(bad)


def test_crop_box_rejects_nan_and_bad_shapes():
    with pytest.raises(InvalidParameterError, match="NaN"):
        crop_box(np.array([[np.nan, 0.0, 0.0]]), [0, 0, 0], [1, 1, 1])
    with pytest.raises(InvalidParameterError, match=r"\(N, 3\)"):
        crop_box(np.zeros(3), [0, 0, 0], [1, 1, 1])


# -- distances and normalisation ----------------------------------------------------------
def test_nearest_distances_against_brute_force():
    q, p = cloud(6, 50), cloud(7, 80)
    d, idx = nearest_distances(q, p, return_index=True)
    full = np.linalg.norm(q[:, None] - p[None], axis=-1)
    np.testing.assert_allclose(d, full.min(axis=1))
    np.testing.assert_array_equal(idx, full.argmin(axis=1))


@SETTINGS
@given(seed=seeds)
def test_chamfer_properties(seed):
    rng = np.random.default_rng(seed)
    a, b = rng.uniform(-1, 1, (60, 3)), rng.uniform(-1, 1, (40, 3))
    assert chamfer_distance(a, a) == 0.0
    assert chamfer_distance(a, rng.permutation(a)) == 0.0
    assert np.isclose(chamfer_distance(a, b), chamfer_distance(b, a))
    assert chamfer_distance(a, b) > 0
    # A pure shift of a single point moves the distance by exactly that shift.
    assert np.isclose(chamfer_distance(a[:1], a[:1] + [0.0, 0.0, 0.3]), 0.3)


@SETTINGS
@given(seed=seeds, scale=st.floats(1e-3, 1e3), shift=st.floats(-10, 10))
def test_normalize_cloud_round_trip(seed, scale, shift):
    pts = cloud(seed, 100) * scale + shift
    normed, centre, s = normalize_cloud(pts)
    np.testing.assert_allclose(normed.mean(axis=0), 0.0, atol=1e-9)
    assert np.isclose(np.linalg.norm(normed, axis=1).max(), 1.0)
    np.testing.assert_allclose(normed * s + centre, pts, rtol=1e-9, atol=1e-9 * (scale + abs(shift)))


def test_normalize_single_point():
    normed, centre, s = normalize_cloud(np.array([[1.0, 2.0, 3.0]]))
    np.testing.assert_array_equal(normed, [[0.0, 0.0, 0.0]])
    np.testing.assert_array_equal(centre, [1.0, 2.0, 3.0])
    assert s == 1.0


def test_random_subset():
    pts = cloud(8, 100)
    out, idx = random_subset(pts, 30, rng=0, return_index=True)
    assert len(set(idx.tolist())) == 30
    np.testing.assert_array_equal(out, pts[idx])
    np.testing.assert_array_equal(
        idx, random_subset(pts, 30, rng=np.random.default_rng(0), return_index=True)[1]
    )
    assert random_subset(pts, 500, rng=1, replace=True).shape == (500, 3)
    with pytest.raises(InvalidParameterError, match="replace=True"):
        random_subset(pts, 101, rng=0)
