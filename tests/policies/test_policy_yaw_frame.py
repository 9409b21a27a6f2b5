"""The keypoint yaw frame: the fitted yaw, the reference, round trips, and a runner whose plan turns
with the scene."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from _policy_runs import tiny_train_config
from keygen.errors import InvalidParameterError
from keygen.geometry.rotations import matrix_to_rot6d, random_rotation, rot6d_to_matrix, yaw_matrix
from keygen.policies import TrainConfig, features, load_runner, train_policy
from keygen.policies.config import make_policy_config
from keygen.policies.data import to_yaw_frames
from keygen.policies.runtime import PolicyRunner
from keygen.policies.yaw_frame import (
    YAW_REFERENCE_FILE,
    YawFrame,
    estimate_yaw,
    fit_reference,
    grasp_positions,
    nearest_keypoint,
    read_origin_keypoint,
    read_reference,
    write_reference,
)


def _shape(seed: int = 0, k: int = 8) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform([-0.05, -0.04, 0.0], [0.06, 0.04, 0.1], (k, 3))


def _turn(points: np.ndarray, theta: float, shift=(0.0, 0.0, 0.0)) -> np.ndarray:
    return points @ yaw_matrix(theta).T + np.asarray(shift)


def _wrap(a: float) -> float:
    return float((a + np.pi) % (2 * np.pi) - np.pi)


@pytest.mark.parametrize("theta", [0.0, 0.7, -2.5, 3.1])
def test_estimate_yaw_recovers_a_known_turn(theta) -> None:
    shape = _shape()
    seen = _turn(shape, theta, (0.4, -0.2, 0.0))
    assert _wrap(estimate_yaw(seen, shape) - theta) == pytest.approx(0.0, abs=1e-9)
    # z plays no part, and a reference given as (K, 2) is the same reference.
    assert estimate_yaw(seen + [0, 0, 0.3], shape[:, :2]) == pytest.approx(estimate_yaw(seen, shape))


def test_fit_reference_keeps_the_first_orientation_and_averages_noise() -> None:
    rng = np.random.default_rng(1)
    shape = _shape(2)
    angles = np.concatenate([[0.0], rng.uniform(-np.pi, np.pi, 29)])
    sets = np.stack(
        [_turn(shape + rng.normal(0, 0.002, shape.shape), a, (*rng.uniform(-1, 1, 2), 0)) for a in angles]
    )
    ref = fit_reference(sets)
    centred = shape[:, :2] - shape[:, :2].mean(0)
    assert ref.shape == (8, 2)
    np.testing.assert_allclose(ref.mean(0), 0.0, atol=1e-12)
    # Within the noise of one set (2 mm), averaged over 30: well under 2 mm, same orientation.
    assert np.abs(ref - centred).max() < 2e-3
    yaws = [estimate_yaw(s, ref) for s in sets]
    # Each set's yaw carries ~0.02 rad of its own noise (2 mm on a ~5 cm shape), hence 0.1 rad.
    assert max(abs(_wrap(y - a)) for y, a in zip(yaws, angles, strict=True)) < 0.1
    np.testing.assert_array_equal(fit_reference(sets), ref)  # deterministic


def test_frame_round_trips_and_keeps_rotations_proper() -> None:
    rng = np.random.default_rng(3)
    frame = YawFrame.measure(_turn(_shape(), 1.2, (0.5, 0.1, 0.0)), _shape())
    assert frame.origin[2] == 0.0 and _wrap(frame.yaw - 1.2) == pytest.approx(0, abs=1e-9)
    pts = rng.normal(size=(5, 7, 3))
    np.testing.assert_allclose(frame.points(frame.points(pts), inverse=True), pts, atol=1e-12)
    poses = np.concatenate(
        [rng.normal(size=(6, 3)), matrix_to_rot6d(random_rotation(rng, 6)), rng.uniform(0, 1, (6, 1))], axis=1
    )
    turned = frame.poses(poses)
    np.testing.assert_allclose(frame.poses(turned, inverse=True), poses, atol=1e-12)
    np.testing.assert_array_equal(turned[:, 9], poses[:, 9])  # the gripper is not a position
    R = rot6d_to_matrix(turned[:, 3:9])
    np.testing.assert_allclose(R, yaw_matrix(-frame.yaw) @ rot6d_to_matrix(poses[:, 3:9]), atol=1e-12)
    # The object's own keypoints land on the reference: centred at the origin, turned back.
    local = frame.points(_turn(_shape(), 1.2, (0.5, 0.1, 0.0)))
    np.testing.assert_allclose(local[:, :2], _shape()[:, :2] - _shape()[:, :2].mean(0), atol=1e-12)


def test_clear_errors_on_bad_input(tmp_path: Path) -> None:
    line = np.zeros((6, 3))
    line[:, 2] = np.linspace(0, 0.1, 6)  # keypoints on a vertical line: no yaw
    with pytest.raises(InvalidParameterError, match="planar spread"):
        estimate_yaw(line, line)
    with pytest.raises(InvalidParameterError, match="differ in K"):
        estimate_yaw(_shape(k=6), _shape(k=8))
    with pytest.raises(InvalidParameterError, match="finite"):
        YawFrame.measure(np.full((6, 3), np.nan), _shape(k=6))
    with pytest.raises(InvalidParameterError, match=r"\(E >= 1"):
        fit_reference(np.zeros((0, 6, 3)))
    with pytest.raises(InvalidParameterError, match=r"\(\.\.\., 10\)"):
        YawFrame(np.zeros(3), 0.0).poses(np.zeros((2, 9)))
    with pytest.raises(InvalidParameterError, match="missing"):
        read_reference(tmp_path)
    write_reference(tmp_path, _shape())
    np.testing.assert_allclose(read_reference(tmp_path), _shape()[:, :2])
    assert json.loads((tmp_path / YAW_REFERENCE_FILE).read_text())["reference_xy"]
    with pytest.raises(InvalidParameterError, match="use_keypoints"):
        make_policy_config("keygen_no_kp", yaw_frame=True)


def test_training_arrays_go_to_each_episodes_own_frame(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    shape, ends = _shape(k=4), np.array([3, 7])
    angles, shifts = [0.3, -1.9], [(0.5, 0.1, 0.0), (0.4, -0.2, 0.0)]
    kp = np.concatenate(
        [np.repeat(_turn(shape, a, s)[None], n, 0) for a, s, n in zip(angles, shifts, (3, 4), strict=True)]
    )
    kp = np.concatenate([kp, kp + [0, 0, 0.5]], axis=1)  # a second keypointed object rides along
    clouds = rng.normal(size=(7, 5, 3)).astype(np.float32)
    poses = np.concatenate(
        [rng.normal(size=(7, 3)), np.tile([1, 0, 0, 0, 1, 0], (7, 1)), np.ones((7, 1))], axis=1
    )
    c, p, a, k = to_yaw_frames(tmp_path, ends, 4, clouds, poses, poses + 0.01, kp)
    ref = read_reference(tmp_path)
    frames = [YawFrame.measure(kp[0, :4], ref), YawFrame.measure(kp[3, :4], ref)]
    assert _wrap(frames[1].yaw - frames[0].yaw) == pytest.approx(_wrap(angles[1] - angles[0]), abs=1e-9)
    for f, lo, hi in ((frames[0], 0, 3), (frames[1], 3, 7)):
        np.testing.assert_allclose(c[lo:hi], f.points(clouds[lo:hi]), atol=1e-6)
        np.testing.assert_allclose(p[lo:hi], f.poses(poses[lo:hi]), atol=1e-6)
        np.testing.assert_allclose(k[lo:hi], f.points(kp[lo:hi]), atol=1e-6)
    # Both episodes' objects now sit on the same reference, whatever their world pose.
    np.testing.assert_allclose(k[0, :4], k[3, :4], atol=1e-9)
    assert c.dtype == np.float32 and a.shape == (7, 10)


def _grasp_actions(lengths, grasps, close_at) -> np.ndarray:
    """Actions whose gripper opens to 0.25, then closes (to 0) at step ``close_at[e]`` at ``grasps[e]``."""
    out = []
    for n, g, c in zip(lengths, grasps, close_at, strict=True):
        a = np.zeros((n, 10))
        a[:, :3] = np.linspace([0.3, 0.0, 0.3], [0.5, 0.2, 0.2], n)
        a[:, 9] = 1.0
        a[1:c, 9] = 0.25  # a pre-grasp width above the closed command
        a[c:, 9] = 0.0
        a[c, :3] = g
        out.append(a)
    return np.concatenate(out)


def test_grasp_anchor_is_the_keypoint_nearest_the_first_full_close() -> None:
    rng = np.random.default_rng(5)
    shape = _shape(k=5)
    angles, shifts = [0.2, 1.9, -2.4], [(0.5, 0.1, 0.0), (0.4, -0.2, 0.0), (0.45, 0.0, 0.0)]
    first = np.stack([_turn(shape, a, s) for a, s in zip(angles, shifts, strict=True)])
    grasps = first[:, 3] + rng.normal(0, 0.003, (3, 3))  # each demo grasps near keypoint 3
    actions = _grasp_actions([6, 8, 7], grasps, [3, 5, 2])
    found = grasp_positions(actions, np.array([6, 14, 21]))
    np.testing.assert_allclose(found, grasps)  # the first step at the minimum, not the 0.25 width
    assert nearest_keypoint(first, found) == 3
    # The frame centred on keypoint 3: that keypoint sits at the origin (x, y) of every episode.
    ref = fit_reference(first)
    for kp in first:
        frame = YawFrame.measure(kp, ref, origin_keypoint=3)
        np.testing.assert_allclose(frame.points(kp)[3, :2], 0.0, atol=1e-12)
        np.testing.assert_allclose(frame.origin[:2], kp[3, :2])
        assert frame.yaw == YawFrame.measure(kp, ref).yaw  # the origin does not move the yaw fit
    with pytest.raises(InvalidParameterError, match="never closes"):
        grasp_positions(np.ones((6, 10)), np.array([6]))
    with pytest.raises(InvalidParameterError, match="episode_ends"):
        grasp_positions(actions, np.array([6, 14]))
    with pytest.raises(InvalidParameterError, match="not one of the 5"):
        YawFrame.measure(first[0], ref, origin_keypoint=5)
    with pytest.raises(InvalidParameterError, match=r"\(E, 3\) grasps"):
        nearest_keypoint(first, found[:2])


def test_grasp_origin_is_stored_with_the_reference_and_required_by_its_config(tmp_path: Path) -> None:
    write_reference(tmp_path, _shape())
    assert read_origin_keypoint(tmp_path) is None  # runs written before the option: centroid
    write_reference(tmp_path, _shape(), origin_keypoint=2)
    assert read_origin_keypoint(tmp_path) == 2
    np.testing.assert_allclose(read_reference(tmp_path), _shape()[:, :2])
    with pytest.raises(InvalidParameterError, match="not one of the 8"):
        write_reference(tmp_path, _shape(), origin_keypoint=8)
    with pytest.raises(InvalidParameterError, match="needs yaw_frame"):
        make_policy_config("keygen", yaw_origin="grasp")
    with pytest.raises(InvalidParameterError, match="yaw_origin must be one of"):
        make_policy_config("keygen", yaw_frame=True, yaw_origin="handle")
    assert make_policy_config("keygen", yaw_frame=True, yaw_origin="grasp").yaw_origin == "grasp"


def test_training_arrays_in_grasp_centred_frames(tmp_path: Path) -> None:
    rng = np.random.default_rng(6)
    shape, ends = _shape(k=4), np.array([6, 13])
    angles, shifts = [0.3, -1.9], [(0.5, 0.1, 0.0), (0.4, -0.2, 0.0)]
    kp = np.concatenate(
        [np.repeat(_turn(shape, a, s)[None], n, 0) for a, s, n in zip(angles, shifts, (6, 7), strict=True)]
    )
    actions = _grasp_actions([6, 7], kp[[0, 6], 1] + [0.0, 0.0, 0.01], [4, 3])
    clouds = rng.normal(size=(13, 5, 3)).astype(np.float32)
    c, p, a, k = to_yaw_frames(tmp_path, ends, 4, clouds, actions.copy(), actions, kp, origin="grasp")
    assert read_origin_keypoint(tmp_path) == 1
    np.testing.assert_allclose(k[:, 1, :2], 0.0, atol=1e-9)  # keypoint 1 is every episode's origin
    # The grasp itself lands at the same place in both episodes' frames.
    np.testing.assert_allclose(a[4, :3], a[6 + 3, :3], atol=1e-9)
    with pytest.raises(InvalidParameterError, match="yaw origin must be one of"):
        to_yaw_frames(tmp_path, ends, 4, clouds, actions, actions, kp, origin="handle")


class PointPicker:
    """Keypoints = fixed points of the object's cloud: they turn exactly with the object."""

    def __init__(self, category: str, num_keypoints: int):
        self.category, self.num_keypoints = category, num_keypoints

    def batch(self, clouds):
        return type("P", (), {"keypoints": np.stack([c[: self.num_keypoints] for c in clouds])})()


