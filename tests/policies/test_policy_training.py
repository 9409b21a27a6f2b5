"""The trainer end to end on tiny synthetic stores: every policy trains, saves, reloads and acts;
runs resume after an interruption and are reused when finished; the loss really drops."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from _policy_runs import tiny_train_config
from keygen.data.store import EpisodeStore, EpisodeStoreError
from keygen.errors import InvalidParameterError
from keygen.policies import POLICY_NAMES, TrainConfig, load_runner, make_policy_config, train_policy
from keygen.policies import training as training_mod
from keygen.policies.checkpoint import PolicyCheckpointError, load_policy
from keygen.policies.data import KEYPOINT_CACHE
from keygen.policies.size_frame import cached_episode_ends, reference_spread, rest_axis_references


@pytest.mark.parametrize("policy", POLICY_NAMES)
def test_every_policy_trains_saves_reloads_and_acts(
    policy, tiny_store, tmp_path, fake_keypoints, kit
) -> None:
    run = train_policy(
        tiny_train_config(policy, tiny_store, tmp_path / policy, fake_keypoints), progress=False
    )
    for name in ("config.json", "model.safetensors", "train_state.safetensors", "metrics.jsonl"):
        assert (run / name).is_file(), name
    meta = json.loads((run / "config.json").read_text())
    assert meta["finished"] and meta["step"] == 5 and meta["task"] == "pour"
    assert np.isfinite(meta["result"]["final_loss"]) and np.isfinite(meta["result"]["val_loss"])
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [1, 2, 3, 4, 5] and rows[-1]["val_loss"] is not None
    uses_kp = make_policy_config(policy).use_keypoints
    assert (run / "keypoints" / "mug" / "config.json").is_file() == uses_kp
    assert not (run / "keypoints" / "mug" / "notes.txt").exists()  # only checkpoint files are copied

    ep = kit.synthetic_episode(0)
    obs = [kit.observation(ep, t) for t in range(3)]
    frozen = [{k: v.copy() for k, v in o.items()} for o in obs]
    runner = load_runner(run)
    assert (runner.task, runner.policy_name, runner.execute_steps) == ("pour", policy, 8)
    first = [runner.act(o) for o in obs]
    assert all(a.shape == (10,) and a.dtype == np.float32 and np.all(np.isfinite(a)) for a in first)
    assert (runner.last_keypoints.shape == (kit.NUM_KP, 3)) if uses_kp else runner.last_keypoints is None
    for o, f in zip(obs, frozen, strict=True):  # observations are only read
        for k in f:
            np.testing.assert_array_equal(o[k], f[k])
    # Round trip: a fresh load with the same seed gives the same actions; reset() restarts the plan.
    again = load_runner(run)
    np.testing.assert_allclose([again.act(o) for o in obs], first, rtol=1e-5, atol=1e-6)
    runner.reset(seed=0)
    np.testing.assert_allclose([runner.act(o) for o in obs], first, rtol=1e-5, atol=1e-6)


def test_receding_horizon_and_whole_trajectory_modes(tiny_store, tmp_path, fake_keypoints, kit) -> None:
    run = train_policy(
        tiny_train_config("keygen_no_kp", tiny_store, tmp_path / "r", fake_keypoints), progress=False
    )
    runner = load_runner(run, execute_steps=3)
    ep = kit.synthetic_episode(0)
    calls = []
    original = runner.predict
    runner.predict = lambda: calls.append(1) or original()
    for t in range(7):
        runner.act(kit.observation(ep, t))
    assert len(calls) == 3  # queries at steps 0, 3, 6
    runner.reset()
    runner.execute_steps = runner.horizon  # whole-trajectory mode
    calls.clear()
    for t in range(16):
        runner.act(kit.observation(ep, t))
    assert len(calls) == 1
    with pytest.raises(InvalidParameterError, match="execute_steps"):
        runner.execute_steps = 17


def test_interrupted_run_resumes_to_the_same_weights(
    tiny_store, tmp_path, fake_keypoints, monkeypatch
) -> None:
    cfg = dict(steps=10, ckpt_every=5, val_every=5)
    full = train_policy(
        tiny_train_config("keygen", tiny_store, tmp_path / "full", fake_keypoints, **cfg), progress=False
    )

    real_save = training_mod._save_state

    def save_then_die(run_dir, model, ema, opt, step, seconds):
        real_save(run_dir, model, ema, opt, step, seconds)
        if step == 5:
            raise KeyboardInterrupt

    monkeypatch.setattr(training_mod, "_save_state", save_then_die)
    broken = tiny_train_config("keygen", tiny_store, tmp_path / "resumed", fake_keypoints, **cfg)
    with pytest.raises(KeyboardInterrupt):
        train_policy(broken, progress=False)
    assert not json.loads((tmp_path / "resumed" / "config.json").read_text())["finished"]
    monkeypatch.setattr(training_mod, "_save_state", real_save)
    resumed = train_policy(broken, progress=False)
    a, _ = load_policy(full)
    b, _ = load_policy(resumed)
    for (name, x), y in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
        torch.testing.assert_close(x, y, msg=name)
    steps = [json.loads(line)["step"] for line in (resumed / "metrics.jsonl").read_text().splitlines()]
    assert steps == list(range(1, 11))  # nothing logged twice
    # The keypoints were computed once and cached; a finished run is reused as it is.
    assert (resumed / "keypoint_cache.npz").is_file()
    mtime = (resumed / "model.safetensors").stat().st_mtime_ns
    assert train_policy(broken, progress=False) == resumed
    assert (resumed / "model.safetensors").stat().st_mtime_ns == mtime


def test_clear_errors(tiny_store, tmp_path, fake_keypoints) -> None:
    with pytest.raises(InvalidParameterError, match="--keypoints mug="):
        train_policy(tiny_train_config("keygen", tiny_store, tmp_path / "a", None), progress=False)
    run = train_policy(tiny_train_config("dp3", tiny_store, tmp_path / "b", None), progress=False)
    with pytest.raises(InvalidParameterError, match="different configuration"):
        train_policy(tiny_train_config("dp3", tiny_store, tmp_path / "b", None, lr=1e-2), progress=False)
    with pytest.raises(PolicyCheckpointError, match="config.json"):
        load_runner(tmp_path / "nothing")
    (run / "model.safetensors").write_bytes(b"garbage")
    with pytest.raises(PolicyCheckpointError, match="do not fit"):
        load_runner(run)


def _plan_error(runner, ep, kit) -> float:
    """Mean position error (m) of the first 8 planned actions against the demonstration, from step 4."""
    runner.reset(seed=0)
    runner.observe(kit.observation(ep, 3))
    runner.act(kit.observation(ep, 4))
    return float(np.abs(runner.last_plan[:8, :3] - ep["action"][4:12, :3]).mean())


def test_loss_drops_on_a_deterministic_dataset(tmp_path, fake_keypoints, kit) -> None:
    """action = proprio + offset: the noise loss must fall far below its starting value, and sampled
    trajectories must be much closer to the demonstrations than those of the untrained policy."""
    store = kit.make_store(tmp_path / "learn.zarr", episodes=6, length=20)
    cfg = tiny_train_config(
        "keygen_no_kp",
        store,
        tmp_path / "learn",
        None,
        steps=300,
        batch_size=32,
        lr=1e-3,
        log_every=25,
        val_every=100,
        ckpt_every=300,
        warmup_steps=20,
        val_fraction=0.0,
    )
    run = train_policy(cfg, progress=False)
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    first, last = rows[0]["loss"], rows[-1]["loss"]
    assert last < 0.2 * first, (first, last)
    untrained = train_policy(
        tiny_train_config("keygen_no_kp", store, tmp_path / "u", None, steps=1, val_fraction=0.0),
        progress=False,
    )
    ep = kit.synthetic_episode(2)  # seen positions, but sampled afresh
    trained_err, untrained_err = (
        _plan_error(load_runner(run), ep, kit),
        _plan_error(load_runner(untrained), ep, kit),
    )
    assert trained_err < 0.1 and trained_err < 0.5 * untrained_err, (trained_err, untrained_err)


def test_with_a_real_tiny_keypoint_extractor(tiny_store, tmp_path, kit) -> None:
    """The real KeypointExtractor (a tiny trained run) through training, the cache and the runner."""
    from keygen.keypoints.training import KeypointTrainConfig, train_keypoints

    kp_cfg = KeypointTrainConfig(
        category="mug",
        num_instances=2,
        scans_per_instance=2,
        image_size=48,
        scan_points=256,
        num_points=64,
        num_keypoints=4,
        width=32,
        hidden=32,
        canon_steps=3,
        detector_steps=3,
        canon_batch=4,
        pair_batch=2,
        train_ablation=False,
        checkpoint_every=3,
        log_every=1,
    )
    kp_run = train_keypoints(kp_cfg, tmp_path / "kp-mug", progress=False)
    run = train_policy(
        tiny_train_config("keygen", tiny_store, tmp_path / "policy", {"mug": kp_run}), progress=False
    )
    assert (run / "keypoints" / "mug" / "train_config.json").is_file()
    assert (run / "keypoints" / "mug" / "detector" / "model.safetensors").is_file()
    with np.load(run / "keypoint_cache.npz") as cache:
        assert cache["keypoints"].shape == (40, 4, 3) and np.isfinite(cache["keypoints"]).all()
    runner = load_runner(run)
    ep = kit.synthetic_episode(0)
    action = runner.act(kit.observation(ep, 0))
    assert action.shape == (10,) and np.isfinite(action).all()
    # Keypoints are convex combinations of the mug's points: inside its bounding box.
    mug = ep["object_cloud"][0][ep["object_cloud_ids"][0] == 1]
    assert np.all(runner.last_keypoints >= mug.min(0) - 1e-5) and np.all(
        runner.last_keypoints <= mug.max(0) + 1e-5
    )


def test_killed_after_the_last_checkpoint_still_finishes(tiny_store, tmp_path, monkeypatch) -> None:
    real_save = training_mod._save_state

    def save_then_die(run_dir, model, ema, opt, step, seconds):
        real_save(run_dir, model, ema, opt, step, seconds)
        raise KeyboardInterrupt

    monkeypatch.setattr(training_mod, "_save_state", save_then_die)
    cfg = tiny_train_config("dp3", tiny_store, tmp_path / "r", None)
    with pytest.raises(KeyboardInterrupt):
        train_policy(cfg, progress=False)
    monkeypatch.setattr(training_mod, "_save_state", real_save)
    run = train_policy(cfg, progress=False)  # nothing left to train: finishes from the logged metrics
    meta = json.loads((run / "config.json").read_text())
    assert meta["finished"] and np.isfinite(meta["result"]["final_loss"])
    assert np.isfinite(meta["result"]["val_loss"])


def test_object_frame_run_fits_its_normaliser_on_relative_positions(
    tiny_store, tmp_path, fake_keypoints, kit
) -> None:
    from keygen.data.store import EpisodeStore
    from keygen.policies.data import load_policy_data

    cfg = tiny_train_config("keygen", tiny_store, tmp_path / "obj", fake_keypoints)
    cfg = TrainConfig(**{**cfg.__dict__, "policy_overrides": cfg.policy_overrides | {"frame": "object"}})
    data = load_policy_data(EpisodeStore(tiny_store, mode="r"), cfg, cfg.out, progress=False)
    actions, proprio = data.fit_arrays(np.array([0]))
    steps = data.samples(np.array([0]))
    t = data.policy_config.horizon
    assert actions.shape == (len(steps) * t, 10) and proprio.shape == (len(steps) * 2, 10)
    s = int(steps[3])
    origin = data.clouds[s].mean(axis=0)
    np.testing.assert_allclose(
        actions[3 * t : 4 * t, :3], data.actions[data.action_index[s], :3] - origin, atol=1e-6
    )
    np.testing.assert_array_equal(actions[3 * t : 4 * t, 3:], data.actions[data.action_index[s], 3:])
    world = dataclasses.replace(data, policy_config=data.policy_config.with_updates(frame="world"))
    world_actions, _ = world.fit_arrays(np.array([0]))
    np.testing.assert_array_equal(world_actions, data.actions[steps])

    run = train_policy(cfg, progress=False)
    assert json.loads((run / "config.json").read_text())["policy"]["frame"] == "object"
    runner = load_runner(run)
    ep = kit.synthetic_episode(0)
    action = runner.act(kit.observation(ep, 0))
    assert action.shape == (10,) and np.all(np.isfinite(action))


def _scaled_scene(obs: dict, centre: np.ndarray, factor: float) -> dict:
    out = {k: np.array(v, copy=True) for k, v in obs.items()}
    for key in ("object_cloud", "scene_cloud"):
        out[key] = (centre + factor * (obs[key] - centre)).astype(np.float32)
    out["proprio"][:3] = centre + factor * (obs["proprio"][:3] - centre)
    return out


def test_runner_plans_scale_with_the_scene(tiny_store, tmp_path, fake_keypoints, kit) -> None:
    """The fake keypoints are quantiles of the cloud, so they scale with it: a scene twice the size
    about the frame's centre is measured twice as large and gets the same plan, twice as large."""
    run = train_policy(
        tiny_train_config("keygen", tiny_store, tmp_path / "r", fake_keypoints), progress=False
    )
    ep = kit.synthetic_episode(0)
    obs = [kit.observation(ep, t) for t in range(3)]
    runner = load_runner(run, size_normalize=True)
    assert runner.size_reference == pytest.approx(reference_spread(run, kit.NUM_KP))
    first = np.array([runner.act(o) for o in obs])
    frame = runner.size_frame
    assert frame is not None and frame.scale > 0
    twice = load_runner(run, size_normalize=True)
    second = np.array([twice.act(_scaled_scene(o, frame.centre, 2.0)) for o in obs])
    assert twice.size_frame.scale == pytest.approx(2 * frame.scale, rel=1e-5)
    np.testing.assert_allclose(twice.size_frame.centre, frame.centre, atol=1e-6)
    c = frame.centre
    np.testing.assert_allclose(second[:, :3], c + 2 * (first[:, :3] - c), atol=2e-4)
    np.testing.assert_allclose(second[:, 3:], first[:, 3:], atol=1e-4)
    runner.reset()  # a new episode measures its own frame
    assert runner.size_frame is None


