"""The keypoint-measured size frame: scale and centre, round trips, the training reference, bad input.

The runner with a size frame is tested with the other runner tests (test_policy_training.py)."""

from __future__ import annotations

import numpy as np
import pytest

from keygen.errors import InvalidParameterError
from keygen.policies.size_frame import KEYPOINT_CACHE, SizeFrame, keypoint_spread, reference_spread


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
