"""One policy episode: fixed seeds, result fields, invalid actions, keypoint projection and videos."""

import numpy as np
import pytest

from keygen.errors import InvalidParameterError
from keygen.evaluation.rollout import (
    EnvSpec,
    draw_keypoints,
    episode_seed,
    make_env,
    project_keypoints,
    run_policy_episode,
)
from keygen.geometry.cameras import look_at

SPEC = EnvSpec("stack", "test", "hard", 1.0, image_size=32, num_points=256, max_steps=3)


class HoldPolicy:
    """Holds the current pose; reports the first cloud points as its 'keypoints'."""

    def __init__(self, nan_after: int | None = None):
        self.nan_after, self.calls, self.resets, self.first_obs = nan_after, 0, 0, None
        self.last_keypoints = None

    def reset(self):
        self.resets += 1
        self.calls = 0

    def act(self, obs):
        if self.calls == 0:
            self.first_obs = {k: v.copy() for k, v in obs.items()}
        self.calls += 1
        self.last_keypoints = obs["object_cloud"][:3]
        if self.nan_after is not None and self.calls > self.nan_after:
            return np.full(10, np.nan)
        return obs["proprio"]


def test_episode_seed_is_fixed_and_distinct():
    assert episode_seed(0, 3, 1) == episode_seed(0, 3, 1)
    seeds = {episode_seed(s, o, k) for s in range(2) for o in range(4) for k in range(5)}
    assert len(seeds) == 40
    with pytest.raises(InvalidParameterError):
        episode_seed(0, -1, 0)


def test_env_spec_validates():
    with pytest.raises(InvalidParameterError, match="task"):
        EnvSpec("fly", "test", "hard")
    with pytest.raises(InvalidParameterError, match="setting"):
        EnvSpec("stack", "test", "medium")
    with pytest.raises(InvalidParameterError, match="max_steps"):
        EnvSpec("stack", "test", "hard", max_steps=0)


def test_projection_of_a_point_on_the_optical_axis_hits_the_principal_point():
    K = np.array([[50.0, 0, 16], [0, 50.0, 12], [0, 0, 1]])
    T = look_at(np.array([1.0, 0.0, 0.5]), np.array([0.0, 0.0, 0.5]))  # camera-to-world, OpenCV
    pts = np.array([[0.0, 0.0, 0.5], [2.0, 0.0, 0.5]])  # in front of, and behind, the camera
    pixels, visible = project_keypoints(pts, K[None], T[None])
    assert pixels.shape == (1, 2, 2) and visible.tolist() == [[True, False]]
    np.testing.assert_allclose(pixels[0, 0], [16.0, 12.0], atol=1e-9)


def test_draw_keypoints_marks_pixels_and_copies():
    K = np.array([[50.0, 0, 16], [0, 50.0, 16], [0, 0, 1]])
    T = look_at(np.array([1.0, 0.0, 0.5]), np.array([0.0, 0.0, 0.5]))
    obs = {"intrinsics": K[None].astype(np.float32), "extrinsics": T[None].astype(np.float32)}
    rgb = np.zeros((1, 32, 32, 3), np.uint8)
    out = draw_keypoints(rgb, np.array([[0.0, 0.0, 0.5]]), obs)
    assert rgb.max() == 0  # the input is untouched
    assert out[0, 16, 16].tolist() == [255, 64, 64] and out[0, 0, 0].tolist() == [0, 0, 0]
    assert np.array_equal(draw_keypoints(rgb, None, obs), rgb)


def test_episode_result_fields_and_fixed_layout():
    env = make_env(SPEC, object_id=1)
    assert env.max_steps == 3
    a, b = HoldPolicy(), HoldPolicy()
    seed = episode_seed(0, 1, 0)
    result, frames = run_policy_episode(env, a, seed, policy_name="hold", episode=0)
    assert frames is None and a.resets == 1
    assert {"task", "policy", "split", "setting", "scale", "object_id", "episode", "seed", "success"} <= set(
        result
    )
    assert result["task"] == "stack" and result["object_id"] == 1 and result["seed"] == seed
    assert result["steps"] == 3 and result["success"] is False and result["failure"] == "timeout"
    run_policy_episode(env, b, seed)
    np.testing.assert_array_equal(a.first_obs["object_cloud"], b.first_obs["object_cloud"])


def test_invalid_action_ends_the_episode_as_a_failure_and_video_frames():
    env = make_env(SPEC, object_id=0, include_rgb=True)
    result, frames = run_policy_episode(env, HoldPolicy(nan_after=1), 5, record_video=True)
    assert result["failure"] == "invalid_action" and result["steps"] == 1 and not result["success"]
    assert len(frames) == 2 and frames[0].shape == (64, 64, 3) and frames[0].dtype == np.uint8
    with pytest.raises(InvalidParameterError, match="include_rgb"):
        run_policy_episode(make_env(SPEC, 0), HoldPolicy(), 5, record_video=True)