def test_runner_per_axis_frame_reads_the_datasets_episodes(tiny_store, tmp_path, fake_keypoints, kit) -> None:
    run = train_policy(
        tiny_train_config("keygen", tiny_store, tmp_path / "r", fake_keypoints), progress=False
    )
    ends = EpisodeStore(tiny_store, mode="r").episode_ends
    np.testing.assert_array_equal(cached_episode_ends(run), ends)  # the cache keeps the boundaries
    # A run folder on its own (its config naming a dataset that is not there) keeps its references.
    cfg_path = Path(run) / "config.json"
    cfg = json.loads(cfg_path.read_text())
    assert cfg["train"]["dataset"] == str(tiny_store)
    cfg["train"]["dataset"] = str(tmp_path / "moved-away.zarr")
    cfg_path.write_text(json.dumps(cfg))
    runner = load_runner(run, size_normalize="axes")
    assert runner.size_reference == pytest.approx(rest_axis_references(run, kit.NUM_KP, ends))
    assert rest_axis_references(run, kit.NUM_KP) == pytest.approx(runner.size_reference)
    ep = kit.synthetic_episode(0)
    runner.act(kit.observation(ep, 0))
    assert (
        np.shape(runner.size_frame.scale) == (3,) and runner.size_frame.scale[0] == runner.size_frame.scale[1]
    )
    # A cache written before it kept the boundaries: they come from the dataset, or a clear error.
    cache = Path(run) / KEYPOINT_CACHE
    with np.load(cache) as c:
        kp, fingerprint = c["keypoints"], c["fingerprint"]
    np.savez(cache, keypoints=kp, fingerprint=fingerprint)
    with pytest.raises(InvalidParameterError, match="dataset"):
        load_runner(run, size_normalize="axes")
    cfg["train"]["dataset"] = str(tiny_store)
    cfg_path.write_text(json.dumps(cfg))
    assert load_runner(run, size_normalize="axes").size_reference == pytest.approx(runner.size_reference)


