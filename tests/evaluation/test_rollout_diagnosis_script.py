"""benchmarks/rollout_diagnosis.py: the pour fields (how far the mug leans, where its opening is
relative to the box) on hand-built anchors whose answers are known."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="module")
def m(load_benchmark_script):
    return load_benchmark_script("rollout_diagnosis")


def _anchors(axis: np.ndarray, opening: np.ndarray, box_yaw: float) -> dict:
    return {
        "bottom_center": opening - axis,
        "opening_center": opening,
        "container_center": np.array([0.5, -0.2, 0.06]),
        "container_x_axis": np.array([np.cos(box_yaw), np.sin(box_yaw), 0.0]),
        "container_half_extents": np.array([0.08, 0.06, 0.03]),
    }


def test_upright_mug_over_the_box_centre_leans_zero_and_sits_at_the_origin(m) -> None:
    tilt, dist, in_box = m.pour_tip_state(
        _anchors(np.array([0.0, 0.0, 0.09]), np.array([0.5, -0.2, 0.2]), 0.3)
    )
    assert tilt == pytest.approx(0.0, abs=1e-6)
    assert dist == pytest.approx(0.0, abs=1e-9) and in_box == pytest.approx([0.0, 0.0], abs=1e-9)


@pytest.mark.parametrize("lean_deg", [30.0, 90.0, 135.0])
def test_lean_is_the_angle_of_the_axis_from_vertical(m, lean_deg) -> None:
    a = np.deg2rad(lean_deg)
    axis = 0.09 * np.array([np.sin(a) * np.cos(1.0), np.sin(a) * np.sin(1.0), np.cos(a)])
    tilt, _, _ = m.pour_tip_state(_anchors(axis, np.array([0.5, -0.2, 0.2]), 0.0))
    assert tilt == pytest.approx(lean_deg, abs=1e-6)


def test_offset_is_read_in_the_box_frame_in_half_extents(m) -> None:
    # Box turned 90 degrees: its x axis is world +y, its y axis world -x.
    opening = np.array([0.5 - 0.03, -0.2 + 0.04, 0.2])  # 4 cm along the box's x, 3 cm along its y
    tilt, dist, in_box = m.pour_tip_state(_anchors(np.array([0.0, 0.0, 0.09]), opening, np.pi / 2))
    assert dist == pytest.approx(5.0)
    assert in_box == pytest.approx([0.04 / 0.08, 0.03 / 0.06])
