"""A dataset prepared for policy training: per-step features computed once, windows by index tables.

Windows follow ``keygen.data.windows.WindowSampler`` exactly (history repeats the first step,
actions past the end repeat the last one, never crossing episodes), but as two index tables over
the global steps, so a batch is a handful of numpy fancy-indexing operations.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from tqdm import tqdm

from keygen.atomic import atomic_write
from keygen.data.store import ACTION_KEY, OBJECT_CLOUD_IDS_KEY, OBJECT_CLOUD_KEY, PROPRIO_KEY, EpisodeStore
from keygen.errors import InvalidParameterError
from keygen.policies import features
from keygen.policies.checkpoint import KEYPOINTS_DIR
from keygen.policies.config import (
    HEADING_TASKS,
    YAW_ORIGINS,
    PolicyConfig,
    keypoint_categories,
    make_policy_config,
)
from keygen.policies.robot_base import episode_bases
from keygen.policies.target_frame import TARGET_FRAME_TASKS
from keygen.policies.target_token import TARGET_TOKEN_TASKS

if TYPE_CHECKING:
    from keygen.policies.training import TrainConfig
    from keygen.policies.yaw_frame import YawFrame

KEYPOINT_CACHE = "keypoint_cache.npz"
CACHE_EPISODE_ENDS = "episode_ends"  # the dataset's episode boundaries, stored beside the keypoints
# A keypoint run's inference files: its top-level JSON (train_config.json, summaries) and the
# config.json + model.safetensors of each model folder; optimizer states and scan caches stay behind.
_MODEL_FILES = ("config.json", "model.safetensors")


@dataclass
class PolicyData:
    task: str
    categories: tuple[str, ...]
    policy_config: PolicyConfig
    clouds: np.ndarray  # (S, P, 3) resampled cloud of each step
    proprio: np.ndarray  # (S, 10)
    actions: np.ndarray  # (S, 10)
    keypoints: np.ndarray | None  # (S, M, 3)
    episode_ends: np.ndarray  # (E,)
    obs_index: np.ndarray  # (S, H) global steps of each step's observation history
    action_index: np.ndarray  # (S, T) global steps of each step's action window
    targets: np.ndarray | None = None  # (S, 5) target token of each step's episode (target_token)
    bases: np.ndarray | None = None  # (S, 4) robot base in each step's episode frame (robot_base)

    def _steps(self, episodes: np.ndarray) -> np.ndarray:
        starts = np.concatenate([[0], self.episode_ends[:-1]])
        return np.concatenate(
            [np.arange(starts[e], self.episode_ends[e]) for e in episodes] or [np.zeros(0, int)]
        )

    def samples(self, episodes: np.ndarray) -> np.ndarray:
        """Global step ids (one window each) of the given episodes."""
        return self._steps(np.asarray(episodes, dtype=np.int64)).astype(np.int64)

    def fit_arrays(self, episodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Actions and proprioception (N, 10) of the episodes as the policy's normaliser sees them:
        per step in the world frame; in the object frame, every window's action and history
        positions relative to the centroid of the window's latest cloud (the policy's origin)."""
        steps = self.samples(episodes)
        if self.policy_config.frame == "world":
            return self.actions[steps], self.proprio[steps]
        origin = self.clouds[steps].mean(axis=1)[:, None]  # (N, 1, 3); obs_index[s, -1] == s
        actions = self.actions[self.action_index[steps]]  # fancy indexing: copies
        proprio = self.proprio[self.obs_index[steps]]
        actions[..., :3] -= origin
        proprio[..., :3] -= origin
        return actions.reshape(-1, actions.shape[-1]), proprio.reshape(-1, proprio.shape[-1])

    def batch(self, steps: np.ndarray) -> dict[str, torch.Tensor]:
        """Model inputs of the windows ending (observation side) at global ``steps``."""
        cfg = self.policy_config
        obs = self.obs_index[steps]  # (B, H)
        out = {
            "cloud": torch.from_numpy(
                self.clouds[obs[:, cfg.obs_horizon - cfg.cloud_frames :]]
            ),  # (B, F, P, 3)
            "proprio": torch.from_numpy(self.proprio[obs]),  # (B, H, 10)
            "action": torch.from_numpy(self.actions[self.action_index[steps]]),  # (B, T, 10)
        }
        if self.keypoints is not None:
            out["keypoints"] = torch.from_numpy(self.keypoints[obs])  # (B, H, M, 3)
        if self.targets is not None:
            out["target"] = torch.from_numpy(self.targets[steps])  # (B, 5)
        if self.bases is not None:
            out["base"] = torch.from_numpy(self.bases[steps])  # (B, 4)
        return out