def test_size_frame_needs_a_keypoint_policy(tiny_store, tmp_path, fake_keypoints) -> None:
    run = train_policy(
        tiny_train_config("keygen_no_kp", tiny_store, tmp_path / "r", fake_keypoints), progress=False
    )
    with pytest.raises(InvalidParameterError, match="keypoints"):
        load_runner(run, size_normalize=True)


def test_max_episodes_trains_on_the_first_episodes_and_cannot_change_on_resume(
    tmp_path, fake_keypoints, kit
) -> None:
    store = kit.make_store(tmp_path / "five.zarr", episodes=5)
    run = train_policy(
        tiny_train_config("keygen", store, tmp_path / "head", fake_keypoints, max_episodes=3), progress=False
    )
    meta = json.loads((run / "config.json").read_text())
    assert meta["train"]["max_episodes"] == 3
    assert meta["result"]["train_episodes"] + meta["result"]["val_episodes"] == 3
    ends = EpisodeStore(store, mode="r").episode_ends
    np.testing.assert_array_equal(cached_episode_ends(run), ends[:3])  # keypoints of those 3 only
    with np.load(run / KEYPOINT_CACHE) as cache:
        assert len(cache["keypoints"]) == ends[2]
    with pytest.raises(InvalidParameterError, match="max_episodes: 3 -> 4"):
        train_policy(
            tiny_train_config("keygen", store, run, fake_keypoints, max_episodes=4, steps=6), progress=False
        )
    with pytest.raises(EpisodeStoreError, match="holds 5 episodes, fewer than the 9"):
        train_policy(
            tiny_train_config("keygen", store, tmp_path / "too-many", fake_keypoints, max_episodes=9)
        )
    with pytest.raises(InvalidParameterError, match="max_episodes"):
        tiny_train_config("keygen", store, tmp_path / "x", fake_keypoints, max_episodes=0)


