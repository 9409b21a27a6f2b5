"""Observation features: deterministic resampling, keypoints per task object, windows as model inputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from keygen.data import EpisodeStore, WindowSampler
from keygen.errors import InvalidParameterError
from keygen.policies import KeypointSource, TrainConfig, make_policy_config
from keygen.policies.data import load_policy_data, window_tables
from keygen.policies.features import (
    MIN_OBJECT_POINTS,
    resample_cloud,
    stack_history,
    step_features,
    window_inputs,
)


def test_resample_is_deterministic_fixed_size_and_from_the_cloud() -> None:
    pts = np.random.default_rng(0).normal(size=(300, 3)).astype(np.float32)
    a, b = resample_cloud(pts, 64), resample_cloud(pts.copy(), 64)
    np.testing.assert_array_equal(a, b)
    assert a.shape == (64, 3) and a.dtype == np.float32
    assert np.all(np.isin(a.view([("", a.dtype)] * 3), pts.view([("", pts.dtype)] * 3)))
    assert resample_cloud(pts[:10], 64).shape == (64, 3)  # fewer points repeat
    with pytest.raises(InvalidParameterError, match="N >= 1"):
        resample_cloud(np.zeros((0, 3)), 8)


def test_keypoint_source_is_object_major_and_falls_back_when_unseen(kit) -> None:
    NUM_KP, FakeExtractor = kit.NUM_KP, kit.FakeExtractor
    ep = kit.synthetic_episode(0, length=3)
    source = KeypointSource("stack", {"bowl": FakeExtractor("bowl")})
    assert (source.num_objects, source.num_keypoints, source.num_tokens) == (2, NUM_KP, 2 * NUM_KP)
    kp = source(ep["object_cloud"], ep["object_cloud_ids"])  # (S, M, 3)
    assert kp.shape == (3, 2 * NUM_KP, 3)
    ext = FakeExtractor("bowl")
    for slot, label in enumerate((1, 2)):
        want = ext.batch([ep["object_cloud"][0][ep["object_cloud_ids"][0] == label]]).keypoints[0]
        np.testing.assert_allclose(kp[0, slot * NUM_KP : (slot + 1) * NUM_KP], want)
    ids = ep["object_cloud_ids"].copy()
    ids[:, : MIN_OBJECT_POINTS * 10] = 2  # object 1 nearly unseen: its slot uses the whole cloud
    ids[:, 0] = 1
    kp2 = source(ep["object_cloud"], ids)
    np.testing.assert_allclose(kp2[0, :NUM_KP], ext.batch([ep["object_cloud"][0]]).keypoints[0])
    with pytest.raises(InvalidParameterError, match="--keypoints mug="):
        KeypointSource("pour", {"bowl": FakeExtractor("bowl")})


def test_window_inputs_match_the_trainer_batches(tmp_path: Path, fake_keypoints: dict, kit) -> None:
    """The trainer's index tables reproduce WindowSampler windows, features included."""
    store = EpisodeStore(kit.make_store(tmp_path / "s.zarr", episodes=3, length=7), mode="r")
    cfg = TrainConfig.from_preset(
        "quick",
        policy="keygen",
        dataset=store.path,
        out=tmp_path / "run",
        keypoints=fake_keypoints,
        policy_overrides={"num_points": 32},
    )
    data = load_policy_data(store, cfg, cfg.out, progress=False)
    pc = data.policy_config
    keys = ["object_cloud", "object_cloud_ids", "proprio"]
    sampler = WindowSampler(store, pc.obs_horizon, pc.horizon, keys, in_memory=True)
    idx = np.array([0, 1, 6, 7, 13, 20])
    batch = sampler.batch(idx)
    frozen = {k: v.copy() for k, v in batch.items()}
    source = KeypointSource("pour", {"mug": kit.FakeExtractor("mug")})
    got = window_inputs(batch, pc, source)
    want = data.batch(idx)
    assert set(got) == set(want)
    for key in want:
        torch.testing.assert_close(got[key], want[key], msg=key)
    for key in frozen:  # the batch is only read
        np.testing.assert_array_equal(batch[key], frozen[key])
    obs, act = window_tables(store.episode_ends, 2, 16)
    assert obs.shape == (21, 2) and act.shape == (21, 16)
    assert obs[7].tolist() == [7, 7] and act[0, -1] == 6  # clipped at episode edges


def test_step_features_and_history_stacking(kit) -> None:
    NUM_KP = kit.NUM_KP
    ep = kit.synthetic_episode(1, length=4)
    cfg = make_policy_config("keygen", num_points=32, num_keypoints=NUM_KP, num_objects=1)
    source = KeypointSource("pour", {"mug": kit.FakeExtractor("mug")})
    obs = kit.observation(ep, 2)
    frozen = {k: v.copy() for k, v in obs.items()}
    f = step_features(obs, cfg, source)
    assert f["cloud"].shape == (32, 3) and f["proprio"].shape == (10,) and f["keypoints"].shape == (NUM_KP, 3)
    for k in frozen:
        np.testing.assert_array_equal(obs[k], frozen[k])
    inputs = stack_history([f, f], cfg)
    assert inputs["cloud"].shape == (1, 1, 32, 3) and inputs["keypoints"].shape == (1, 2, NUM_KP, 3)
    with pytest.raises(InvalidParameterError, match="KeypointSource"):
        step_features(obs, cfg, None)
    with pytest.raises(InvalidParameterError, match="scene_cloud"):
        step_features({"proprio": obs["proprio"]}, make_policy_config("dp3"), None)
