"""One policy episode in an environment: reset with a fixed seed, act until the episode ends.

The episode seed is a pure function of ``(seed, object_id, k)``, so episode ``k`` on an object is the
same scene for every policy and every rerun: policies are compared on identical layouts, and a resumed
evaluation continues with exactly the episodes it had not finished. The policy is anything with
``reset()``, ``act(obs) -> (10,) action`` and (optionally) ``last_keypoints`` (M, 3) in the world frame,
drawn into the video frames when present.
"""

from __future__ import annotations

import inspect
import time
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from keygen.errors import InvalidParameterError
from keygen.sim import PHYSICS_VERSION

# Colours of the drawn keypoints, cycled (RGB): distinct hues so a keypoint can be followed over time.
KEYPOINT_COLOURS = np.array(
    [
        [255, 64, 64],
        [64, 220, 64],
        [64, 128, 255],
        [255, 200, 0],
        [255, 0, 255],
        [0, 230, 230],
        [255, 128, 0],
        [160, 80, 255],
    ],
    dtype=np.uint8,
)


class Policy(Protocol):
    def reset(self) -> None: ...  # may take ``seed=`` (the episode seed) for its sampling noise

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray: ...


@dataclass(frozen=True)
class EnvSpec:
    """How to build an evaluation environment; must match what the demonstrations were recorded with."""

    task: str
    split: str
    setting: str
    scale: float = 1.0
    image_size: int = 128
    num_points: int = 1024
    max_steps: int | None = None  # None: the task's own time limit

    def __post_init__(self) -> None:
        from keygen.objects.splits import SPLITS
        from keygen.sim.env import TASKS
        from keygen.sim.tasks.base import SETTINGS

        if self.task not in TASKS:
            raise InvalidParameterError(f"task must be one of {sorted(TASKS)}, got {self.task!r}")
        if self.split not in SPLITS:
            raise InvalidParameterError(f"split must be one of {SPLITS}, got {self.split!r}")
        if self.setting not in SETTINGS:
            raise InvalidParameterError(f"setting must be one of {SETTINGS}, got {self.setting!r}")
        if self.image_size < 16 or self.num_points < 16:
            raise InvalidParameterError(
                f"image_size and num_points must be >= 16, got {self.image_size} and {self.num_points}"
            )
        if self.max_steps is not None and self.max_steps < 1:
            raise InvalidParameterError(f"max_steps must be >= 1 or None, got {self.max_steps}")


def episode_seed(seed: int, object_id: int, k: int) -> int:
    """The environment seed of episode ``k`` on ``object_id`` of an evaluation seeded ``seed``."""
    if min(seed, object_id, k) < 0:
        raise InvalidParameterError(f"seed, object id and episode must be >= 0, got {seed}, {object_id}, {k}")
    return int(np.random.SeedSequence([int(seed), int(object_id), int(k)]).generate_state(1)[0])


def make_env(spec: EnvSpec, object_id: int, include_rgb: bool = False):
    """The unwrapped ``KeyGenEnv`` for one object (RGB only when a video is recorded)."""
    import gymnasium as gym

    import keygen

    env = gym.make(
        keygen.ENV_IDS[spec.task],
        object_split=spec.split,
        object_id=int(object_id),
        setting=spec.setting,
        scale=spec.scale,
        image_size=spec.image_size,
        num_points=spec.num_points,
        include_rgb=include_rgb,
    ).unwrapped
    if spec.max_steps is not None:
        env.max_steps = int(spec.max_steps)  # a shorter time limit for smoke tests only
    return env