def _keypoint_batch(b: int = 6, h: int = 2, m: int = 4) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(3)
    return {
        "keypoints": torch.randn(b, h, m, 3, generator=gen),
        "cloud": torch.randn(b, 1, 8, 3, generator=gen),
        "action": torch.randn(b, 16, 10, generator=gen),
    }


def test_keypoint_noise_moves_each_keypoint_by_one_offset_over_the_history() -> None:
    batch = _keypoint_batch()
    frozen = {k: v.clone() for k, v in batch.items()}
    out = training_mod.perturb_keypoints(batch, np.random.default_rng([0, 7]), 0.01)
    for key, value in frozen.items():  # the input batch is not mutated
        torch.testing.assert_close(batch[key], value, rtol=0, atol=0)
    offset = out["keypoints"] - batch["keypoints"]
    torch.testing.assert_close(offset[:, 0], offset[:, 1])  # the same offset at every history frame
    assert out["cloud"] is batch["cloud"] and out["action"] is batch["action"]  # nothing else moves
    per_keypoint = offset[:, 0].reshape(-1, 3)
    assert len(torch.unique(per_keypoint[:, 0])) == len(per_keypoint)  # one draw per window and keypoint
    assert 0.004 < float(per_keypoint.std()) < 0.02  # std 1 cm, 72 draws
    again = training_mod.perturb_keypoints(batch, np.random.default_rng([0, 7]), 0.01)
    torch.testing.assert_close(again["keypoints"], out["keypoints"], rtol=0, atol=0)  # seeded by step
    assert training_mod.perturb_keypoints(batch, np.random.default_rng(0), 0.0) is batch
    no_kp = {k: v for k, v in batch.items() if k != "keypoints"}
    assert training_mod.perturb_keypoints(no_kp, np.random.default_rng(0), 0.01) is no_kp


