"""Registry-wide checks of the three environments (smoke, check_env, determinism, robustness)."""

import os

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import keygen
from keygen.errors import InvalidParameterError
from keygen.objects.splits import SPLITS
from keygen.sim.tasks.base import SETTINGS

IDS = sorted(keygen.ENV_IDS.values())
FAST = dict(image_size=48, num_points=128, include_rgb=False)


def make(env_id, **kwargs):
    return gym.make(env_id, **{**FAST, **kwargs}).unwrapped


def test_import_registers_ids_and_egl():
    assert os.environ["MUJOCO_GL"] == "egl"
    for env_id in ("keygen/Pour-v0", "keygen/CollectKnife-v0", "keygen/StackBowl-v0"):
        assert env_id in gym.registry


@pytest.mark.parametrize("env_id", IDS)
def test_check_env(env_id):
    env = make(env_id, include_rgb=True)
    check_env(env, skip_render_check=True)
    env.close()


@pytest.mark.parametrize("env_id", IDS)
@pytest.mark.parametrize("setting", SETTINGS)
@pytest.mark.parametrize("split", SPLITS)
def test_smoke_every_task_setting_split(env_id, setting, split):
    env = make(env_id, object_split=split, object_id=1, setting=setting)
    obs, info = env.reset(seed=3)
    assert env.observation_space.contains(obs)
    hold = obs["proprio"].copy()
    for _ in range(20):
        obs, reward, terminated, truncated, info = env.step(hold)
        for key, value in obs.items():
            assert value.shape == env.observation_space[key].shape, key
            assert np.all(np.isfinite(value)), key
        assert info["failure"] != "physics_unstable"
        if terminated or truncated:
            break
    assert set(info) >= {"success", "failure", "metrics", "anchors", "objects"}
    assert np.any(obs["object_cloud_ids"] == 1), "the manipulated object is in the object cloud"
    env.close()


@pytest.mark.parametrize("env_id", IDS)
def test_reset_is_deterministic(env_id):
    env_a, env_b = make(env_id, setting="hard"), make(env_id, setting="hard")
    obs_a, info_a = env_a.reset(seed=11)
    obs_b, info_b = env_b.reset(seed=11)
    for key in obs_a:
        np.testing.assert_array_equal(obs_a[key], obs_b[key], err_msg=key)
    for name in info_a["anchors"]:
        np.testing.assert_array_equal(info_a["anchors"][name], info_b["anchors"][name])
    obs_c, _ = env_a.reset(seed=12)
    assert not np.array_equal(obs_a["object_cloud"], obs_c["object_cloud"])


def test_physics_instability_ends_episode_without_exception():
    env = make("keygen/StackBowl-v0")
    obs, _ = env.reset(seed=0)
    env.data.qvel[:] = 1e6  # blow the simulation up
    obs, reward, terminated, truncated, info = env.step(obs["proprio"])
    assert terminated and not info["success"]
    assert info["failure"] == "physics_unstable"
    assert all(np.all(np.isfinite(v)) for v in obs.values())


def test_bad_arguments_and_actions():
    with pytest.raises(InvalidParameterError):
        make("keygen/StackBowl-v0", setting="medium")
    with pytest.raises(InvalidParameterError):
        make("keygen/StackBowl-v0", object_split="val")
    with pytest.raises(InvalidParameterError):
        make("keygen/StackBowl-v0", scale=-1.0)
    env = make("keygen/StackBowl-v0")
    with pytest.raises(InvalidParameterError):
        env.step(np.zeros(10))  # before reset
    obs, _ = env.reset(seed=0)
    with pytest.raises(InvalidParameterError):
        env.step(np.zeros(7))
    bad = obs["proprio"].copy()
    bad[0] = np.nan
    with pytest.raises(InvalidParameterError):
        env.step(bad)


def test_randomisation_changes_appearance_but_not_with_same_seed():
    env = make("keygen/StackBowl-v0", randomize=True, include_rgb=True)
    plain = make("keygen/StackBowl-v0", randomize=False, include_rgb=True)
    a, _ = env.reset(seed=5)
    b, _ = env.reset(seed=5)
    c, _ = plain.reset(seed=5)
    np.testing.assert_array_equal(a["rgb"], b["rgb"])
    assert not np.array_equal(a["rgb"], c["rgb"])
    assert not np.allclose(a["extrinsics"], c["extrinsics"])  # camera jitter


def test_scale_multiplies_the_object():
    small = make("keygen/StackBowl-v0", scale=0.7)
    big = make("keygen/StackBowl-v0", scale=1.2)
    _, info_s = small.reset(seed=0)
    _, info_b = big.reset(seed=0)
    r_s, r_b = info_s["anchors"]["rim_radius"][0], info_b["anchors"]["rim_radius"][0]
    assert r_b / r_s == pytest.approx(1.2 / 0.7, rel=1e-6)


def test_wrist_camera_moves_with_the_hand():
    env = make("keygen/StackBowl-v0", wrist_camera=True, include_rgb=True)
    obs, _ = env.reset(seed=0)
    assert obs["rgb"].shape[0] == 5 and obs["depth"].shape[0] == 5
    before = obs["extrinsics"][4].copy()
    start = obs["proprio"][:3].copy()
    fixed = obs["extrinsics"][:4].copy()
    target = obs["proprio"].copy()
    target[:3] += np.array([0.05, 0.05, -0.05])
    for _ in range(5):
        obs, *_ = env.step(target)
    moved = obs["extrinsics"][4][:3, 3] - before[:3, 3]
    np.testing.assert_allclose(moved, obs["proprio"][:3] - start, atol=0.01)
    np.testing.assert_allclose(obs["extrinsics"][:4], fixed, atol=1e-6)
    # the wrist view looks past the fingers at the table: most pixels see something close
    assert np.mean(obs["depth"][4] > 0) > 0.5 and np.median(obs["depth"][4][obs["depth"][4] > 0]) < 0.6


def test_tile_views_grid():
    from keygen.sim.cameras import tile_views

    views = np.stack([np.full((4, 6, 3), i, np.uint8) for i in range(1, 6)])  # five 4x6 views
    grid = tile_views(views)
    assert grid.shape == (8, 18, 3)  # 3 wide, 2 high
    assert grid[0, 0, 0] == 1 and grid[0, 6, 0] == 2 and grid[4, 0, 0] == 4 and grid[4, 12, 0] == 0