def _picker_loader(run_dir, device="cpu"):
    meta = json.loads((Path(run_dir) / "config.json").read_text())
    return PointPicker(meta["category"], meta["num_keypoints"])


def test_a_yaw_frame_policy_plans_turn_with_the_scene(
    tiny_store, tmp_path, fake_keypoints, kit, monkeypatch
) -> None:
    monkeypatch.setattr(features, "load_extractor", _picker_loader)
    cfg = tiny_train_config("keygen", tiny_store, tmp_path / "yaw", fake_keypoints, model={"yaw_frame": True})
    run = train_policy(cfg, progress=False)
    assert (run / YAW_REFERENCE_FILE).is_file()
    assert json.loads((run / "config.json").read_text())["policy"]["yaw_frame"] is True
    ep = kit.synthetic_episode(0)
    obs = [kit.observation(ep, t) for t in range(3)]
    runner = load_runner(run)
    first = np.array([runner.act(o) for o in obs])
    centre, theta = np.array([0.3, -0.1, 0.0]), 2.2
    other = load_runner(run)
    second = np.array([other.act(kit.turned_scene(o, theta, centre)) for o in obs])
    assert _wrap(other.yaw_frame.yaw - runner.yaw_frame.yaw - theta) == pytest.approx(0.0, abs=1e-5)
    R = yaw_matrix(theta)
    np.testing.assert_allclose(second[:, :3], (first[:, :3] - centre) @ R.T + centre, atol=2e-4)
    np.testing.assert_allclose(second[:, 3:6], first[:, 3:6] @ R.T, atol=2e-4)
    np.testing.assert_allclose(second[:, 9], first[:, 9], atol=2e-4)
    runner.reset()
    assert runner.yaw_frame is None
    # A yaw-frame policy cannot run without its reference, nor another policy with one.
    with pytest.raises(InvalidParameterError, match="yaw reference"):
        PolicyRunner(runner.model, "pour", runner.keypoints)
    # A centroid-centred policy takes no origin keypoint.
    with pytest.raises(InvalidParameterError, match="origin keypoint"):
        PolicyRunner(
            runner.model, "pour", runner.keypoints, yaw_reference=runner.yaw_reference, yaw_origin_keypoint=0
        )
    (run / YAW_REFERENCE_FILE).unlink()
    with pytest.raises(InvalidParameterError, match="missing"):
        load_runner(run)