def test_proprio_noise_moves_the_hand_position_by_one_offset_over_the_history() -> None:
    gen = torch.Generator().manual_seed(4)
    batch = {
        "proprio": torch.randn(40, 2, 10, generator=gen),
        "action": torch.randn(40, 16, 10, generator=gen),
    }
    frozen = {k: v.clone() for k, v in batch.items()}
    out = training_mod.perturb_proprio(batch, np.random.default_rng([0, 7]), 0.01)
    for key, value in frozen.items():  # the input batch is not mutated
        torch.testing.assert_close(batch[key], value, rtol=0, atol=0)
    offset = out["proprio"] - batch["proprio"]
    assert out["proprio"].dtype == batch["proprio"].dtype and out["action"] is batch["action"]
    torch.testing.assert_close(offset[:, 0], offset[:, 1])  # the same offset at every history frame
    assert torch.all(offset[..., 3:] == 0)  # rotation (6D) and gripper are kept
    assert len(torch.unique(offset[:, 0, 0])) == 40  # one draw per window
    assert 0.006 < float(offset[:, 0, :3].std()) < 0.014  # std 1 cm, 120 draws
    again = training_mod.perturb_proprio(batch, np.random.default_rng([0, 7]), 0.01)
    torch.testing.assert_close(again["proprio"], out["proprio"], rtol=0, atol=0)  # seeded by step
    assert training_mod.perturb_proprio(batch, np.random.default_rng(0), 0.0) is batch


