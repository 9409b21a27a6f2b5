"""The target yaw frame: the knife block's slot axis and centre measured from its points, the frame's
half-turn invariance, clear errors, training arrays in each episode's frame, and a runner whose plan
turns with the scene."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from _policy_runs import tiny_train_config
from keygen.data.store import ACTION_KEY, EpisodeStore
from keygen.errors import InvalidParameterError
from keygen.geometry.rotations import yaw_matrix
from keygen.policies import TrainConfig, load_runner, train_policy
from keygen.policies.config import make_policy_config
from keygen.policies.data import to_target_frames
from keygen.policies.runtime import PolicyRunner
from keygen.policies.target_frame import TARGET_LABEL, measure_target_frame, target_points
from keygen.policies.yaw_frame import YAW_REFERENCE_FILE

SIZE = (0.17, 0.09, 0.11)  # block length (along the slot), width, height
SLOT = (0.10, 0.012)  # slot length and width


def _block(centre_xy, yaw: float, n: int = 600, seed: int = 0, size=SIZE, slot=SLOT) -> np.ndarray:
    """``n`` points of a knife block, turned by ``yaw`` (slot along the block's x axis), its bottom
    centre at ``centre_xy``: three quarters on its top face (a jittered grid with the slot left
    open: fused clouds are farthest-point resampled, so evenly spread) and the rest on two sides."""
    rng = np.random.default_rng(seed)
    lx, ly, h = size
    n_top = (3 * n) // 4
    cols = int(np.ceil(np.sqrt(1.3 * n_top * lx / ly)))
    rows = int(np.ceil(1.3 * n_top / cols))
    gx, gy = np.meshgrid((np.arange(cols) + 0.5) / cols - 0.5, (np.arange(rows) + 0.5) / rows - 0.5)
    top = np.column_stack([gx.ravel() * lx, gy.ravel() * ly])
    top = top + rng.uniform(-0.2, 0.2, top.shape) * [lx / cols, ly / rows]
    top = top[~((np.abs(top[:, 0]) < slot[0] / 2) & (np.abs(top[:, 1]) < slot[1] / 2))]
    top = top[np.linspace(0, len(top) - 1, n_top).astype(int)]
    top = np.column_stack([top, np.full(len(top), h)])
    k = (n - n_top) // 2
    side_x = np.column_stack([rng.uniform(-lx / 2, lx / 2, k), np.full(k, -ly / 2), rng.uniform(0, h, k)])
    side_y = np.column_stack(
        [
            np.full(n - n_top - k, lx / 2),
            rng.uniform(-ly / 2, ly / 2, n - n_top - k),
            rng.uniform(0, h, n - n_top - k),
        ]
    )
    local = np.concatenate([top, side_x, side_y])
    return local @ yaw_matrix(yaw).T + [centre_xy[0], centre_xy[1], 0.0]


def _half_turn_diff(a: float, b: float) -> float:
    """|a - b| modulo pi, in [0, pi/2]."""
    d = (a - b) % np.pi
    return min(d, np.pi - d)


@pytest.mark.parametrize("yaw", [0.0, 0.4, 1.5, -2.0, 3.0])
def test_the_frame_finds_the_slot_axis_and_the_block_centre(yaw) -> None:
    centre = np.array([0.5, -0.18])
    frame = measure_target_frame(_block(centre, yaw, seed=1))
    assert _half_turn_diff(frame.yaw, yaw) < np.radians(1.0)
    np.testing.assert_allclose(frame.origin, [*centre, 0.0], atol=3e-3)
    # The slot runs along the frame's x axis, which points away from the robot base (the origin).
    u = np.array([np.cos(frame.yaw), np.sin(frame.yaw)])
    assert u @ frame.origin[:2] > 0
    slot_end = np.array([*centre, SIZE[2]]) + yaw_matrix(yaw) @ [SLOT[0] / 2, 0.0, 0.0]
    local = frame.points(slot_end)
    assert abs(local[1]) < 2e-3 and abs(abs(local[0]) - SLOT[0] / 2) < 3e-3


@pytest.mark.parametrize("size", [(0.10, 0.10, 0.1), (0.08, 0.10, 0.1)])
def test_the_slot_opening_decides_on_square_and_cross_long_blocks(size) -> None:
    # A block for a narrow blade can be square, or longer across its slot than along it: the
    # bounding box alone would then pick the wrong axis.
    yaw = 0.6
    narrow_slot = (0.032, 0.011)  # the shortest opening the task makes: a 1.4 cm blade + 1.8 cm
    frame = measure_target_frame(_block((0.5, -0.18), yaw, n=300, seed=3, size=size, slot=narrow_slot))
    assert _half_turn_diff(frame.yaw, yaw) < np.radians(1.0)


def test_a_half_turned_block_gives_the_same_frame() -> None:
    centre = (0.45, -0.2)
    a = measure_target_frame(_block(centre, 0.7, seed=2))
    b = measure_target_frame(_block(centre, 0.7 + np.pi, seed=2))
    assert abs(np.angle(np.exp(1j * (a.yaw - b.yaw)))) < np.radians(1.0)
    np.testing.assert_allclose(a.origin, b.origin, atol=3e-3)


def test_clear_errors_on_bad_target_points() -> None:
    with pytest.raises(InvalidParameterError, match="fewer than"):
        measure_target_frame(_block((0.5, -0.2), 0.3)[-5:])
    with pytest.raises(InvalidParameterError, match="finite"):
        measure_target_frame(np.full((20, 3), np.nan))
    with pytest.raises(InvalidParameterError, match="finite"):
        measure_target_frame(np.zeros((20, 2)))
    flat = np.column_stack([np.linspace(0.4, 0.6, 30), np.full(30, -0.2), np.full(30, 0.1)])
    with pytest.raises(InvalidParameterError, match="no area"):
        measure_target_frame(flat)
    with pytest.raises(InvalidParameterError, match="differ in length"):
        target_points(np.zeros((5, 3)), np.zeros(4))


def test_the_config_ties_the_target_source_to_a_yaw_frame() -> None:
    cfg = make_policy_config("keygen", yaw_frame=True, yaw_source="target")
    assert cfg.yaw_source == "target"
    # Measured on points, not keypoints: a policy without keypoints may use it.
    assert make_policy_config("keygen_no_kp", yaw_frame=True, yaw_source="target").yaw_frame
    with pytest.raises(InvalidParameterError, match="needs yaw_frame"):
        make_policy_config("keygen", yaw_source="target")
    with pytest.raises(InvalidParameterError, match="does not apply"):
        make_policy_config("keygen", yaw_frame=True, yaw_source="target", yaw_origin="grasp")
    with pytest.raises(InvalidParameterError, match="yaw_source must be one of"):
        make_policy_config("keygen", yaw_frame=True, yaw_source="block")
    # Configurations saved before the field existed read back with the keypoint source.
    data = make_policy_config("keygen_yaw").to_dict()
    data.pop("yaw_source")
    assert make_policy_config("keygen_yaw").from_dict(data).yaw_source == "keypoints"


def _knife_episode(kit, seed: int, yaw: float, centre=(0.5, -0.18)) -> dict[str, np.ndarray]:
    """A synthetic episode whose target (label 2) is a knife block turned by ``yaw``."""
    ep = kit.synthetic_episode(seed)
    ids = ep["object_cloud_ids"]
    n_block = int((ids[0] == TARGET_LABEL).sum())
    cloud = ep["object_cloud"].copy()
    cloud[:, ids[0] == TARGET_LABEL] = _block(centre, yaw, n=n_block, seed=seed).astype(np.float32)
    ep["object_cloud"] = cloud
    return ep


def _knife_store(kit, path: Path, yaws) -> Path:
    store = EpisodeStore(path, mode="w")
    for e, yaw in enumerate(yaws):
        store.append_episode(_knife_episode(kit, e, yaw), {"task": "knife", "seed": e, "success": True})
    return path


def test_training_arrays_go_to_each_episodes_target_frame(tmp_path: Path, kit) -> None:
    yaws = [0.3, 2.0, -1.2]
    store = EpisodeStore(_knife_store(kit, tmp_path / "knife.zarr", yaws), "r")
    s = store.num_steps
    raw = [np.asarray(store.read(k, 0, s)) for k in ("object_cloud", "proprio", ACTION_KEY)]
    keypoints = raw[0][:, :4].copy()
    clouds, proprio, actions, kp = to_target_frames(store, raw[0], raw[1], raw[2], keypoints)
    ids = np.asarray(store.read("object_cloud_ids", 0, s))
    starts = np.concatenate([[0], store.episode_ends[:-1]])
    for e, (a, b) in enumerate(zip(starts, store.episode_ends, strict=True)):
        frame = measure_target_frame(target_points(raw[0][a], ids[a]))
        # In its frame every episode's block lies at the origin with the slot along x.
        block = clouds[a][ids[a] == TARGET_LABEL]
        top = block[block[:, 2] > block[:, 2].max() - 0.01]
        assert np.abs(top[:, :2].max(0) + top[:, :2].min(0)).max() / 2 < 5e-3
        assert np.ptp(top[:, 0]) > 1.5 * np.ptp(top[:, 1])
        np.testing.assert_allclose(proprio[a:b], frame.poses(raw[1][a:b]), atol=1e-5)
        np.testing.assert_allclose(actions[a:b], frame.poses(raw[2][a:b]), atol=1e-5)
        np.testing.assert_allclose(kp[a:b], frame.points(keypoints[a:b]), atol=1e-5)
        assert _half_turn_diff(frame.yaw, yaws[e]) < np.radians(4.0)  # 36 top points
    # The input arrays are left as they were.
    np.testing.assert_array_equal(raw[0], np.asarray(store.read("object_cloud", 0, s)))
    # No keypoints: the rest still turns.
    assert to_target_frames(store, raw[0], raw[1], raw[2], None)[3] is None


def test_a_target_frame_policy_plans_turn_with_the_block(tmp_path: Path, kit, fake_keypoints) -> None:
    store = _knife_store(kit, tmp_path / "knife.zarr", [0.3, 2.0])
    cfg = tiny_train_config(
        "keygen",
        store,
        tmp_path / "run",
        fake_keypoints,
        steps=3,
        model={"yaw_frame": True, "yaw_source": "target"},
    )
    run = train_policy(cfg, progress=False)
    assert json.loads((run / "config.json").read_text())["policy"]["yaw_source"] == "target"
    assert not (run / YAW_REFERENCE_FILE).exists()  # a geometric frame needs no fitted reference
    ep = _knife_episode(kit, 7, 0.9)
    obs = [kit.observation(ep, t) for t in range(3)]
    runner = load_runner(run)
    first = np.array([runner.act(o) for o in obs])
    assert _half_turn_diff(runner.yaw_frame.yaw, 0.9) < np.radians(4.0)
    # The whole scene turned about the block's centre: the frame turns with it, so does the plan.
    centre, theta = np.array([0.5, -0.18, 0.0]), -0.5
    other = load_runner(run)
    second = np.array([other.act(kit.turned_scene(o, theta, centre)) for o in obs])
    assert abs(np.angle(np.exp(1j * (other.yaw_frame.yaw - runner.yaw_frame.yaw - theta)))) < 1e-4
    R = yaw_matrix(theta)
    np.testing.assert_allclose(second[:, :3], (first[:, :3] - centre) @ R.T + centre, atol=5e-4)
    np.testing.assert_allclose(second[:, 3:6], first[:, 3:6] @ R.T, atol=5e-4)
    np.testing.assert_allclose(second[:, 9], first[:, 9], atol=5e-4)
    runner.reset()
    assert runner.yaw_frame is None
    # A target-frame policy takes no keypoint yaw reference.
    with pytest.raises(InvalidParameterError, match="yaw reference"):
        PolicyRunner(runner.model, "knife", runner.keypoints, yaw_reference=np.eye(4)[:, :2])


def test_training_refuses_the_target_frame_where_the_target_has_no_axis(tmp_path: Path, kit) -> None:
    store = kit.make_store(tmp_path / "pour.zarr", task="pour")
    cfg = TrainConfig.from_preset(
        "quick", policy="keygen_no_kp", dataset=store, out=tmp_path / "run", steps=2,
        policy_overrides={"yaw_frame": True, "yaw_source": "target"},
    )  # fmt: skip
    with pytest.raises(InvalidParameterError, match="'pour' task's target has none"):
        train_policy(cfg, progress=False)
