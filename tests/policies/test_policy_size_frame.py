"""The keypoint-measured size frame: scale and centre, round trips, the training reference, bad input.

The runner with a size frame is tested with the other runner tests (test_policy_training.py)."""

from __future__ import annotations

import numpy as np
import pytest

from keygen.errors import InvalidParameterError
from keygen.evaluation.evaluate import SIZE_FRAMES
from keygen.policies.size_frame import (
    KEYPOINT_CACHE,
    SIZE_MODES,
    SizeFrame,
    cached_episode_ends,
    keypoint_axis_spreads,
    keypoint_spread,
    reference_spread,
    rest_axis_references,
    size_mode,
)


def test_measure_takes_the_spread_ratio_and_the_objects_footprint() -> None:
    rng = np.random.default_rng(0)
    kp = rng.uniform(-0.05, 0.05, (10, 3)) + [0.5, 0.1, 0.08]
    points = rng.uniform(-0.06, 0.06, (200, 3)) + [0.5, 0.1, 0.07]
    frame = SizeFrame.measure(kp, points, keypoint_spread(kp) / 1.5)
    assert frame.scale == pytest.approx(1.5)
    np.testing.assert_allclose(frame.centre[:2], kp.mean(0)[:2])
    assert frame.centre[2] == points[:, 2].min()  # on the table under the object
    # Twice the object about that centre: twice the scale, the same centre.
    c = frame.centre
    bigger = SizeFrame.measure(c + 2 * (kp - c), c + 2 * (points - c), keypoint_spread(kp) / 1.5)
    assert bigger.scale == pytest.approx(3.0)
    np.testing.assert_allclose(bigger.centre, c, atol=1e-12)


def test_to_policy_and_back_round_trip_positions_only() -> None:
    rng = np.random.default_rng(1)
    frame = SizeFrame(np.array([0.5, -0.1, 0.02]), 1.6)
    feats = {
        "cloud": rng.uniform(0, 1, (32, 3)).astype(np.float32),
        "keypoints": rng.uniform(0, 1, (6, 3)).astype(np.float32),
        "proprio": rng.uniform(0, 1, 10).astype(np.float32),
    }
    before = {k: v.copy() for k, v in feats.items()}
    scaled = frame.to_policy(feats)
    for key in feats:  # inputs are only read
        np.testing.assert_array_equal(feats[key], before[key])
        assert scaled[key].dtype == np.float32 and scaled[key].shape == feats[key].shape
    c = frame.centre
    np.testing.assert_allclose(scaled["cloud"], c + (feats["cloud"] - c) / 1.6, atol=1e-6)
    np.testing.assert_array_equal(scaled["proprio"][3:], feats["proprio"][3:])  # rotation, gripper
    plan = np.concatenate([scaled["keypoints"], rng.uniform(0, 1, (6, 7))], axis=1).astype(np.float32)
    world = frame.to_world(plan)
    np.testing.assert_allclose(world[:, :3], feats["keypoints"], atol=1e-6)
    np.testing.assert_array_equal(world[:, 3:], plan[:, 3:])


def test_bad_inputs_are_refused() -> None:
    kp = np.eye(3)
    with pytest.raises(InvalidParameterError, match="reference"):
        SizeFrame.measure(kp, kp, 0.0)
    with pytest.raises(InvalidParameterError, match="object points"):
        SizeFrame.measure(kp, np.zeros((0, 3)), 1.0)
    with pytest.raises(InvalidParameterError, match="no spread"):
        SizeFrame.measure(np.ones((4, 3)), kp, 1.0)
    with pytest.raises(InvalidParameterError, match="keypoints"):
        keypoint_spread(np.zeros(3))


def test_reference_spread_is_the_median_over_the_training_steps(tmp_path) -> None:
    rng = np.random.default_rng(2)
    kp = rng.uniform(0, 0.1, (9, 8, 3)).astype(np.float32)  # 9 steps, 2 objects x 4 keypoints
    np.savez(tmp_path / KEYPOINT_CACHE, keypoints=kp, fingerprint=np.array("x"))
    expected = np.median([keypoint_spread(k[:4]) for k in kp])
    assert reference_spread(tmp_path, 4) == pytest.approx(expected, rel=1e-6)
    with pytest.raises(InvalidParameterError, match="keypoint_cache.npz"):
        reference_spread(tmp_path / "elsewhere", 4)