@pytest.mark.parametrize("field", ["keypoint_noise", "proprio_noise"])
def test_training_noise_trains_is_stored_and_is_checked(field, tiny_store, tmp_path, fake_keypoints) -> None:
    run = train_policy(
        tiny_train_config("keygen", tiny_store, tmp_path / "noisy", fake_keypoints, **{field: 0.01}),
        progress=False,
    )
    meta = json.loads((run / "config.json").read_text())
    assert meta["train"][field] == 0.01 and np.isfinite(meta["result"]["final_loss"])
    clean = train_policy(
        tiny_train_config("keygen", tiny_store, tmp_path / "clean", fake_keypoints), progress=False
    )
    # Same seed, same batches: only the noised input differs, so the weights do.
    a, b = load_policy(run)[0].state_dict(), load_policy(clean)[0].state_dict()
    assert any(not torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(InvalidParameterError, match=f"{field}: 0.01 -> 0.02"):
        train_policy(tiny_train_config("keygen", tiny_store, run, fake_keypoints, **{field: 0.02}, steps=6))
    for bad in (-0.01, 0.5, float("nan"), True):
        with pytest.raises(InvalidParameterError, match=field):
            tiny_train_config("keygen", tiny_store, tmp_path / "x", fake_keypoints, **{field: bad})


def test_keypoint_noise_needs_keypoints_and_proprio_noise_does_not(
    tiny_store, tmp_path, fake_keypoints
) -> None:
    with pytest.raises(InvalidParameterError, match="no_kp"):
        tiny_train_config("keygen_no_kp", tiny_store, tmp_path / "x", fake_keypoints, keypoint_noise=0.01)
    config = tiny_train_config("dp3", tiny_store, tmp_path / "dp3", proprio_noise=0.01)
    assert config.proprio_noise == 0.01


def test_a_run_written_before_a_new_train_field_still_resumes(tiny_store, tmp_path, fake_keypoints) -> None:
    run = train_policy(
        tiny_train_config("keygen", tiny_store, tmp_path / "old", fake_keypoints), progress=False
    )
    meta = json.loads((run / "config.json").read_text())
    del meta["train"]["keypoint_noise"]  # as a run from before the field existed holds it
    (run / "config.json").write_text(json.dumps(meta))
    resumed = train_policy(
        tiny_train_config("keygen", tiny_store, run, fake_keypoints, steps=7), progress=False
    )
    assert json.loads((resumed / "config.json").read_text())["step"] == 7
