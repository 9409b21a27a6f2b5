"""Observations -> model inputs: resampled clouds, keypoints per task object, proprioception.

Per step (a dataset step or an environment observation):

- ``object`` cloud: the task objects' points (``object_cloud``: every label is a task object) and
  ``scene`` cloud: the workspace crop, each resampled to the model's point count by deterministic
  farthest-point sampling (same input, same output; fewer points are repeated cyclically);
- keypoints: for each keypointed object of the task (:data:`TASK_KEYPOINT_OBJECTS`), its points
  (by label) through that category's extractor; (M, 3) world frame, object-major
  (slot s, keypoint k at row s * K + k). An object seen by fewer than :data:`MIN_OBJECT_POINTS`
  points (occluded, out of view) falls back to the whole object cloud, so the shapes stay fixed;
- proprioception (10,).

Windows add the observation history; :func:`window_inputs` turns a ``WindowSampler`` batch into the
model's input dict without modifying it.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from keygen.data.store import OBJECT_CLOUD_IDS_KEY, OBJECT_CLOUD_KEY, PROPRIO_KEY, SCENE_CLOUD_KEY
from keygen.errors import InvalidParameterError, KeyGenError
from keygen.geometry.clouds import farthest_point_sample
from keygen.policies.config import TASK_KEYPOINT_OBJECTS, PolicyConfig, keypoint_categories

MIN_OBJECT_POINTS = 16
EXTRACT_CHUNK = 256  # clouds per extractor call when precomputing a dataset's keypoints


class Extractor(Protocol):
    """What features need of ``keygen.keypoints.extractor.KeypointExtractor``."""

    category: str
    num_keypoints: int

    def batch(self, clouds: list[np.ndarray]) -> Any: ...  # .keypoints (B, K, 3)


def load_extractor(run_dir: str | Path, device: str = "cpu") -> Extractor:
    """Load a ``keygen keypoints train`` run (indirection so tests can substitute a fake)."""
    from keygen.keypoints.extractor import KeypointExtractor

    return KeypointExtractor.load(run_dir, device=device)


def cloud_key(config: PolicyConfig) -> str:
    return OBJECT_CLOUD_KEY if config.cloud_source == "object" else SCENE_CLOUD_KEY


def resample_cloud(points: np.ndarray, n: int) -> np.ndarray:
    """(N, 3) -> (n, 3) float32 by deterministic farthest-point sampling (cyclic repeat if N < n)."""
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise InvalidParameterError(f"a cloud must be (N, 3) with N >= 1, got {points.shape}")
    if len(points) == n:
        return points.copy()
    return farthest_point_sample(points, n, start_index=0, method="fast").astype(np.float32)


def object_points(cloud: np.ndarray, ids: np.ndarray, label: int) -> np.ndarray:
    """The points of one object (by label), or the whole cloud when it is (almost) unseen."""
    part = cloud[ids == label]
    return part if len(part) >= MIN_OBJECT_POINTS else cloud


class KeypointSource:
    """The keypoint extractors of a task's objects: clouds (+ labels) -> (M, 3) world keypoints."""

    def __init__(self, task: str, extractors: Mapping[str, Extractor]):
        needed = keypoint_categories(task)
        missing = [c for c in needed if c not in extractors]
        if missing:
            raise InvalidParameterError(
                f"task {task!r} needs keypoint extractors for {list(needed)}; missing {missing}. Train them "
                f"with `keygen keypoints train` and pass e.g. --keypoints {needed[0]}=runs/kp-{needed[0]}"
            )
        self.task = task
        self.objects = TASK_KEYPOINT_OBJECTS[task]
        self.extractors = {c: extractors[c] for c in needed}
        counts = {c: int(e.num_keypoints) for c, e in self.extractors.items()}
        if len(set(counts.values())) != 1:
            raise InvalidParameterError(f"the task's extractors must share a keypoint count, got {counts}")
        self.num_keypoints = next(iter(counts.values()))
        self.num_objects = len(self.objects)

    @property
    def num_tokens(self) -> int:
        return self.num_keypoints * self.num_objects

    def __call__(
        self, clouds: np.ndarray, ids: np.ndarray, progress: Callable[[int], Any] | None = None
    ) -> np.ndarray:
        """(S, N, 3) clouds and (S, N) labels -> (S, M, 3) float32 keypoints, batched per extractor."""
        clouds, ids = np.asarray(clouds), np.asarray(ids)
        if clouds.ndim != 3 or ids.shape != clouds.shape[:2]:
            raise InvalidParameterError(
                f"clouds must be (S, N, 3) with ids (S, N); got {clouds.shape}, {ids.shape}"
            )
        s, k = len(clouds), self.num_keypoints
        out = np.zeros((s, self.num_tokens, 3), np.float32)
        for start in range(0, s, EXTRACT_CHUNK):
            stop = min(s, start + EXTRACT_CHUNK)
            for slot, (category, label) in enumerate(self.objects):
                parts = [object_points(clouds[i], ids[i], label) for i in range(start, stop)]
                kp = np.asarray(self.extractors[category].batch(parts).keypoints, dtype=np.float32)
                if kp.shape != (stop - start, k, 3):
                    raise KeyGenError(
                        f"the {category} extractor returned keypoints {kp.shape}, "
                        f"expected {(stop - start, k, 3)}"
                    )
                out[start:stop, slot * k : (slot + 1) * k] = kp
            if progress is not None:
                progress(stop - start)
        return out