def window_tables(episode_ends: np.ndarray, obs_horizon: int, horizon: int) -> tuple[np.ndarray, np.ndarray]:
    """(S, H) observation and (S, T) action step indices, clipped to each step's episode."""
    ends = np.asarray(episode_ends, dtype=np.int64)
    starts = np.concatenate([[0], ends[:-1]])
    lengths = ends - starts
    first = np.repeat(starts, lengths)  # (S,)
    last = np.repeat(ends - 1, lengths)
    now = np.arange(int(ends[-1]) if len(ends) else 0)
    obs = np.clip(now[:, None] + np.arange(-obs_horizon + 1, 1), first[:, None], last[:, None])
    act = np.clip(now[:, None] + np.arange(horizon), first[:, None], last[:, None])
    return obs, act


def dataset_task(store: EpisodeStore) -> str:
    tasks = sorted({str(m.get("task")) for m in store.all_meta()})
    if len(tasks) != 1:
        raise InvalidParameterError(f"{store.path} must hold episodes of one task, found {tasks}")
    return tasks[0]


def _fingerprint_files(directory: Path) -> str:
    h = hashlib.sha256()
    for path in sorted(directory.rglob("*")):
        if path.is_file():
            h.update(str(path.relative_to(directory)).encode())
            h.update(path.read_bytes())
    return h.hexdigest()[:16]


def _dataset_fingerprint(store: EpisodeStore, proprio: np.ndarray) -> str:
    h = hashlib.sha256(store.episode_ends.tobytes())
    h.update(np.ascontiguousarray(proprio).tobytes())
    return h.hexdigest()[:16]


def copy_keypoint_runs(
    run_dir: Path, categories: tuple[str, ...], sources: dict[str, Path] | None
) -> dict[str, Path]:
    """Copy each category's keypoint checkpoint files into ``run_dir/keypoints/<category>`` (once)."""
    out = {}
    for cat in categories:
        target = run_dir / KEYPOINTS_DIR / cat
        if not target.is_dir():
            if not sources or cat not in sources:
                raise InvalidParameterError(
                    f"this policy conditions on keypoints of {list(categories)}; missing {cat!r}. Pass "
                    + " ".join(f"--keypoints {c}=runs/kp-{c}" for c in categories)
                    + " (runs of `keygen keypoints train`)"
                )
            src = Path(sources[cat])
            if not src.is_dir():
                raise InvalidParameterError(f"keypoint run for {cat!r} not found: {src} is not a directory")
            tmp = Path(tempfile.mkdtemp(dir=run_dir, prefix=f".kp-{cat}-"))
            for path in src.rglob("*"):
                top_json = path.parent == src and path.suffix == ".json"
                if path.is_file() and (top_json or (path.name in _MODEL_FILES and path.parent.parent == src)):
                    (tmp / path.relative_to(src)).parent.mkdir(parents=True, exist_ok=True)
                    shutil.copy2(path, tmp / path.relative_to(src))
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(tmp, target)
        out[cat] = target
    return out


def _cached_keypoints(run_dir: Path, key: str, compute, episode_ends: np.ndarray) -> np.ndarray:
    """The keypoints of every dataset step, computed once per dataset + extractors (``key``). The
    cache also keeps the dataset's episode boundaries, so a run folder on its own still knows which
    steps are the objects at rest (the per-axis size frame's references)."""
    path = run_dir / KEYPOINT_CACHE
    ends = np.asarray(episode_ends, dtype=np.int64)
    keypoints = None
    if path.is_file():
        with np.load(path) as cache:
            if str(cache["fingerprint"]) == key:
                keypoints = cache["keypoints"]
                if CACHE_EPISODE_ENDS in cache.files:
                    return keypoints
    if keypoints is None:
        keypoints = compute()
    # A cache written before the boundaries were kept is rewritten with them, keypoints unchanged.
    atomic_write(
        path,
        lambda tmp: np.savez(
            tmp, keypoints=keypoints, fingerprint=np.array(key), **{CACHE_EPISODE_ENDS: ends}
        ),
    )
    return keypoints


