"""Running the expert over many episodes: evaluation without recording, and recorded demonstrations.

Episode ``k`` of a run uses object ``object_ids[k % len(object_ids)]`` and the seed
``SeedSequence([seed, k])``, so a run is reproducible and a resumed run continues with new seeds.
Workers are processes; each builds its own environment and returns finished episodes to the parent,
which alone writes the store (single writer), one atomic append per episode.
"""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from keygen.errors import InvalidParameterError

ENV_DEFAULTS = {"image_size": 128, "num_points": 1024, "include_rgb": True}


@dataclass(frozen=True)
class RunSpec:
    task: str
    split: str
    object_ids: tuple[int, ...]
    setting: str
    scale: float
    seed: int
    record: bool
    env_kwargs: tuple[tuple[str, Any], ...] = ()
    expert_options: tuple[tuple[str, Any], ...] = ()  # keyword arguments of the task's expert

    def episode(self, k: int) -> tuple[int, int]:
        """(object id, env seed) of episode ``k``."""
        seed = int(np.random.SeedSequence([self.seed, k]).generate_state(1)[0])
        return self.object_ids[k % len(self.object_ids)], seed


_ENVS: dict[tuple, Any] = {}


def _env_for(spec: RunSpec, object_id: int):
    import gymnasium as gym

    import keygen

    key = (spec.task, spec.split, object_id, spec.setting, spec.scale, spec.env_kwargs)
    if key not in _ENVS:
        _ENVS.clear()  # one env at a time per process: each holds a renderer
        _ENVS[key] = gym.make(
            keygen.ENV_IDS[spec.task],
            object_split=spec.split,
            object_id=object_id,
            setting=spec.setting,
            scale=spec.scale,
            **dict(spec.env_kwargs),
        ).unwrapped
    return _ENVS[key]


_RECORDER: dict[str, Any] = {}  # this process's EpisodeWriter, created on first use


def run_one(args: tuple[RunSpec, int]) -> tuple[dict, dict | None]:
    """Run episode ``k``; returns its result (JSON-able) and, when recording, its stacked steps."""
    from keygen.data.store import EpisodeWriter
    from keygen.expert.runner import make_expert, run_episode

    spec, k = args
    object_id, seed = spec.episode(k)
    env = _env_for(spec, object_id)
    steps = None
    if spec.record:
        # No store: the caller writes. One writer per process, its arrays reused episode after
        # episode (see EpisodeWriter's reuse_buffers), so the returned steps are views that the
        # next episode overwrites: a worker's result is pickled at once, and in-process callers
        # consume each episode before asking for the next (iterate_episodes).
        if "writer" not in _RECORDER:
            _RECORDER["writer"] = EpisodeWriter(reuse_buffers=True)
        buffer = _RECORDER["writer"]
        buffer.discard()
        result = run_episode(
            env,
            make_expert(spec.task, **dict(spec.expert_options)),
            seed,
            on_step=lambda obs, action, info: buffer.add(obs, action, info["anchors"]),
        )
        steps = buffer.stacked()
    else:
        result = run_episode(env, make_expert(spec.task, **dict(spec.expert_options)), seed)
    meta = result.to_json() | {"episode_index": k, "objects": env.task.object_ids()}
    if spec.expert_options:
        meta["expert_options"] = dict(spec.expert_options)
    return meta, steps


def iterate_episodes(spec: RunSpec, indices: list[int], workers: int) -> Iterator[tuple[dict, dict | None]]:
    """Results in completion order (unordered with several workers).

    With ``workers == 1`` a recorded episode's step arrays are reused by the next episode: store
    them (``EpisodeStore.append_episode``) or copy them before advancing the iterator.
    """
    if workers < 1:
        raise InvalidParameterError(f"--workers must be >= 1, got {workers}")
    jobs = [(spec, k) for k in indices]
    if workers == 1:
        for job in jobs:
            yield run_one(job)
        return
    ctx = mp.get_context("spawn")  # a fresh process per worker: no inherited GL contexts
    with ctx.Pool(workers) as pool:
        yield from pool.imap_unordered(run_one, jobs)