def step_features(
    obs: Mapping[str, np.ndarray], config: PolicyConfig, keypoints: KeypointSource | None
) -> dict[str, np.ndarray]:
    """One observation (env or dataset step) -> ``cloud`` (P, 3), ``proprio`` (10,), ``keypoints`` (M, 3)."""
    return steps_features([obs], config, keypoints)[0]


def steps_features(
    observations: Sequence[Mapping[str, np.ndarray]], config: PolicyConfig, keypoints: KeypointSource | None
) -> list[dict[str, np.ndarray]]:
    """:func:`step_features` of several observations, with one extractor call per object for all."""
    needed = [cloud_key(config), PROPRIO_KEY]
    if config.use_keypoints:
        if keypoints is None:
            raise InvalidParameterError(f"policy {config.name!r} uses keypoints; give it a KeypointSource")
        needed += [OBJECT_CLOUD_KEY, OBJECT_CLOUD_IDS_KEY]
    for obs in observations:
        for key in needed:
            if key not in obs:
                raise InvalidParameterError(
                    f"policy {config.name!r} needs observation key {key!r}; got {sorted(obs)}"
                )
    out = [
        {
            "cloud": resample_cloud(obs[cloud_key(config)], config.num_points),
            "proprio": np.asarray(obs[PROPRIO_KEY], dtype=np.float32).copy(),
        }
        for obs in observations
    ]
    if config.use_keypoints and observations:
        kp = keypoints(
            np.stack([np.asarray(o[OBJECT_CLOUD_KEY]) for o in observations]),
            np.stack([np.asarray(o[OBJECT_CLOUD_IDS_KEY]) for o in observations]),
        )  # (S, M, 3)
        for feats, row in zip(out, kp, strict=True):
            feats["keypoints"] = row
    return out


def stack_history(
    frames: Sequence[Mapping[str, np.ndarray]], config: PolicyConfig
) -> dict[str, torch.Tensor]:
    """H per-step feature dicts (oldest first) -> a batch of one: the model's input dict."""
    if len(frames) != config.obs_horizon:
        raise InvalidParameterError(f"need {config.obs_horizon} frames of history, got {len(frames)}")
    out = {
        "cloud": torch.from_numpy(np.stack([f["cloud"] for f in frames[-config.cloud_frames :]]))[None],
        "proprio": torch.from_numpy(np.stack([f["proprio"] for f in frames]))[None],
    }
    if config.use_keypoints:
        out["keypoints"] = torch.from_numpy(np.stack([f["keypoints"] for f in frames]))[None]
    return out


def window_inputs(
    batch: Mapping[str, np.ndarray],
    config: PolicyConfig,
    keypoints: np.ndarray | KeypointSource | None = None,
) -> dict[str, torch.Tensor]:
    """A ``WindowSampler.batch`` (keys: the cloud key, ``proprio``, ``action``, and for keypoints
    ``object_cloud`` + ``object_cloud_ids``) -> model inputs. ``keypoints`` is either precomputed
    (B, H, M, 3) or a source run here. The batch is only read."""
    b, h = batch[PROPRIO_KEY].shape[:2]
    clouds = np.asarray(batch[cloud_key(config)])[:, h - config.cloud_frames :]  # (B, F, N, 3)
    resampled = np.stack([[resample_cloud(c, config.num_points) for c in row] for row in clouds])
    out = {
        "cloud": torch.from_numpy(resampled),  # (B, F, P, 3)
        "proprio": torch.as_tensor(np.asarray(batch[PROPRIO_KEY], dtype=np.float32)).clone(),
    }
    if "action" in batch:
        out["action"] = torch.as_tensor(np.asarray(batch["action"], dtype=np.float32)).clone()
    if config.use_keypoints:
        if isinstance(keypoints, KeypointSource):
            flat_c = np.asarray(batch[OBJECT_CLOUD_KEY]).reshape(b * h, *batch[OBJECT_CLOUD_KEY].shape[2:])
            flat_i = np.asarray(batch[OBJECT_CLOUD_IDS_KEY]).reshape(b * h, -1)
            keypoints = keypoints(flat_c, flat_i).reshape(b, h, -1, 3)
        if keypoints is None:
            raise InvalidParameterError(
                f"policy {config.name!r} uses keypoints; pass them or a KeypointSource"
            )
        out["keypoints"] = torch.as_tensor(np.asarray(keypoints, dtype=np.float32)).clone()
    return out
