"""benchmarks/target_frame_accuracy.py: the axis error ignores the slot's direction, and one
observation's errors come from the frame measured on the block's labelled points."""

from __future__ import annotations

import numpy as np
import pytest

from keygen.geometry.rotations import yaw_matrix


@pytest.fixture(scope="module")
def accuracy(load_benchmark_script):
    return load_benchmark_script("target_frame_accuracy")


def test_axis_error_is_taken_modulo_a_half_turn(accuracy) -> None:
    assert accuracy.axis_error_deg(0.0, np.array([1.0, 0.0, 0.0])) == pytest.approx(0.0)
    assert accuracy.axis_error_deg(np.pi, np.array([2.0, 0.0, 0.0])) == pytest.approx(0.0, abs=1e-6)
    assert accuracy.axis_error_deg(np.radians(100), np.array([1.0, 0.0, 0.0])) == pytest.approx(80.0)
    assert accuracy.axis_error_deg(np.pi / 2, np.array([1.0, 0.0, 0.0])) == pytest.approx(90.0)


def test_errors_of_a_constructed_block(accuracy) -> None:
    rng = np.random.default_rng(0)
    # A 16 x 9 cm top face with a 10 x 1.2 cm slot along the block's x, turned by 0.8 rad.
    gx, gy = np.meshgrid(np.linspace(-0.08, 0.08, 33), np.linspace(-0.045, 0.045, 19))
    top = np.column_stack([gx.ravel(), gy.ravel()])
    top = top[~((np.abs(top[:, 0]) < 0.05) & (np.abs(top[:, 1]) < 0.006))]
    block = np.column_stack([top, np.full(len(top), 0.11)]) @ yaw_matrix(0.8).T + [0.5, -0.2, 0.0]
    knife = rng.uniform([0.3, 0.0, 0.0], [0.4, 0.1, 0.02], (50, 3))
    cloud = np.concatenate([knife, block])
    ids = np.concatenate([np.ones(50, int), np.full(len(block), 2)])
    slot_axis = yaw_matrix(0.8) @ [1.0, 0.0, 0.0]
    axis_err, centre_cm = accuracy.errors(cloud, ids, slot_axis, np.array([0.5, -0.2, 0.11]))
    assert axis_err < 0.5 and centre_cm < 0.2
    # The other axis of the block reads as a 90 degree error.
    across = yaw_matrix(0.8) @ [0.0, 1.0, 0.0]
    assert accuracy.errors(cloud, ids, across, np.array([0.5, -0.2, 0.11]))[0] > 89.0


def test_shared_summary_of_an_error_list(load_benchmark_script) -> None:
    summary = load_benchmark_script("_first_step_accuracy").summarise(np.array([1.0, 2.0, 3.0]))
    assert summary["median"] == 2.0 and summary["max"] == 3.0 and 2.0 < summary["p95"] < 3.0
