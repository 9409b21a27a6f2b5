"""The knife task's scripted expert: seeded successes, the grasp guard's single retry, determinism,
and the anchor geometry it is built on."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest

import keygen  # noqa: F401  (registers the environments)
from keygen.expert.knife import KnifeExpert, grasp_rotation, insert_pose
from keygen.expert.runner import make_expert, run_episode

ENV_ID = "keygen/CollectKnife-v0"
FAST = {"include_rgb": False, "image_size": 64, "num_points": 256}
Z = np.array([0.0, 0.0, 1.0])


def make_env(split: str, index: int, setting: str):
    return gymnasium.make(ENV_ID, object_split=split, object_id=index, setting=setting, **FAST).unwrapped


class BlindExpert(KnifeExpert):
    """Never feels the knife between its fingers: every grasp counts as a miss."""

    def grip_detected(self, obs, info) -> bool:
        return False


def test_make_expert_loads_the_knife_expert():
    expert = make_expert("knife")
    assert isinstance(expert, KnifeExpert) and expert.task == "knife"


def test_grasp_rotation_points_down_and_closes_across_the_handle():
    rng = np.random.default_rng(0)
    for _ in range(20):
        yaw = rng.uniform(-np.pi, np.pi)
        axis = np.array([np.cos(yaw), np.sin(yaw), rng.uniform(-0.1, 0.1)])
        anchors = {"handle_axis": axis, "handle_grasp": np.array([0.5, rng.uniform(0.05, 0.2), 0.01])}
        R = grasp_rotation(anchors)
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(R[:, 2], -Z, atol=1e-12)
        assert abs(R[:, 1] @ axis) < 1e-9  # closing axis across the handle
        assert R[:, 0] @ np.array([0.5, anchors["handle_grasp"][1], 0.0]) > 0  # x away from the base


def test_insert_pose_puts_the_blade_down_along_the_slot():
    rng = np.random.default_rng(1)
    tcp_pos = np.array([0.5, 0.0, 0.3])
    tcp_rot = np.diag([1.0, -1.0, -1.0])
    for _ in range(10):
        yaw = rng.uniform(-np.pi, np.pi)
        slot_axis = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        axis, edge = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])  # knife lying along x, face up
        anchors = {
            "blade_axis": axis,
            "edge_direction": edge,
            "blade_tip": tcp_pos + 0.2 * axis,
            "slot_axis": slot_axis,
            "slot_center_top": np.array([0.5, -0.15, 0.12]),
        }
        approach = np.cross(Z, slot_axis)
        pos, rot = insert_pose(tcp_pos, tcp_rot, anchors, approach, 0.05, 0.0)
        knife_rot = rot @ tcp_rot.T  # how the knife turns with the hand
        np.testing.assert_allclose(knife_rot @ axis, -Z, atol=1e-9)  # blade straight down
        assert abs(abs(knife_rot @ edge @ slot_axis) - 1.0) < 1e-9  # blade plane along the slot
        assert rot[:, 2] @ approach == pytest.approx(1.0)
        tip = pos + rot @ (tcp_rot.T @ (anchors["blade_tip"] - tcp_pos))
        np.testing.assert_allclose(tip, anchors["slot_center_top"] - 0.05 * Z, atol=1e-9)


@pytest.mark.parametrize(
    ("split", "index", "setting", "seed"),
    [("test", 4, "hard", 0), ("policy", 0, "easy", 0)],
)
def test_expert_inserts_the_knife(split, index, setting, seed):
    env = make_env(split, index, setting)
    expert = KnifeExpert()
    result = run_episode(env, expert, seed)
    env.close()
    assert result.success, result
    assert result.failure is None and expert.failure is None
    assert expert.grasp_attempts == 1
    assert result.metrics["inserted_fraction"] >= 0.5 and result.steps <= env.max_steps


def test_a_missed_grasp_retries_once_then_gives_up():
    env = make_env("test", 1, "easy")
    phases: list[str] = []
    expert = BlindExpert()
    result = run_episode(env, expert, 0, on_step=lambda obs, action, info: phases.append(expert.phase))
    env.close()
    assert not result.success and result.failure == "expert_grasp_missed"
    assert expert.grasp_attempts == 2
    # Exactly one return to the pre-grasp: pre_grasp, ..., reopen, pre_grasp, ... close (then stop).
    starts = [
        i for i, p in enumerate(phases) if p == "pre_grasp" and (i == 0 or phases[i - 1] != "pre_grasp")
    ]
    assert len(starts) == 2 and "reopen" in phases[starts[0] : starts[1]]
    assert phases[-1] == "close"


def test_episodes_are_deterministic_for_a_seed():
    env = make_env("test", 1, "easy")
    runs = []
    for _ in range(2):
        actions: list[np.ndarray] = []
        result = run_episode(
            env, BlindExpert(), 5, on_step=lambda obs, action, info, log=actions: log.append(action)
        )
        runs.append((np.array(actions), result.failure, result.steps))
    env.close()
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    assert runs[0][1:] == runs[1][1:]
