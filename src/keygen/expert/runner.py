"""Running an expert in an environment: one episode, with an optional per-step callback."""

from __future__ import annotations

import importlib
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from keygen.errors import InvalidParameterError
from keygen.expert.base import Expert

EXPERTS = {
    "pour": "keygen.expert.pour:PourExpert",
    "knife": "keygen.expert.knife:KnifeExpert",
    "stack": "keygen.expert.stack:StackExpert",
}


def make_expert(task: str, **options: Any) -> Expert:
    """The task's scripted expert; ``options`` go to its constructor (e.g. ``grasp`` for pour)."""
    if task not in EXPERTS:
        raise InvalidParameterError(f"task must be one of {sorted(EXPERTS)}, got {task!r}")
    module, name = EXPERTS[task].split(":")
    return getattr(importlib.import_module(module), name)(**options)


@dataclass
class EpisodeResult:
    task: str
    split: str
    object_id: int
    setting: str
    scale: float
    seed: int
    success: bool
    failure: str | None
    steps: int
    seconds: float
    metrics: dict[str, float] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["metrics"] = {k: float(v) for k, v in self.metrics.items()}
        return d


def run_episode(
    env,
    expert: Expert,
    seed: int,
    on_step: Callable[[dict, np.ndarray, dict], None] | None = None,
    hold_steps: int = 12,
) -> EpisodeResult:
    """Reset with ``seed`` and let ``expert`` act until the episode ends.

    ``on_step(obs, action, info)`` is called with the observation each action was chosen from
    (for recording demonstrations). When the script finishes before the episode ends, its last
    target is held for up to ``hold_steps`` more steps so settling-based success can register.
    """
    env = getattr(env, "unwrapped", env)  # the episode's settings live on the base env
    t0 = time.perf_counter()
    obs, info = env.reset(seed=seed)
    expert.reset(env, obs, info)
    steps, last, held = 0, None, 0
    terminated = truncated = False
    while not (terminated or truncated):
        action = expert.act(obs, info)
        if action is None:
            if expert.failure is not None or last is None or held >= hold_steps:
                break
            action, held = last, held + 1
        if on_step is not None:
            on_step(obs, action, info)
        obs, _, terminated, truncated, info = env.step(action)
        last, steps = action, steps + 1
    failure = None if info["success"] else (expert.failure or info.get("failure") or "not_achieved")
    return EpisodeResult(
        task=env.task_name,
        split=env.object_split,
        object_id=env.object_id,
        setting=env.setting,
        scale=env.scale,
        seed=int(seed),
        success=bool(info["success"]),
        failure=failure,
        steps=steps,
        seconds=round(time.perf_counter() - t0, 3),
        metrics=dict(info.get("metrics", {})),
    )