def yaw_episode_frames(
    run_dir: Path,
    episode_ends: np.ndarray,
    num_keypoints: int,
    actions: np.ndarray,
    keypoints: np.ndarray,
    origin: str = "centroid",
) -> list[YawFrame]:
    """One keypoint yaw frame (:mod:`keygen.policies.yaw_frame`) per episode; the reference (and,
    for ``origin="grasp"``, the keypoint nearest the demonstrated grasp) is fitted on the episodes'
    first steps and written to the run for rollouts."""
    from keygen.policies import yaw_frame

    if origin not in YAW_ORIGINS:
        raise InvalidParameterError(f"yaw origin must be one of {YAW_ORIGINS}, got {origin!r}")
    ends = np.asarray(episode_ends, dtype=np.int64)
    starts = np.concatenate([[0], ends[:-1]])
    first = keypoints[starts, :num_keypoints]  # (E, K, 3) the manipulated object at rest
    reference = yaw_frame.fit_reference(first)
    anchor = None
    if origin == "grasp":
        anchor = yaw_frame.nearest_keypoint(first, yaw_frame.grasp_positions(actions, ends))
    yaw_frame.write_reference(run_dir, reference, anchor)
    return yaw_frame.episode_frames(first, reference, anchor)


def _measure_first_steps(store: EpisodeStore, measure):
    """``measure`` of the placement target's points at each episode's first step, one per episode;
    an episode whose target cannot be measured is named in the error."""
    from keygen.policies.target_frame import target_points

    out = []
    for e, a in enumerate(np.concatenate([[0], np.asarray(store.episode_ends, dtype=np.int64)[:-1]])):
        cloud = store.read(OBJECT_CLOUD_KEY, int(a), int(a) + 1)[0]
        ids = store.read(OBJECT_CLOUD_IDS_KEY, int(a), int(a) + 1)[0]
        try:
            out.append(measure(target_points(cloud, ids)))
        except InvalidParameterError as err:
            raise InvalidParameterError(f"episode {e} of {store.path}: {err}") from None
    return out


def target_episode_frames(store: EpisodeStore) -> list[YawFrame]:
    """One target yaw frame (:mod:`keygen.policies.target_frame`) per episode, measured on the
    placement target's points at the episode's first step; nothing is written to the run."""
    from keygen.policies.target_frame import measure_target_frame

    return _measure_first_steps(store, measure_target_frame)