def test_a_grasp_centred_policy_measures_its_frame_on_the_anchor(
    tiny_store, tmp_path, fake_keypoints, kit, monkeypatch
) -> None:
    monkeypatch.setattr(features, "load_extractor", _picker_loader)
    cfg = tiny_train_config(
        "keygen", tiny_store, tmp_path / "grasp", fake_keypoints, steps=2,
        model={"yaw_frame": True, "yaw_origin": "grasp"},
    )  # fmt: skip
    run = train_policy(cfg, progress=False)
    anchor = read_origin_keypoint(run)
    assert anchor is not None
    ep = kit.synthetic_episode(0)
    obs = kit.observation(ep, 0)
    runner = load_runner(run)
    runner.act(obs)
    np.testing.assert_allclose(runner.yaw_frame.origin[:2], runner.last_keypoints[anchor, :2], atol=1e-6)
    assert runner.yaw_origin_keypoint == anchor
    # With a size frame the scene is scaled about the grasp (the frame's origin), which stays put.
    sized = load_runner(run, size_normalize=True)
    sized.act(obs)
    np.testing.assert_allclose(sized.size_frame.centre[:2], 0.0, atol=1e-12)
    grasp = sized.yaw_frame.points(sized.last_keypoints[anchor][None])
    np.testing.assert_allclose(grasp[0, :2], 0.0, atol=1e-6)
    moved = sized.size_frame.to_policy({"cloud": grasp, "proprio": np.zeros(10)})["cloud"]
    np.testing.assert_allclose(moved[0, :2], grasp[0, :2], atol=1e-6)  # the grasp is not moved
    # Without the stored anchor the grasp-centred policy refuses to run.
    with pytest.raises(InvalidParameterError, match="origin keypoint"):
        PolicyRunner(runner.model, "pour", runner.keypoints, yaw_reference=runner.yaw_reference)


def test_training_refuses_the_yaw_frame_on_a_task_without_a_heading(tmp_path, kit) -> None:
    store = kit.make_store(tmp_path / "stack.zarr", task="stack")
    cfg = TrainConfig.from_preset(
        "quick", policy="keygen_yaw", dataset=store, out=tmp_path / "run", keypoints={"bowl": tmp_path},
        steps=2,
    )  # fmt: skip
    with pytest.raises(InvalidParameterError, match="'stack' task's object has none"):
        train_policy(cfg, progress=False)
    assert not (tmp_path / "run" / YAW_REFERENCE_FILE).exists()
