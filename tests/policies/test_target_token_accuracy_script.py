"""benchmarks/target_token_accuracy.py: one observation's errors come from the token measured on the
box's labelled points, and a recording's first steps are compared with their anchors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from keygen.data.store import ACTION_KEY, EpisodeStore
from keygen.geometry.rotations import yaw_matrix


@pytest.fixture(scope="module")
def accuracy(load_benchmark_script):
    return load_benchmark_script("target_token_accuracy")


def _scene(centre=(0.5, -0.2), yaw: float = 0.7, outer=(0.08, 0.07), height: float = 0.06):
    """A mug blob (label 1) and an open box's four walls (label 2), outer half sizes ``outer``."""
    rng = np.random.default_rng(0)
    hx, hy = outer
    walls = []
    for side in (-1, 1):
        walls.append(
            np.column_stack([np.full(40, side * hx), rng.uniform(-hy, hy, 40), rng.uniform(0, height, 40)])
        )
        walls.append(
            np.column_stack([rng.uniform(-hx, hx, 40), np.full(40, side * hy), rng.uniform(0, height, 40)])
        )
    box = np.concatenate(walls)
    box[::10, 2] = height
    box = box @ yaw_matrix(yaw).T + [centre[0], centre[1], 0.0]
    mug = rng.uniform([0.4, 0.1, 0.0], [0.5, 0.2, 0.1], (60, 3))
    cloud = np.concatenate([mug, box]).astype(np.float32)
    ids = np.concatenate([np.ones(60, np.int32), np.full(len(box), 2, np.int32)])
    return cloud, ids


def test_errors_of_a_constructed_box(accuracy) -> None:
    cloud, ids = _scene()
    inner = np.array([0.071, 0.062, 0.027])  # walls 0.9 and 0.8 cm thick
    centre_cm, top_cm, wall_cm = accuracy.errors(cloud, ids, np.array([0.5, -0.2, 0.06]), inner)
    assert centre_cm < 0.05 and top_cm < 1e-3
    assert wall_cm == pytest.approx(0.85, abs=0.05)
    # Anchors listing the inner sizes in the other order give the same wall thickness.
    assert accuracy.errors(cloud, ids, np.array([0.5, -0.2, 0.06]), inner[[1, 0, 2]])[2] == pytest.approx(
        wall_cm
    )
    # A centre 3 cm off reads as 3 cm.
    assert accuracy.errors(cloud, ids, np.array([0.53, -0.2, 0.06]), inner)[0] == pytest.approx(3.0, abs=0.05)


def test_main_on_a_recording(accuracy, tmp_path: Path, capsys) -> None:
    store = EpisodeStore(tmp_path / "pour.zarr", mode="w")
    for e, centre in enumerate([(0.5, -0.2), (0.45, -0.17)]):
        cloud, ids = _scene(centre, yaw=0.3 * e)
        steps = 3
        store.append_episode(
            {
                "object_cloud": np.repeat(cloud[None], steps, 0),
                "object_cloud_ids": np.repeat(ids[None], steps, 0),
                "proprio": np.zeros((steps, 10), np.float32),
                ACTION_KEY: np.zeros((steps, 10), np.float32),
                "anchors/container_center": np.repeat(np.array([[*centre, 0.06]], np.float32), steps, 0),
                "anchors/container_half_extents": np.repeat(
                    np.array([[0.071, 0.062, 0.027]], np.float32), steps, 0
                ),
            },
            {"task": "pour", "seed": e, "success": True},
        )
    out = tmp_path / "acc.json"
    result = accuracy.main([str(tmp_path / "pour.zarr"), "--out", str(out)])
    assert result["episodes"] == 2 and result["centre_error_cm"]["max"] < 0.05
    assert out.is_file() and "centre_error_cm" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        accuracy.main([str(tmp_path / "pour.zarr"), "--split", "test"])
