"""The robot-base input: the base's place and the world's heading in a yaw frame, worked by hand;
one value per episode in training; a model that conditions on it; a runner that gives the model its
own frame's value; clear errors where it has no meaning."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from _policy_runs import tiny_inputs, tiny_model, tiny_train_config, with_all_weights_drawn
from keygen.data.store import EpisodeStore
from keygen.errors import InvalidParameterError
from keygen.policies import load_runner, train_policy
from keygen.policies.config import make_policy_config
from keygen.policies.data import load_policy_data
from keygen.policies.diffusion import DiffusionPolicy
from keygen.policies.robot_base import BASE_DIM, base_in_frame, episode_bases
from keygen.policies.yaw_frame import YawFrame


def test_the_base_and_heading_in_a_frame_worked_by_hand() -> None:
    # Frame at (0.5, 0.2) turned by +90 degrees: the base (world origin) lies at (-0.5, -0.2) from the
    # origin, which the frame's -90 degree turn maps to (-0.2, 0.5); the world's +x axis to (0, -1).
    frame = YawFrame(np.array([0.5, 0.2, 0.0]), np.pi / 2)
    value = base_in_frame(frame)
    assert value.shape == (BASE_DIM,) and value.dtype == np.float32
    np.testing.assert_allclose(value, [-0.2, 0.5, 0.0, -1.0], atol=1e-6)
    # The same as mapping the base and a point one metre along world +x through the frame.
    ends = frame.points(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))
    np.testing.assert_allclose(value[:2], ends[0, :2], atol=1e-6)
    np.testing.assert_allclose(value[2:], ends[1, :2] - ends[0, :2], atol=1e-6)
    # The identity frame: the base at the origin, the heading along +x.
    np.testing.assert_allclose(base_in_frame(YawFrame(np.zeros(3), 0.0)), [0, 0, 1, 0], atol=1e-7)


def test_every_step_carries_its_episodes_value() -> None:
    frames = [YawFrame(np.array([0.4, -0.1, 0.0]), 0.3), YawFrame(np.array([0.6, 0.2, 0.0]), -2.0)]
    out = episode_bases(frames, np.array([3, 7]))
    assert out.shape == (7, BASE_DIM)
    np.testing.assert_array_equal(out[:3], np.broadcast_to(base_in_frame(frames[0]), (3, BASE_DIM)))
    np.testing.assert_array_equal(out[3:], np.broadcast_to(base_in_frame(frames[1]), (4, BASE_DIM)))
    assert episode_bases([], np.zeros(0, np.int64)).shape == (0, BASE_DIM)


def test_the_config_needs_a_yaw_frame_and_the_dit() -> None:
    assert not make_policy_config("keygen_yaw").robot_base
    assert make_policy_config("keygen_yaw", robot_base=True).robot_base
    with pytest.raises(InvalidParameterError, match="needs yaw_frame"):
        make_policy_config("keygen", robot_base=True)  # world frame: the base never moves
    with pytest.raises(InvalidParameterError, match="DiT backbone"):
        make_policy_config("dp3", robot_base=True, yaw_frame=True, yaw_source="target")
    # Configurations saved before the field existed read back without it.
    data = make_policy_config("keygen_yaw").to_dict()
    data.pop("robot_base")
    assert not make_policy_config("keygen").from_dict(data).robot_base


def _model(**overrides) -> DiffusionPolicy:
    return tiny_model("keygen_yaw", **overrides)


def _inputs(base: list[float] | None) -> dict[str, torch.Tensor]:
    return tiny_inputs() if base is None else tiny_inputs(base=base)


def test_the_model_conditions_on_the_base() -> None:
    model = with_all_weights_drawn(_model(robot_base=True))
    near = _inputs([-0.3, 0.1, 1.0, 0.0])
    far = _inputs([-0.7, -0.4, 0.0, 1.0])
    before = {k: v.clone() for k, v in near.items()}
    a = model.predict(near, generator=torch.Generator().manual_seed(3))
    b = model.predict(far, generator=torch.Generator().manual_seed(3))
    assert a.shape == (1, 16, 10)
    assert not torch.allclose(a, b)  # the input reaches the noise network
    for key, value in before.items():
        torch.testing.assert_close(near[key], value)  # the inputs are not modified
    loss = model.compute_loss(dict(near, action=torch.zeros((1, 16, 10))))
    assert torch.isfinite(loss)
    with pytest.raises(InvalidParameterError, match="needs input 'base'"):
        model.predict(_inputs(None))
    with pytest.raises(InvalidParameterError, match="input 'base' must be"):
        model.predict(dict(near, base=torch.zeros((1, 3))))
    # An object frame shifts the base's position like every other point, not the heading.
    shifted = model.to_frame(near, torch.tensor([[0.1, -0.1, 0.05]]))
    np.testing.assert_allclose(shifted["base"][0].numpy(), [-0.4, 0.2, 1.0, 0.0], atol=1e-6)
    # Without the option the model has no base parameters (older checkpoints keep their shapes).
    assert not any(name.startswith("obs_encoder.base") for name in _model().state_dict())


def test_training_and_the_runner_use_each_episodes_frame(
    tiny_store: Path, tmp_path: Path, kit, fake_keypoints
) -> None:
    cfg = tiny_train_config(
        "keygen", tiny_store, tmp_path / "run", fake_keypoints, steps=3,
        model={"yaw_frame": True, "robot_base": True},
    )  # fmt: skip
    run = train_policy(cfg, progress=False)
    assert json.loads((run / "config.json").read_text())["policy"]["robot_base"] is True
    # Training arrays: one value per episode, in the frame its other inputs are in. The frame moves
    # the world's points rigidly, so the tcp seen from the base, turned by the world's heading in
    # the frame, is the tcp's world position.
    store = EpisodeStore(tiny_store, "r")
    data = load_policy_data(store, cfg, tmp_path / "run", progress=False)
    assert data.bases is not None and data.bases.shape == (store.num_steps, BASE_DIM)
    world_tcp = np.asarray(store.read("proprio", 0, store.num_steps))[:, :2]
    starts = np.concatenate([[0], store.episode_ends[:-1]])
    for a, b in zip(starts, store.episode_ends, strict=True):
        np.testing.assert_array_equal(data.bases[a:b], np.broadcast_to(data.bases[a], (b - a, BASE_DIM)))
        c, s = data.bases[a, 2:]
        assert np.hypot(c, s) == pytest.approx(1.0, abs=1e-6)
        from_base = data.proprio[a:b, :2] - data.bases[a, :2]
        turned_back = from_base @ np.array([[c, -s], [s, c]])  # rows: R(heading)^T applied
        np.testing.assert_allclose(turned_back, world_tcp[a:b], atol=1e-5)
    assert data.batch(np.array([0, 1]))["base"].shape == (2, BASE_DIM)
    # The runner hands the model the value of the frame it measured at the first query.
    runner = load_runner(run)
    seen = []
    predict = runner.model.predict
    runner.model.predict = lambda inputs, **kw: seen.append(inputs["base"].clone()) or predict(inputs, **kw)
    ep = kit.synthetic_episode(0)
    for t in range(3):
        runner.act(kit.observation(ep, t))
    assert seen, "the runner never queried the model"
    for value in seen:
        np.testing.assert_allclose(value[0].numpy(), base_in_frame(runner.yaw_frame), atol=1e-6)
    with pytest.raises(InvalidParameterError, match="without size normalisation"):
        load_runner(run, size_normalize=True)
