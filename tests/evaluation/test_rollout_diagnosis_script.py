"""benchmarks/rollout_diagnosis.py: the pour fields (where the mug's opening is relative to the box
when it tips) on hand-built anchors whose answers are known."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="module")
def m(load_benchmark_script):
    return load_benchmark_script("rollout_diagnosis")


def _anchors(opening: np.ndarray, box_yaw: float) -> dict:
    return {
        "opening_center": opening,
        "container_center": np.array([0.5, -0.2, 0.06]),
        "container_x_axis": np.array([np.cos(box_yaw), np.sin(box_yaw), 0.0]),
        "container_half_extents": np.array([0.08, 0.06, 0.03]),
    }


def test_opening_over_the_box_centre_sits_at_the_origin(m) -> None:
    dist, in_box = m.lip_offset_from_box(_anchors(np.array([0.5, -0.2, 0.2]), 0.3))
    assert dist == pytest.approx(0.0, abs=1e-9) and in_box == pytest.approx([0.0, 0.0], abs=1e-9)


def test_offset_is_read_in_the_box_frame_in_half_extents(m) -> None:
    # Box turned 90 degrees: its x axis is world +y, its y axis world -x.
    opening = np.array([0.5 - 0.03, -0.2 + 0.04, 0.2])  # 4 cm along the box's x, 3 cm along its y
    dist, in_box = m.lip_offset_from_box(_anchors(opening, np.pi / 2))
    assert dist == pytest.approx(5.0)
    assert in_box == pytest.approx([0.04 / 0.08, 0.03 / 0.06])


def test_size_scale_reads_the_runners_measured_frame(m) -> None:
    class Frame:
        def __init__(self, scale):
            self.scale = scale

    class Runner:
        size_frame = None

    runner = Runner()
    assert m._size_scale(runner) is None  # no size frame measured (or none asked for)
    runner.size_frame = Frame(1.23456)
    assert m._size_scale(runner) == 1.2346
    runner.size_frame = Frame(np.array([1.5, 1.5, 2.25]))
    assert m._size_scale(runner) == [1.5, 1.5, 2.25]
    assert m._size_scale(object()) is None  # a runner without the attribute
