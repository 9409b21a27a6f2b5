"""Shared fixtures of the policy tests: a fake keypoint extractor, tiny synthetic episode stores and
the benchmark scripts (not a package) loaded by path."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from keygen.data.store import ACTION_KEY, EpisodeStore
from keygen.policies import features

N_POINTS = 96  # stored cloud size (the models resample to their own count)
NUM_KP = 4


@dataclass(frozen=True)
class FakePrediction:
    keypoints: np.ndarray  # (B, K, 3)


class FakeExtractor:
    """Keypoints at fixed per-axis quantiles of the cloud: deterministic, and they move with the object."""

    def __init__(self, category: str, num_keypoints: int = NUM_KP):
        self.category, self.num_keypoints = category, num_keypoints
        self.calls = 0

    def batch(self, clouds: list[np.ndarray]) -> FakePrediction:
        self.calls += 1
        qs = (np.arange(self.num_keypoints) + 0.5) / self.num_keypoints
        return FakePrediction(np.stack([np.quantile(c, qs, axis=0) for c in clouds]).astype(np.float32))

    def __call__(self, cloud: np.ndarray) -> FakePrediction:
        return self.batch([cloud] if cloud.ndim == 2 else list(cloud))


def fake_loader(run_dir, device="cpu") -> FakeExtractor:
    meta = json.loads((Path(run_dir) / "config.json").read_text())
    return FakeExtractor(meta["category"], meta["num_keypoints"])


@pytest.fixture(autouse=True)
def one_thread():
    """One torch thread: on a shared 2-core machine, OpenMP threads that wait on each other make
    small models many times slower than one thread."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def fake_keypoints(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict[str, Path]:
    """Keypoint 'runs' for every category, loaded by the fake loader instead of the real extractor."""
    monkeypatch.setattr(features, "load_extractor", fake_loader)
    runs = {}
    for cat in ("mug", "knife", "bowl"):
        d = tmp_path / f"kp-{cat}"
        d.mkdir()
        (d / "config.json").write_text(json.dumps({"category": cat, "num_keypoints": NUM_KP}))
        (d / "notes.txt").write_text("not a checkpoint file: not copied")
        runs[cat] = d
    return runs


def synthetic_episode(seed: int, length: int = 20) -> dict[str, np.ndarray]:
    """An episode whose action is a deterministic function of the observation (proprio + offset)."""
    rng = np.random.default_rng(seed)
    obj = np.array([0.5, 0.0, 0.05]) + rng.uniform(-0.1, 0.1, 3) * [1, 1, 0]
    pos = np.array([0.4, 0.1, 0.3]) + np.linspace(0, 1, length)[:, None] * (obj - [0.4, 0.1, 0.3])
    proprio = np.zeros((length, 10), np.float32)
    proprio[:, :3] = pos
    proprio[:, 3:9] = [1, 0, 0, 0, 1, 0]
    proprio[:, 9] = np.linspace(0.08, 0.0, length)
    action = proprio.copy()
    action[:, :3] += [0.01, -0.005, 0.002]
    action[:, 9] = np.maximum(proprio[:, 9] - 0.004, 0)
    half = N_POINTS // 2
    cloud = np.concatenate(
        [
            obj + rng.normal(0, 0.02, (length, half, 3)),
            obj + [0.15, 0, 0] + rng.normal(0, 0.03, (length, half, 3)),
        ],
        axis=1,
    ).astype(np.float32)
    ids = np.concatenate([np.ones((length, half)), np.full((length, half), 2)], axis=1).astype(np.int32)
    scene = np.concatenate(
        [cloud[:, ::2], rng.uniform([0.2, -0.3, 0], [0.8, 0.3, 0.1], (length, half, 3))], axis=1
    )
    return {
        "proprio": proprio,
        ACTION_KEY: action.astype(np.float32),
        "object_cloud": cloud,
        "object_cloud_ids": ids,
        "scene_cloud": scene.astype(np.float32),
    }


def make_store(path: Path, episodes: int = 2, task: str = "pour", length: int = 20) -> Path:
    store = EpisodeStore(path, mode="w")
    for e in range(episodes):
        store.append_episode(synthetic_episode(e, length), {"task": task, "seed": e, "success": True})
    return path


@pytest.fixture
def tiny_store(tmp_path: Path) -> Path:
    return make_store(tmp_path / "tiny.zarr")


def observation(step: dict[str, np.ndarray], t: int) -> dict[str, np.ndarray]:
    """Step ``t`` of a synthetic episode as an environment observation."""
    return {k: v[t] for k, v in step.items() if k != ACTION_KEY}


def turned_scene(obs: dict[str, np.ndarray], theta: float, centre: np.ndarray) -> dict[str, np.ndarray]:
    """An observation with the whole scene (clouds, tcp position and rotation) turned by ``theta``
    about the vertical axis through ``centre``."""
    from keygen.geometry.rotations import yaw_matrix

    out = {k: np.array(v, copy=True) for k, v in obs.items()}
    R = yaw_matrix(theta)
    for key in ("object_cloud", "scene_cloud"):
        out[key] = ((obs[key] - centre) @ R.T + centre).astype(np.float32)
    out["proprio"][:3] = (obs["proprio"][:3] - centre) @ R.T + centre
    out["proprio"][3:6] = obs["proprio"][3:6] @ R.T
    out["proprio"][6:9] = obs["proprio"][6:9] @ R.T
    return out


@pytest.fixture
def kit() -> SimpleNamespace:
    """The helpers above for the test modules (conftest is not importable by name under pytest)."""
    return SimpleNamespace(
        NUM_KP=NUM_KP,
        FakeExtractor=FakeExtractor,
        make_store=make_store,
        observation=observation,
        synthetic_episode=synthetic_episode,
        turned_scene=turned_scene,
    )


@pytest.fixture(scope="module")
def policy_fit(load_benchmark_script):
    return load_benchmark_script("policy_fit")


@pytest.fixture(scope="module")
def yaw_frame_accuracy(load_benchmark_script):
    return load_benchmark_script("yaw_frame_accuracy")
