"""Completion of partial scans of surfaces of revolution about their fitted vertical axis."""

from __future__ import annotations

import numpy as np
import pytest

from keygen.errors import InvalidParameterError
from keygen.keypoints import completion
from keygen.keypoints.completion import complete_about_axis, fit_vertical_axis
from keygen.keypoints.refine import InferenceSettings

CENTRE = np.array([0.31, -0.12])
RADIUS = 0.04


def _half_cylinder(n: int = 800, seed: int = 0) -> np.ndarray:
    """The half of a tapered cup one camera sees: angles 0..pi, heights 0..8 cm."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0.0, np.pi, n)
    height = rng.uniform(0.0, 0.08, n)
    radius = RADIUS * (1.0 - 1.5 * height)  # narrower towards the top
    return np.column_stack([CENTRE[0] + radius * np.cos(angle), CENTRE[1] + radius * np.sin(angle), height])


def _handle(n: int = 60) -> np.ndarray:
    """A blob well outside the body (a handle) on the seen side."""
    rng = np.random.default_rng(1)
    return np.column_stack(
        [np.full(n, CENTRE[0] + 2.0 * RADIUS), np.full(n, CENTRE[1]), rng.uniform(0.02, 0.06, n)]
    ) + rng.normal(0.0, 0.002, (n, 3))


def test_the_axis_of_a_half_seen_body_is_found_despite_a_handle():
    cloud = np.concatenate([_half_cylinder(), _handle()])
    point, radii = fit_vertical_axis(cloud)
    assert np.linalg.norm(point[:2] - CENTRE) < 1e-3
    assert np.all((radii > 0.6 * RADIUS) & (radii < 1.05 * RADIUS))


def _large_handle(n: int = 350, seed: int = 2) -> np.ndarray:
    """A loop in the vertical plane through the axis, reaching 2.2 radii out over most of the body's
    height: with 350 points next to 500 on the body it holds two fifths of the cloud."""
    rng = np.random.default_rng(seed)
    t = rng.uniform(-np.pi / 2, np.pi / 2, n)
    loop = np.column_stack(
        [
            CENTRE[0] + RADIUS * (1.0 + 1.2 * np.cos(t)),
            CENTRE[1] + rng.normal(0.0, 0.004, n),
            0.04 + 0.035 * np.sin(t),
        ]
    )
    return loop + rng.normal(0.0, 0.001, (n, 3))


def test_a_handle_holding_two_fifths_of_the_points_does_not_pull_the_axis(monkeypatch):
    cloud = np.concatenate([_half_cylinder(500), _large_handle()])
    point, radii = fit_vertical_axis(cloud)
    assert np.linalg.norm(point[:2] - CENTRE) < 1e-3
    assert np.all((radii > 0.6 * RADIUS) & (radii < 1.05 * RADIUS))
    again, _ = fit_vertical_axis(cloud)
    np.testing.assert_array_equal(point, again)  # the consensus is seeded
    # Without the consensus the trimmed least squares alone keeps the handle and misses by centimetres:
    # the case the consensus is there for.
    monkeypatch.setattr(completion, "_RANSAC_HYPOTHESES", 0)
    trimmed_only, _ = fit_vertical_axis(cloud)
    assert np.linalg.norm(trimmed_only[:2] - CENTRE) > 0.01


def test_completion_covers_the_unseen_half_and_never_copies_the_handle():
    body, handle = _half_cylinder(), _handle()
    cloud = np.concatenate([body, handle])
    out = complete_about_axis(cloud, copies=6)
    assert out.dtype == np.float32 and out.shape[1] == 3
    np.testing.assert_allclose(out[: len(cloud)], cloud.astype(np.float32))  # the input comes first
    assert len(out) == len(cloud) + 5 * len(body)  # every body point turned 5 times, the handle once
    angles = np.arctan2(out[:, 1] - CENTRE[1], out[:, 0] - CENTRE[0])
    counts, _ = np.histogram(angles, bins=12, range=(-np.pi, np.pi))
    assert counts.min() > 0.02 * len(out)  # every side is covered, the half no camera saw included
    far = np.linalg.norm(out[:, :2] - CENTRE, axis=1) > 1.5 * RADIUS
    assert far.sum() == len(handle)


def test_completion_follows_any_up_axis():
    cloud = _half_cylinder()
    turn = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # world z -> -y
    upright = complete_about_axis(cloud, copies=4)
    lying = complete_about_axis(cloud @ turn.T, up=turn @ np.array([0.0, 0.0, 1.0]), copies=4)
    np.testing.assert_allclose(np.sort(lying @ turn, axis=0), np.sort(upright, axis=0), atol=1e-5)


def test_off_small_or_flat_clouds_come_back_unchanged():
    cloud = _half_cylinder()
    np.testing.assert_array_equal(complete_about_axis(cloud, copies=1), cloud.astype(np.float32))
    few = cloud[:10]
    np.testing.assert_array_equal(complete_about_axis(few), few.astype(np.float32))
    flat = cloud.copy()
    flat[:, 2] = 0.0
    np.testing.assert_array_equal(complete_about_axis(flat), flat.astype(np.float32))
    with pytest.raises(InvalidParameterError):
        complete_about_axis(cloud[:, :2])
    with pytest.raises(InvalidParameterError):
        complete_about_axis(cloud, tolerance=0.5)


def test_settings_round_trip_and_old_files_mean_off():
    s = InferenceSettings(ensemble=4, axial_copies=6)
    assert InferenceSettings.from_json(s.to_json()).axial_copies == 6
    assert s.replace(ensemble=1, axial_copies=0).axial_copies == 0 and s.replace(ensemble=1).axial_copies == 6
    assert InferenceSettings.from_json({"ensemble": 4, "refine_iters": 0}).axial_copies == 0
    with pytest.raises(InvalidParameterError):
        InferenceSettings(axial_copies=-1)
