"""benchmarks/yaw_frame_accuracy.py: the heading proxy and the offset-removed yaw error."""

from __future__ import annotations

import numpy as np
import pytest


def test_heading_points_from_the_centre_to_the_handle(yaw_frame_accuracy) -> None:
    mug = {"bottom_center": np.array([0.5, 0.1, 0.0]), "handle_grasp": np.array([0.5, 0.2, 0.05])}
    assert yaw_frame_accuracy._heading("pour", mug) == pytest.approx(np.pi / 2)
    knife = {"blade_tip": np.array([0.6, 0.1, 0.01]), "handle_grasp": np.array([0.4, 0.1, 0.02])}
    assert abs(yaw_frame_accuracy._heading("knife", knife)) == pytest.approx(np.pi)


def test_errors_are_measured_after_the_constant_offset_and_wrap(yaw_frame_accuracy) -> None:
    # The frame's zero is arbitrary: a constant offset near the wrap-around is removed exactly.
    headings = np.linspace(-3.0, 3.0, 7)
    offset = 3.1
    train = [(h + offset, h) for h in headings]
    assert yaw_frame_accuracy.circular_offset(train) == pytest.approx(offset)
    deviations = np.radians([0.0, 2.0, -5.0])
    test = [(h + offset + d, h) for h, d in zip(headings[:3], deviations, strict=True)]
    np.testing.assert_allclose(yaw_frame_accuracy.abs_errors_deg(test, offset), [0.0, 2.0, 5.0], atol=1e-9)