def apply_episode_frames(
    frames: list[YawFrame],
    episode_ends: np.ndarray,
    clouds: np.ndarray,
    proprio: np.ndarray,
    actions: np.ndarray,
    keypoints: np.ndarray | None,
    targets: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Every step in its episode's frame (one per episode): new arrays, the inputs are only read.
    ``targets`` (S, 5) are target tokens (:mod:`keygen.policies.target_token`)."""
    from keygen.policies.target_token import target_in_frame

    ends = np.asarray(episode_ends, dtype=np.int64)
    out = [np.empty_like(a) for a in (clouds, proprio, actions)]
    kp_out = None if keypoints is None else np.empty_like(keypoints)
    tg_out = None if targets is None else np.empty_like(targets)
    for frame, a, b in zip(frames, np.concatenate([[0], ends[:-1]]), ends, strict=True):
        out[0][a:b] = frame.points(clouds[a:b])
        out[1][a:b] = frame.poses(proprio[a:b])
        out[2][a:b] = frame.poses(actions[a:b])
        if kp_out is not None:
            kp_out[a:b] = frame.points(keypoints[a:b])
        if tg_out is not None:
            tg_out[a:b] = target_in_frame(targets[a:b], frame)
    return out[0], out[1], out[2], kp_out, tg_out


def to_yaw_frames(
    run_dir: Path,
    episode_ends: np.ndarray,
    num_keypoints: int,
    clouds: np.ndarray,
    proprio: np.ndarray,
    actions: np.ndarray,
    keypoints: np.ndarray,
    origin: str = "centroid",
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every step in its episode's keypoint yaw frame (:func:`yaw_episode_frames`)."""
    frames = yaw_episode_frames(run_dir, episode_ends, num_keypoints, actions, keypoints, origin)
    return apply_episode_frames(frames, episode_ends, clouds, proprio, actions, keypoints)[:4]


def to_target_frames(
    store: EpisodeStore,
    clouds: np.ndarray,
    proprio: np.ndarray,
    actions: np.ndarray,
    keypoints: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Every step in its episode's target yaw frame (:func:`target_episode_frames`)."""
    frames = target_episode_frames(store)
    return apply_episode_frames(frames, store.episode_ends, clouds, proprio, actions, keypoints)[:4]


def episode_target_tokens(store: EpisodeStore) -> np.ndarray:
    """(S, 5) world-frame target token of every step: its episode's, measured on the episode's
    first observation (:mod:`keygen.policies.target_token`)."""
    from keygen.policies.target_token import TARGET_DIM, measure_target

    tokens = np.asarray(_measure_first_steps(store, measure_target), np.float32).reshape(-1, TARGET_DIM)
    lengths = np.diff(np.concatenate([[0], np.asarray(store.episode_ends, dtype=np.int64)]))
    return np.repeat(tokens, lengths, axis=0)


def load_policy_data(
    store: EpisodeStore, config: TrainConfig, run_dir: Path, progress: bool = True
) -> PolicyData:
    """Read the store, resample every step's cloud, compute (or load cached) keypoints."""
    if store.num_episodes == 0:
        raise InvalidParameterError(f"{store.path} holds no successful episodes; record demos first")
    task = dataset_task(store)
    policy_cfg = make_policy_config(config.policy, **config.policy_overrides)
    if policy_cfg.yaw_frame and policy_cfg.yaw_source == "target" and task not in TARGET_FRAME_TASKS:
        raise InvalidParameterError(
            f"the target yaw frame turns the scene by the axis of the object placed into, and the "
            f"{task!r} task's target has none the frame can measure (tasks with one: "
            f"{', '.join(TARGET_FRAME_TASKS)}); train without it"
        )
    if policy_cfg.yaw_frame and policy_cfg.yaw_source == "keypoints" and task not in HEADING_TASKS:
        raise InvalidParameterError(
            f"the yaw frame turns the scene by the manipulated object's heading, and the {task!r} task's "
            f"object has none (tasks with one: {', '.join(HEADING_TASKS)}); train without it"
        )
    if policy_cfg.target_token and task not in TARGET_TOKEN_TASKS:
        raise InvalidParameterError(
            f"the target token states where the object placed into stands, for tasks whose target has "
            f"no keypoints ({', '.join(TARGET_TOKEN_TASKS)}); the {task!r} task's has, train without it"
        )
    categories = keypoint_categories(task) if policy_cfg.use_keypoints else ()
    source = None
    if policy_cfg.use_keypoints:
        run_dir.mkdir(parents=True, exist_ok=True)
        dirs = copy_keypoint_runs(run_dir, categories, config.keypoints)
        source = features.KeypointSource(
            task, {c: features.load_extractor(d, config.device) for c, d in dirs.items()}
        )
        policy_cfg = policy_cfg.with_updates(
            num_keypoints=source.num_keypoints, num_objects=source.num_objects
        )
    s = store.num_steps
    proprio = np.asarray(store.read(PROPRIO_KEY, 0, s), dtype=np.float32)
    actions = np.asarray(store.read(ACTION_KEY, 0, s), dtype=np.float32)
    raw = store.read(features.cloud_key(policy_cfg), 0, s)
    clouds = np.stack(
        [
            features.resample_cloud(c, policy_cfg.num_points)
            for c in tqdm(raw, desc="clouds", unit="step", disable=not progress, leave=False)
        ]
    )
    keypoints = None
    if source is not None:
        objects = (
            raw if features.cloud_key(policy_cfg) == OBJECT_CLOUD_KEY else store.read(OBJECT_CLOUD_KEY, 0, s)
        )
        ids = store.read(OBJECT_CLOUD_IDS_KEY, 0, s)
        key = (
            _dataset_fingerprint(store, proprio)
            + "-"
            + "-".join(_fingerprint_files(run_dir / KEYPOINTS_DIR / c) for c in categories)
        )

        def compute() -> np.ndarray:
            with tqdm(total=s, desc="keypoints", unit="step", disable=not progress, leave=False) as bar:
                return source(objects, ids, progress=bar.update)

        keypoints = _cached_keypoints(run_dir, key, compute, store.episode_ends)
    targets = episode_target_tokens(store) if policy_cfg.target_token else None
    frames = None
    if policy_cfg.yaw_frame and policy_cfg.yaw_source == "keypoints":
        assert source is not None and keypoints is not None  # the config demands keypoints
        frames = yaw_episode_frames(
            run_dir, store.episode_ends, source.num_keypoints, actions, keypoints, policy_cfg.yaw_origin
        )
    elif policy_cfg.yaw_frame:
        frames = target_episode_frames(store)
    bases = None
    if frames is not None:
        clouds, proprio, actions, keypoints, targets = apply_episode_frames(
            frames, store.episode_ends, clouds, proprio, actions, keypoints, targets
        )
        if policy_cfg.robot_base:
            bases = episode_bases(frames, store.episode_ends)
    obs_index, action_index = window_tables(store.episode_ends, policy_cfg.obs_horizon, policy_cfg.horizon)
    return PolicyData(
        task,
        categories,
        policy_cfg,
        clouds,
        proprio,
        actions,
        keypoints,
        store.episode_ends,
        obs_index,
        action_index,
        targets,
        bases,
    )
