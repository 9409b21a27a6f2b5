import gymnasium as gym
import numpy as np
import pytest

import keygen  # noqa: F401
from keygen.sim.tasks.stack import SETTLE_STEPS


def make(**kwargs):
    return gym.make(
        "keygen/StackBowl-v0", image_size=48, num_points=128, include_rgb=False, **kwargs
    ).unwrapped


def run_still(env, steps):
    obs = env._observe()
    info = None
    for _ in range(steps):
        obs, _, terminated, _, info = env.step(obs["proprio"])
        if terminated:
            break
    return info


@pytest.mark.parametrize("object_id", [0, 3])
def test_bowl_dropped_into_base_bowl_succeeds_after_settling(object_id):
    env = make(object_id=object_id, setting="hard")
    env.reset(seed=object_id)
    env.task.place_nested(env.model, env.data)
    info = run_still(env, SETTLE_STEPS + 15)
    assert info["success"], info["metrics"]
    assert info["metrics"]["still_seconds"] >= 1.0


def test_bowl_beside_base_bowl_is_a_near_miss():
    env = make(object_id=2)
    env.reset(seed=1)
    env.task.place_beside(env.model, env.data)
    info = run_still(env, SETTLE_STEPS + 5)
    assert not info["success"]
    assert info["metrics"]["nested"] == 0.0


def test_success_needs_a_full_second_of_rest():
    env = make(object_id=1)
    env.reset(seed=2)
    env.task.place_nested(env.model, env.data)
    info = run_still(env, 3)
    assert not info["success"]


def test_base_bowl_leaves_room_for_a_finger():
    env = make(object_id=4, setting="hard")
    _, info = env.reset(seed=4)
    a = info["anchors"]
    wall = env.task.base_asset.params.get("wall_thickness", 0.006) * env.task.base_asset.scale
    inner_b = a["base_rim_radius"][0] - wall
    assert inner_b - a["rim_radius"][0] >= 0.02
    # the bowls start apart
    assert (
        np.linalg.norm((a["bottom_center"] - a["base_bottom_center"])[:2])
        > a["rim_radius"][0] + a["base_rim_radius"][0]
    )
