"""The scripted stacking expert: geometry helpers, seeded successes, the grasp retry and give-up."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import keygen  # noqa: F401  (registers the env ids, sets MUJOCO_GL before mujoco loads)
from keygen.expert.runner import make_expert, run_episode
from keygen.expert.stack import StackExpert, far_side_angle, grasp_rotation, lowest_point_z, rim_point
from keygen.geometry.rotations import axis_angle_to_matrix, is_rotation, yaw_matrix


def make_env(split: str, index: int, setting: str):
    return gym.make(
        "keygen/StackBowl-v0",
        object_split=split,
        object_id=index,
        setting=setting,
        include_rgb=False,
        image_size=48,
        num_points=128,
    ).unwrapped


# -- geometry helpers ----------------------------------------------------------------------------------
@pytest.mark.parametrize("yaw_deg", [0.0, 75.0, 180.0, -120.0])
def test_grasp_rotation_points_down_closes_radially_and_turns_the_wrist_least(yaw_deg):
    radial = yaw_matrix(np.radians(yaw_deg)) @ np.array([1.0, 0.0, 0.0])
    home = np.diag([1.0, -1.0, -1.0])  # the robot's home tcp: z down, y along -y of the world
    R = grasp_rotation(radial * 0.07, home)
    assert is_rotation(R)
    np.testing.assert_allclose(R[:, 2], [0.0, 0.0, -1.0], atol=1e-12)
    assert abs(abs(R[:, 1] @ radial) - 1.0) < 1e-12
    # of the two symmetric options the chosen one is within 90 deg of the current wrist yaw
    assert R[:, 1] @ home[:, 1] >= -1e-12


@pytest.mark.parametrize("yaw_deg", [0.0, 75.0, 180.0, -120.0])
def test_the_grasp_goes_to_the_far_side_of_the_rim_whatever_the_yaw(yaw_deg):
    # bowl frame: axis z, rim_grasp on +x at radius 0.07, 8 mm under a rim at 0.05; turned and moved
    R = yaw_matrix(np.radians(yaw_deg)) @ axis_angle_to_matrix(np.array([1.0, 0.0, 0.0]), 0.05)
    t = np.array([0.5, 0.1, 0.0])
    local = {"opening_center": [0, 0, 0.05], "bottom_center": [0, 0, 0.0], "rim_grasp": [0.07, 0, 0.042]}
    anchors = {k: R @ np.asarray(v, float) + t for k, v in local.items()}
    np.testing.assert_allclose(rim_point(anchors, 0.0), anchors["rim_grasp"], atol=1e-12)
    p = rim_point(anchors, far_side_angle(anchors))
    axis = R[:, 2]
    radial = p - anchors["opening_center"]
    assert np.isclose(np.linalg.norm(radial - (radial @ axis) * axis), 0.07)  # on the rim circle
    assert np.isclose(radial @ axis, -0.008)  # at rim_grasp's height
    in_plane = radial - (radial @ axis) * axis
    toward_x = np.array([1.0, 0, 0]) - axis[0] * axis  # world +x in the rim's plane
    np.testing.assert_allclose(in_plane / 0.07, toward_x / np.linalg.norm(toward_x), atol=1e-9)


def test_lowest_point_bounds_a_tilted_bowl():
    upright = {
        "bottom_center": np.array([0.5, 0.1, 0.0]),
        "opening_center": np.array([0.5, 0.1, 0.06]),
        "rim_radius": np.array([0.08]),
    }
    assert lowest_point_z(upright) == pytest.approx(0.0)
    tilt = axis_angle_to_matrix(np.array([1.0, 0.0, 0.0]), np.radians(30.0))
    pivot = np.array([0.5, 0.1, 0.2])
    tilted = {k: pivot + tilt @ (v - pivot) if v.shape == (3,) else v for k, v in upright.items()}
    # the bowl's far bottom edge hangs below its tilted bottom centre by rim_radius * sin(30 deg)
    assert lowest_point_z(tilted) == pytest.approx(tilted["bottom_center"][2] - 0.04)


# -- episodes ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("split", "index", "setting", "seed"), [("test", 1, "hard", 0), ("train", 3, "easy", 2)]
)
def test_expert_stacks_the_bowls(split, index, setting, seed):
    env = make_env(split, index, setting)
    expert = make_expert("stack")
    assert isinstance(expert, StackExpert)
    result = run_episode(env, expert, seed=seed)
    assert result.success, (result.failure, expert.phase, result.metrics)
    assert result.failure is None and expert.attempts == 1
    assert result.metrics["nested"] == 1.0 and result.metrics["still_seconds"] >= 1.0
    assert result.steps < env.max_steps


def test_same_seed_same_episode():
    env = make_env("policy", 0, "hard")
    runs = []
    for _ in range(2):
        actions: list[np.ndarray] = []
        record = actions.append
        result = run_episode(env, StackExpert(), seed=5, on_step=lambda o, a, i, rec=record: rec(a.copy()))
        runs.append((result, np.array(actions)))
    (first, a1), (second, a2) = runs
    assert first.success == second.success and first.steps == second.steps
    np.testing.assert_array_equal(a1, a2)
    assert first.metrics == second.metrics


def _run_with_stale_start(env, expert: StackExpert, seed: int, shift: np.ndarray) -> dict:
    """An episode whose first anchors (only) place bowl A ``shift`` away from where it stands."""
    obs, info = env.reset(seed=seed)
    stale = dict(info)
    stale["anchors"] = {
        k: v + shift if k in ("rim_grasp", "opening_center", "bottom_center") else v
        for k, v in info["anchors"].items()
    }
    expert.reset(env, obs, stale)
    info = stale
    while (action := expert.act(obs, info)) is not None:
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            break
    return info


def test_a_missed_grasp_is_retried_once_from_fresh_anchors():
    env = make_env("test", 1, "hard")
    expert = StackExpert()
    # the first approach closes on air 6 cm beside the bowl; the retry reads the true anchors
    info = _run_with_stale_start(env, expert, seed=0, shift=np.array([0.0, 0.06, 0.0]))
    assert expert.attempts == 2
    assert expert.failure is None
    assert info["success"], (expert.phase, info["metrics"])


class _NeverHolds(StackExpert):
    """A grasp guard that never sees the bowl in the hand: every attempt counts as a miss."""

    def grip_detected(self, held_before: np.ndarray) -> bool:
        return False


def test_two_misses_give_up_with_grasp_missed():
    env = make_env("test", 2, "hard")
    expert = _NeverHolds()
    result = run_episode(env, expert, seed=1)
    assert not result.success
    assert result.failure == "expert_grasp_missed"
    assert expert.attempts == 2  # exactly one retry
    assert result.steps < env.max_steps
