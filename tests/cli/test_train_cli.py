"""keygen train: a short run with a JSON summary, resume/reuse, and clear errors."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from keygen.cli import train
from keygen.data.store import EpisodeStore, EpisodeStoreError
from keygen.errors import InvalidParameterError


def run_cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    train.register(sub)
    args = parser.parse_args(["train", *argv])
    return args.func(args)


def make_store(path: Path) -> Path:
    store = EpisodeStore(path, mode="w")
    rng = np.random.default_rng(0)
    for e in range(2):
        t = 12
        proprio = np.zeros((t, 10), np.float32)
        proprio[:, :3] = np.linspace([0.4, 0.0, 0.3], [0.5, 0.1, 0.1], t) + e * 0.01
        proprio[:, 3:9] = [1, 0, 0, 0, 1, 0]
        cloud = (np.array([0.5, 0.0, 0.05]) + rng.normal(0, 0.03, (t, 64, 3))).astype(np.float32)
        store.append_episode(
            {
                "proprio": proprio,
                "action": proprio + 0.01,
                "object_cloud": cloud,
                "object_cloud_ids": np.ones((t, 64), np.int32),
                "scene_cloud": cloud,
            },
            {"task": "pour", "seed": e, "success": True},
        )
    return path


@pytest.fixture(autouse=True)
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_train_prints_a_json_summary_and_reuses_a_finished_run(tmp_path, capsys) -> None:
    store = make_store(tmp_path / "d.zarr")
    argv = [
        "--policy",
        "dp3",
        "--dataset",
        str(store),
        "--out",
        str(tmp_path / "run"),
        "--steps",
        "3",
        "--batch-size",
        "4",
        "--preset",
        "quick",
        "--seed",
        "1",
        "--json",
    ]
    assert run_cli(argv) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["run_dir"] == str(tmp_path / "run") and summary["steps"] == 3
    assert np.isfinite(summary["final_loss"]) and np.isfinite(summary["val_loss"]) and summary["seconds"] >= 0
    assert (tmp_path / "run" / "model.safetensors").is_file()
    assert run_cli(argv) == 0  # finished: reused, same summary
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == summary


def test_keygen_without_keypoints_names_the_categories(tmp_path) -> None:
    store = make_store(tmp_path / "d.zarr")
    with pytest.raises(InvalidParameterError, match="--keypoints mug="):
        run_cli(["--policy", "keygen", "--dataset", str(store), "--out", str(tmp_path / "r"), "--steps", "2"])
    with pytest.raises(InvalidParameterError, match="CATEGORY=RUN_DIR"):
        run_cli(
            [
                "--policy",
                "keygen",
                "--dataset",
                str(store),
                "--out",
                str(tmp_path / "r"),
                "--keypoints",
                "mug",
            ]
        )
    with pytest.raises(InvalidParameterError, match="does not exist"):
        run_cli(["--policy", "dp3", "--dataset", str(tmp_path / "none.zarr"), "--out", str(tmp_path / "r2")])


def test_yaw_frame_needs_a_keypoint_policy(tmp_path) -> None:
    store = make_store(tmp_path / "d.zarr")
    with pytest.raises(InvalidParameterError, match="use_keypoints"):
        run_cli(["--policy", "dp3", "--dataset", str(store), "--out", str(tmp_path / "r"), "--yaw-frame"])


def test_yaw_origin_needs_the_yaw_frame(tmp_path) -> None:
    store = make_store(tmp_path / "d.zarr")
    with pytest.raises(InvalidParameterError, match="needs yaw_frame"):
        run_cli(
            [
                "--policy",
                "keygen",
                "--dataset",
                str(store),
                "--out",
                str(tmp_path / "r"),
                "--yaw-origin",
                "grasp",
            ]
        )


def test_yaw_source_target_needs_the_yaw_frame_and_a_knife_dataset(tmp_path) -> None:
    store = make_store(tmp_path / "d.zarr")  # a pour dataset
    argv = ["--policy", "keygen_no_kp", "--dataset", str(store), "--out", str(tmp_path / "r"), "--steps", "2"]
    with pytest.raises(InvalidParameterError, match="needs yaw_frame"):
        run_cli([*argv, "--yaw-source", "target"])
    with pytest.raises(InvalidParameterError, match="'pour' task's target has none"):
        run_cli([*argv, "--yaw-frame", "--yaw-source", "target"])


def test_max_episodes_beyond_the_dataset_fails_before_creating_the_run(tmp_path) -> None:
    store = make_store(tmp_path / "d.zarr")
    argv = ["--policy", "dp3", "--dataset", str(store), "--out", str(tmp_path / "r"), "--steps", "2"]
    with pytest.raises(EpisodeStoreError, match="holds 2 episodes, fewer than the 3 asked for"):
        run_cli([*argv, "--max-episodes", "3"])
    assert not (tmp_path / "r").exists()
    with pytest.raises(InvalidParameterError, match="max_episodes must be a positive int"):
        run_cli([*argv, "--max-episodes", "0"])


def test_target_token_needs_the_dit_and_a_visible_target(tmp_path) -> None:
    store = make_store(tmp_path / "d.zarr")  # a pour dataset whose clouds hold the mug only (label 1)
    argv = ["--dataset", str(store), "--out", str(tmp_path / "r"), "--steps", "2", "--target-token"]
    with pytest.raises(InvalidParameterError, match="DiT backbone"):
        run_cli(["--policy", "dp3", *argv])
    with pytest.raises(InvalidParameterError, match="episode 0 of .* the target shows 0 points"):
        run_cli(["--policy", "keygen_no_kp", *argv])


def test_robot_base_needs_a_yaw_frame_and_is_refused_before_creating_the_run(tmp_path) -> None:
    store = make_store(tmp_path / "d.zarr")
    argv = ["--dataset", str(store), "--out", str(tmp_path / "r"), "--steps", "2", "--robot-base"]
    with pytest.raises(InvalidParameterError, match="needs yaw_frame"):
        run_cli(["--policy", "keygen", *argv])
    with pytest.raises(InvalidParameterError, match="DiT backbone"):
        run_cli(["--policy", "dp3", "--yaw-frame", "--yaw-source", "target", *argv])
    assert not (tmp_path / "r").exists()


def test_keypoint_noise_is_refused_for_policies_without_keypoints_and_out_of_range(tmp_path) -> None:
    store = make_store(tmp_path / "d.zarr")
    argv = ["--dataset", str(store), "--out", str(tmp_path / "r"), "--steps", "2"]
    with pytest.raises(InvalidParameterError, match="'dp3' has none"):
        run_cli(["--policy", "dp3", *argv, "--keypoint-noise", "0.01"])
    with pytest.raises(InvalidParameterError, match="keypoint_noise is a std in metres"):
        run_cli(["--policy", "keygen", *argv, "--keypoint-noise", "-0.01"])
    assert not (tmp_path / "r").exists()


def test_proprio_noise_reaches_the_run_config_and_is_range_checked(tmp_path) -> None:
    store = make_store(tmp_path / "d.zarr")
    argv = ["--policy", "dp3", "--dataset", str(store), "--steps", "2", "--batch-size", "4", "--json"]
    with pytest.raises(InvalidParameterError, match="proprio_noise is a std in metres"):
        run_cli([*argv, "--out", str(tmp_path / "bad"), "--proprio-noise", "0.2"])
    assert not (tmp_path / "bad").exists()
    assert (
        run_cli([*argv, "--out", str(tmp_path / "r"), "--preset", "quick", "--proprio-noise", "0.005"]) == 0
    )
    assert json.loads((tmp_path / "r" / "config.json").read_text())["train"]["proprio_noise"] == 0.005
