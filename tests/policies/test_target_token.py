"""The target token: the placement target's centre, top and size measured from its points, its
invariance to the target's turn, clear errors, training arrays in each episode's frame, a model that
uses it, and a runner that measures it once per episode and whose plan turns with the scene."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from _policy_runs import tiny_inputs, tiny_model, tiny_train_config, with_all_weights_drawn
from keygen.data.store import ACTION_KEY, EpisodeStore
from keygen.errors import InvalidParameterError
from keygen.geometry.rotations import yaw_matrix
from keygen.policies import TrainConfig, load_runner, train_policy
from keygen.policies.config import make_policy_config
from keygen.policies.data import apply_episode_frames, episode_target_tokens, target_episode_frames
from keygen.policies.diffusion import DiffusionPolicy
from keygen.policies.target_frame import TARGET_LABEL, target_points
from keygen.policies.target_token import TARGET_DIM, measure_target, target_in_frame
from keygen.policies.yaw_frame import YawFrame

BOX = (0.16, 0.13, 0.06)  # outer length, width, wall height


def _open_box(centre_xy, yaw: float, n: int = 400, seed: int = 0, size=BOX) -> np.ndarray:
    """``n`` points on an open box's four walls and floor (what cameras see of the pouring box),
    turned by ``yaw``, its bottom centre at ``centre_xy``; the wall tops carry the highest points."""
    rng = np.random.default_rng(seed)
    lx, ly, h = size
    per_wall = (n - n // 5) // 4
    n_floor = n - 4 * per_wall
    floor = np.column_stack(
        [
            rng.uniform(-lx / 2, lx / 2, n_floor),
            rng.uniform(-ly / 2, ly / 2, n_floor),
            np.full(n_floor, 0.008),
        ]
    )
    walls = []
    for axis, half, other in (
        (0, lx / 2, ly / 2),
        (0, -lx / 2, ly / 2),
        (1, ly / 2, lx / 2),
        (1, -ly / 2, lx / 2),
    ):
        along = rng.uniform(-other, other, per_wall)
        z = rng.uniform(0.0, h, per_wall)
        z[:6] = h  # the wall tops are seen
        xy = (
            np.column_stack([np.full(per_wall, half), along])
            if axis == 0
            else np.column_stack([along, np.full(per_wall, half)])
        )
        walls.append(np.column_stack([xy, z]))
    local = np.concatenate([floor, *walls])
    return local @ yaw_matrix(yaw).T + [centre_xy[0], centre_xy[1], 0.0]


@pytest.mark.parametrize("yaw", [0.0, 0.5, 1.2, -2.4])
def test_the_token_finds_the_box_centre_top_and_size(yaw) -> None:
    centre = np.array([0.49, -0.2])
    token = measure_target(_open_box(centre, yaw, seed=1))
    assert token.shape == (TARGET_DIM,) and token.dtype == np.float32
    np.testing.assert_allclose(token[:2], centre, atol=3e-3)
    assert token[2] == pytest.approx(BOX[2], abs=1e-6)
    np.testing.assert_allclose(token[3:], [BOX[0] / 2, BOX[1] / 2], atol=3e-3)


def test_turning_the_box_moves_only_its_centre() -> None:
    # Turning the points about a vertical axis turns the centre with them and leaves top and size:
    # the rectangle is found from the convex hull's edges, which turn with the points.
    points = _open_box((0.45, -0.18), 0.3, seed=4)
    pivot, theta = np.array([0.5, -0.2, 0.0]), 0.8
    turned = (points - pivot) @ yaw_matrix(theta).T + pivot
    a, b = measure_target(points), measure_target(turned)
    np.testing.assert_allclose(b[:3], (a[:3] - pivot) @ yaw_matrix(theta).T + pivot, atol=1e-5)
    np.testing.assert_allclose(b[3:], a[3:], atol=1e-5)


def test_a_frame_maps_the_position_and_keeps_the_extents() -> None:
    token = np.array([0.5, -0.2, 0.06, 0.08, 0.07], np.float32)
    before = token.copy()
    frame = YawFrame(np.array([0.4, 0.1, 0.0]), 0.7)
    out = target_in_frame(token, frame)
    np.testing.assert_allclose(out[:3], frame.points(token[:3]), atol=1e-6)
    np.testing.assert_array_equal(out[3:], token[3:])
    np.testing.assert_array_equal(token, before)  # input left as it was
    batch = target_in_frame(np.stack([token, token]), frame)
    assert batch.shape == (2, TARGET_DIM)


def test_clear_errors_on_bad_target_points() -> None:
    with pytest.raises(InvalidParameterError, match="fewer than"):
        measure_target(_open_box((0.5, -0.2), 0.0)[:5])
    with pytest.raises(InvalidParameterError, match="finite"):
        measure_target(np.full((20, 3), np.nan))
    with pytest.raises(InvalidParameterError, match="finite"):
        measure_target(np.zeros((20, 2)))
    with pytest.raises(InvalidParameterError, match="5 numbers"):
        target_in_frame(np.zeros(3), YawFrame(np.zeros(3), 0.0))


def test_the_config_needs_the_dit_for_a_target_token() -> None:
    assert not make_policy_config("keygen").target_token
    assert make_policy_config("keygen_yaw", target_token=True).target_token
    with pytest.raises(InvalidParameterError, match="DiT backbone"):
        make_policy_config("dp3", target_token=True)
    # Configurations saved before the field existed read back without it.
    data = make_policy_config("keygen").to_dict()
    data.pop("target_token")
    assert not make_policy_config("keygen").from_dict(data).target_token


def _model(**overrides) -> DiffusionPolicy:
    return tiny_model("keygen", **overrides)


def _inputs(target: list[float] | None) -> dict[str, torch.Tensor]:
    return tiny_inputs() if target is None else tiny_inputs(target=target)


def test_the_model_conditions_on_the_target() -> None:
    model = with_all_weights_drawn(_model(target_token=True))
    near = _inputs([0.45, -0.15, 0.05, 0.08, 0.07])
    far = _inputs([0.55, -0.25, 0.05, 0.08, 0.07])
    a = model.predict(near, generator=torch.Generator().manual_seed(3))
    b = model.predict(far, generator=torch.Generator().manual_seed(3))
    assert a.shape == (1, 16, 10)
    assert not torch.allclose(a, b)  # the token reaches the noise network
    with pytest.raises(InvalidParameterError, match="needs input 'target'"):
        model.predict(_inputs(None))
    with pytest.raises(InvalidParameterError, match="input 'target' must be"):
        model.predict(dict(near, target=torch.zeros((1, 3))))
    # The object frame shifts the token's position like every other point, not its extents.
    shifted = model.to_frame(near, torch.tensor([[0.4, -0.1, 0.0]]))
    np.testing.assert_allclose(shifted["target"][0].numpy(), [0.05, -0.05, 0.05, 0.08, 0.07], atol=1e-6)
    # Without the option the model has no target parameters (older checkpoints keep their shapes).
    assert not any("target" in name for name in _model().state_dict())


def _knife_store(kit, path: Path, yaws, centre=(0.5, -0.18)) -> Path:
    """Synthetic knife episodes whose target (label 2) is an open box turned by each yaw."""
    store = EpisodeStore(path, mode="w")
    for e, yaw in enumerate(yaws):
        ep = kit.synthetic_episode(e)
        ids = ep["object_cloud_ids"]
        n = int((ids[0] == TARGET_LABEL).sum())
        ep["object_cloud"][:, ids[0] == TARGET_LABEL] = _open_box(centre, yaw, n=n, seed=e).astype(np.float32)
        store.append_episode(ep, {"task": "knife", "seed": e, "success": True})
    return path


def test_training_tokens_are_each_episodes_first_measurement_in_its_frame(tmp_path: Path, kit) -> None:
    store = EpisodeStore(_knife_store(kit, tmp_path / "knife.zarr", [0.3, 1.1, -0.6]), "r")
    s = store.num_steps
    tokens = episode_target_tokens(store)
    assert tokens.shape == (s, TARGET_DIM)
    clouds, ids = (
        np.asarray(store.read("object_cloud", 0, s)),
        np.asarray(store.read("object_cloud_ids", 0, s)),
    )
    starts = np.concatenate([[0], store.episode_ends[:-1]])
    for a, b in zip(starts, store.episode_ends, strict=True):
        np.testing.assert_array_equal(
            tokens[a:b], np.broadcast_to(measure_target(target_points(clouds[a], ids[a])), (b - a, 5))
        )
    frames = target_episode_frames(store)
    raw = [np.asarray(store.read(k, 0, s)) for k in ("proprio", ACTION_KEY)]
    before = tokens.copy()
    *_, in_frame = apply_episode_frames(frames, store.episode_ends, clouds, raw[0], raw[1], None, tokens)
    np.testing.assert_array_equal(tokens, before)  # the inputs are only read
    for frame, a in zip(frames, starts, strict=True):
        np.testing.assert_allclose(in_frame[a], target_in_frame(tokens[a], frame), atol=1e-6)
    # The target frame is centred on the box, so every episode's token sits near its origin.
    assert np.abs(in_frame[:, :2]).max() < 2e-2


def test_a_target_token_policy_measures_once_and_turns_with_the_scene(
    tmp_path: Path, kit, fake_keypoints
) -> None:
    store = _knife_store(kit, tmp_path / "knife.zarr", [0.3, 1.4])
    cfg = tiny_train_config(
        "keygen", store, tmp_path / "run", fake_keypoints, steps=3,
        model={"yaw_frame": True, "yaw_source": "target", "target_token": True},
    )  # fmt: skip
    run = train_policy(cfg, progress=False)
    assert json.loads((run / "config.json").read_text())["policy"]["target_token"] is True
    ep = kit.synthetic_episode(9)
    ids = ep["object_cloud_ids"]
    label = ids[0] == TARGET_LABEL
    # The box's long side along the line to the robot: an open box has no slot, so the target frame
    # takes the longer side, and the sign rule stays clear of its half-turn ambiguity when turned.
    box_yaw = float(np.arctan2(-0.18, 0.5))
    ep["object_cloud"][:, label] = _open_box((0.5, -0.18), box_yaw, n=int(label.sum()), seed=9).astype(
        np.float32
    )
    obs = [kit.observation(ep, t) for t in range(3)]
    runner = load_runner(run)
    first = np.array([runner.act(o) for o in obs])
    np.testing.assert_allclose(runner.target, measure_target(target_points(obs[0]["object_cloud"], ids[0])))
    # Measured once per episode: a later observation with the box elsewhere does not move it.
    moved = dict(
        obs[2], object_cloud=obs[2]["object_cloud"] + np.where(label[:, None], 0.05, 0.0).astype(np.float32)
    )
    kept = runner.target.copy()
    runner.act(moved)
    np.testing.assert_array_equal(runner.target, kept)
    runner.reset()
    assert runner.target is None
    # The whole scene turned about the box: token, frame and plan turn together.
    centre, theta = np.array([0.5, -0.18, 0.0]), 0.6
    other = load_runner(run)
    second = np.array([other.act(kit.turned_scene(o, theta, centre)) for o in obs])
    R = yaw_matrix(theta)
    np.testing.assert_allclose(other.target[:3], (kept[:3] - centre) @ R.T + centre, atol=1e-5)
    np.testing.assert_allclose(second[:, :3], (first[:, :3] - centre) @ R.T + centre, atol=5e-4)
    np.testing.assert_allclose(second[:, 9], first[:, 9], atol=5e-4)


def test_training_refuses_a_target_token_where_the_target_has_keypoints(
    tmp_path: Path, kit, fake_keypoints
) -> None:
    store = kit.make_store(tmp_path / "stack.zarr", task="stack")
    cfg = TrainConfig.from_preset(
        "quick", policy="keygen", dataset=store, out=tmp_path / "run", keypoints=fake_keypoints, steps=2,
        policy_overrides={"target_token": True},
    )  # fmt: skip
    with pytest.raises(InvalidParameterError, match="'stack' task's has"):
        train_policy(cfg, progress=False)


def test_a_target_token_policy_refuses_the_size_frame(tmp_path: Path, kit, fake_keypoints) -> None:
    store = kit.make_store(tmp_path / "pour.zarr", task="pour")
    cfg = tiny_train_config(
        "keygen", store, tmp_path / "run", fake_keypoints, steps=2, model={"target_token": True}
    )
    run = train_policy(cfg, progress=False)
    with pytest.raises(InvalidParameterError, match="without size normalisation"):
        load_runner(run, size_normalize=True)