def project_keypoints(
    keypoints: np.ndarray, intrinsics: np.ndarray, extrinsics: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World points (M, 3) -> pixels (V, M, 2) as (u, v) and a visibility mask (V, M) per view.

    ``extrinsics`` are camera-to-world (V, 4, 4) in the OpenCV convention, as in the observation.
    """
    from keygen.geometry.cameras import project_points

    pts = np.asarray(keypoints, dtype=np.float64).reshape(-1, 3)  # (M, 3)
    world_to_cam = np.linalg.inv(np.asarray(extrinsics, dtype=np.float64))  # (V, 4, 4)
    cam = np.einsum("vij,mj->vmi", world_to_cam[:, :3, :3], pts) + world_to_cam[:, None, :3, 3]  # (V, M, 3)
    pixels = np.stack([project_points(cam[v], intrinsics[v])[0] for v in range(len(cam))])  # (V, M, 2)
    visible = (cam[..., 2] > 0) & np.all(np.isfinite(pixels), axis=-1)  # (V, M)
    return pixels, visible


def draw_keypoints(rgb: np.ndarray, keypoints: np.ndarray | None, obs: dict[str, np.ndarray]) -> np.ndarray:
    """(V, H, W, 3) views with ``keypoints`` (M, 3, world) drawn as small squares; a copy."""
    out = np.array(rgb, dtype=np.uint8, copy=True)
    if keypoints is None or len(keypoints) == 0:
        return out
    v, h, w = out.shape[:3]
    radius = max(1, h // 40)
    pixels, visible = project_keypoints(keypoints, obs["intrinsics"], obs["extrinsics"])
    for view in range(v):
        for m in np.flatnonzero(visible[view]):
            u, r = int(round(pixels[view, m, 0])), int(round(pixels[view, m, 1]))
            if 0 <= u < w and 0 <= r < h:
                r0, r1, u0, u1 = (
                    max(0, r - radius),
                    min(h, r + radius + 1),
                    max(0, u - radius),
                    min(w, u + radius + 1),
                )
                out[view, r0:r1, u0:u1] = KEYPOINT_COLOURS[m % len(KEYPOINT_COLOURS)]
    return out


def run_policy_episode(
    env,
    policy: Policy,
    seed: int,
    *,
    policy_name: str = "",
    episode: int = 0,
    record_video: bool = False,
) -> tuple[dict[str, Any], list[np.ndarray] | None]:
    """Reset ``env`` with ``seed``, let ``policy`` act until terminated or truncated.

    Returns the result (JSON-able: task, policy, split, setting, scale, object_id, episode, seed, success,
    failure, steps, seconds) and, with ``record_video``, one tiled frame per observation with the policy's
    keypoints drawn. A non-finite action ends the episode as the failure ``invalid_action`` instead of
    stopping the evaluation: a policy that diverges has failed that episode.
    """
    from keygen.sim.cameras import tile_views

    env = getattr(env, "unwrapped", env)
    if record_video and not getattr(env, "include_rgb", False):
        raise InvalidParameterError("record_video needs an env built with include_rgb=True")
    t0 = time.perf_counter()
    obs, info = env.reset(seed=int(seed))
    if "seed" in inspect.signature(policy.reset).parameters:
        policy.reset(seed=int(seed))  # the sampling noise too: a rerun repeats the episode exactly
    else:
        policy.reset()
    frames: list[np.ndarray] | None = [] if record_video else None
    steps, terminated, truncated, failure = 0, False, False, None
    while not (terminated or truncated):
        action = np.asarray(policy.act(obs), dtype=np.float64)  # (10,)
        if frames is not None:
            frames.append(
                tile_views(draw_keypoints(obs["rgb"], getattr(policy, "last_keypoints", None), obs))
            )
        if action.shape != (10,) or not np.all(np.isfinite(action)):
            failure = "invalid_action"
            break
        obs, _, terminated, truncated, info = env.step(action)
        steps += 1
    if frames is not None and failure is None:
        frames.append(tile_views(draw_keypoints(obs["rgb"], getattr(policy, "last_keypoints", None), obs)))
    success = bool(info["success"]) and failure is None
    if not success and failure is None:
        failure = info.get("failure") or ("timeout" if truncated else "not_achieved")
    result = {
        "task": env.task_name,
        "policy": policy_name,
        "split": env.object_split,
        "setting": env.setting,
        "scale": float(env.scale),
        "object_id": int(env.object_id),
        "episode": int(episode),
        "seed": int(seed),
        "success": success,
        "failure": None if success else failure,
        "steps": steps,
        "seconds": round(time.perf_counter() - t0, 3),
        "metrics": {k: float(v) for k, v in info.get("metrics", {}).items()},
        "physics": PHYSICS_VERSION,
    }
    return result, frames
