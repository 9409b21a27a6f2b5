"""benchmarks/knife_expert_modes.py: the leave-one-out vote, the scene features and the plan labels
(planning itself runs the expert's previews, tens of seconds an episode, so it is not run here)."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="module")
def m(load_benchmark_script):
    return load_benchmark_script("knife_expert_modes")


def _record(heading: float, face_down: bool, hand: int = 0) -> dict:
    return {
        "hand": hand,
        "side": 1,
        "pitch_deg": 0.0,
        "route": "geodesic",
        "face_down": face_down,
        "heading_deg": heading,
        "grasp_in_block_xy": [0.1, -0.2],
        "block_yaw_deg": 30.0,
        "block_xy": [0.6, 0.1],
        "grasp_xy": [0.4, -0.2],
    }


def test_a_plan_the_scene_decides_is_predicted_and_a_coin_flip_is_not(m):
    rng = np.random.default_rng(0)
    x = rng.normal(size=(200, 3))
    decided = ["a" if v > 0 else "b" for v in x[:, 0]]
    assert m.loo_knn_accuracy(x, decided, k=5) > 0.9
    coin = list(rng.choice(["a", "b"], size=200))
    assert 0.3 < m.loo_knn_accuracy(x, coin, k=5) < 0.7


def test_the_vote_leaves_the_episode_itself_out(m):
    # Each point's label differs from every other point's: with itself left out it is never right.
    x = np.arange(6, dtype=float)[:, None]
    assert m.loo_knn_accuracy(x, list("abcdef"), k=1) == 0.0


def test_features_read_the_heading_as_an_angle_and_the_face_as_a_flag(m):
    a, b = m.features(_record(179.0, True)), m.features(_record(-179.0, True))
    assert np.allclose(a[:2], b[:2], atol=0.05)  # +-179 degrees are neighbours
    assert m.features(_record(0.0, True))[2] == 1.0 and m.features(_record(0.0, False))[2] == 0.0
    assert len(a) == 7


def test_mode_labels_name_the_chosen_keys(m):
    r = _record(0.0, False, hand=1)
    assert m.mode_of(r, ("hand", "side")) == "hand=1/side=1"
    assert m.mode_of(r, ("route",)) == "route=geodesic"


def test_world_features_add_the_table_positions_read_from_the_anchors(m):
    anchors = {"slot_center_top": np.array([0.6, 0.1, 0.12]), "handle_grasp": np.array([0.4, -0.2, 0.01])}
    r = {**_record(10.0, False), **m.scene_positions(anchors)}
    w = m.world_features(r)
    assert w[:7] == m.features(r) and w[7:] == [0.6, 0.1, 0.4, -0.2]