def test_per_axis_frame_scales_width_and_height_apart() -> None:
    rng = np.random.default_rng(3)
    kp = rng.uniform(-0.05, 0.05, (10, 3)) + [0.5, 0.1, 0.06]
    points = rng.uniform(-0.06, 0.06, (200, 3)) + [0.5, 0.1, 0.06]
    h, v = keypoint_axis_spreads(kp)
    frame = SizeFrame.measure_axes(kp, points, (h / 1.5, v))
    np.testing.assert_allclose(frame.scale, [1.5, 1.5, 1.0])
    np.testing.assert_allclose(frame.centre, SizeFrame.measure(kp, points, 1.0).centre)
    # The same object twice as wide and as tall as before: only the horizontal scale follows the width.
    c = frame.centre
    wide = c + (kp - c) * [2.0, 2.0, 1.0]
    wider = SizeFrame.measure_axes(wide, c + (points - c) * [2.0, 2.0, 1.0], (h / 1.5, v))
    np.testing.assert_allclose(wider.scale, [3.0, 3.0, 1.0])
    np.testing.assert_allclose(wider.centre, c, atol=1e-12)
    # In the policy's copy the wider object has the first one's keypoints; the plan maps back per axis.
    scaled = wider.to_policy({"cloud": wide.astype(np.float32), "proprio": np.zeros(10, np.float32)})
    np.testing.assert_allclose(scaled["cloud"], c + (kp - c) / [1.5, 1.5, 1.0], atol=1e-6)
    plan = np.concatenate([scaled["cloud"], np.ones((10, 7))], axis=1)
    np.testing.assert_allclose(wider.to_world(plan)[:, :3], wide, atol=1e-6)
    with pytest.raises(InvalidParameterError, match="reference spreads"):
        SizeFrame.measure_axes(kp, points, (h, 0.0))
    flat = kp.copy()
    flat[:, 2] = 0.06
    with pytest.raises(InvalidParameterError, match="vertical"):
        SizeFrame.measure_axes(flat, points, (h, v))


def test_rest_references_take_each_episodes_first_step(tmp_path) -> None:
    rng = np.random.default_rng(4)
    kp = rng.uniform(0, 0.1, (9, 8, 3)).astype(np.float32)
    np.savez(tmp_path / KEYPOINT_CACHE, keypoints=kp, fingerprint=np.array("x"))
    ends = np.array([3, 7, 9])
    firsts = [keypoint_axis_spreads(kp[i, :4]) for i in (0, 3, 7)]
    expected = (np.median([f[0] for f in firsts]), np.median([f[1] for f in firsts]))
    assert rest_axis_references(tmp_path, 4, ends) == pytest.approx(expected, rel=1e-6)
    for bad in ([3, 7, 8], [7, 3, 9], []):  # not this cache's steps, not increasing, none
        with pytest.raises(InvalidParameterError, match="episode ends"):
            rest_axis_references(tmp_path, 4, np.array(bad))


def test_size_modes_and_their_torch_free_copy() -> None:
    assert size_mode(False) is None and size_mode(None) is None
    assert size_mode(True) == "uniform" and size_mode("axes") == "axes"
    with pytest.raises(InvalidParameterError, match="size normalisation"):
        size_mode("sideways")
    assert {v for v in SIZE_FRAMES.values() if v} == set(SIZE_MODES)
    assert all(SIZE_FRAMES[m] == size_mode(m) for m in SIZE_FRAMES)


def test_rest_references_default_to_the_boundaries_the_cache_keeps(tmp_path) -> None:
    rng = np.random.default_rng(5)
    kp = rng.uniform(0, 0.1, (9, 8, 3)).astype(np.float32)
    ends = np.array([3, 7, 9])
    np.savez(tmp_path / KEYPOINT_CACHE, keypoints=kp, fingerprint=np.array("x"))
    assert cached_episode_ends(tmp_path) is None  # a cache from before the boundaries were kept
    with pytest.raises(InvalidParameterError, match="episode boundaries"):
        rest_axis_references(tmp_path, 4)
    np.savez(tmp_path / KEYPOINT_CACHE, keypoints=kp, fingerprint=np.array("x"), episode_ends=ends)
    np.testing.assert_array_equal(cached_episode_ends(tmp_path), ends)
    assert rest_axis_references(tmp_path, 4) == pytest.approx(rest_axis_references(tmp_path, 4, ends))
    assert cached_episode_ends(tmp_path / "no-run") is None


def test_keypoint_cache_gains_the_episode_boundaries_without_recomputing(tmp_path) -> None:
    from keygen.policies.data import _cached_keypoints

    kp = np.random.default_rng(6).uniform(0, 0.1, (9, 8, 3)).astype(np.float32)
    ends = np.array([3, 7, 9])
    np.savez(tmp_path / KEYPOINT_CACHE, keypoints=kp, fingerprint=np.array("k"))  # an older cache

    def never() -> np.ndarray:
        raise AssertionError("the cached keypoints were recomputed")

    np.testing.assert_array_equal(_cached_keypoints(tmp_path, "k", never, ends), kp)
    np.testing.assert_array_equal(cached_episode_ends(tmp_path), ends)
    np.testing.assert_array_equal(_cached_keypoints(tmp_path, "k", never, ends), kp)  # now a plain hit
    np.testing.assert_array_equal(_cached_keypoints(tmp_path, "other", lambda: 2 * kp, ends), 2 * kp)


def test_about_xy_moves_only_the_horizontal_centre() -> None:
    frame = SizeFrame(np.array([0.4, -0.2, 0.01]), np.array([1.2, 1.2, 0.9]))
    moved = frame.about_xy(np.zeros(2))
    np.testing.assert_allclose(moved.centre, [0.0, 0.0, 0.01])
    np.testing.assert_allclose(moved.scale, frame.scale)
    np.testing.assert_allclose(frame.centre, [0.4, -0.2, 0.01])  # the original is unchanged
    plan = np.zeros((2, 10))
    plan[:, :3] = [[0.0, 0.0, 0.01], [0.1, 0.0, 0.11]]
    np.testing.assert_allclose(moved.to_world(plan)[0, :3], [0.0, 0.0, 0.01])  # the centre stays put
    np.testing.assert_allclose(moved.to_world(plan)[1, :3], [0.12, 0.0, 0.01 + 0.09])
