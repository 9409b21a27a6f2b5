"""Evaluate a trained policy: rollouts over objects x episodes, appended to JSONL as they finish.

Episode ``k`` on object ``o`` uses the seed ``episode_seed(seed, o, k)``. Each finished episode is one
JSON line (written by the parent process alone, flushed and fsynced), so an interrupted evaluation loses
only the episodes in flight, and a rerun with the same arguments skips every episode already in the file.
Workers are spawned processes (no inherited GL contexts); each loads the policy once and builds its own
environments. The environment is built with the image size and point count of the policy's
demonstrations, read from the episode store named in the run's ``config.json``.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

from keygen.errors import InvalidParameterError, KeyGenError
from keygen.evaluation.rollout import EnvSpec, episode_seed, make_env, run_policy_episode
from keygen.sim import PHYSICS_VERSION

# ``size_normalize`` -> the size frame it asks for (keygen.policies.size_frame.SIZE_MODES, repeated
# here because that module imports torch and this one must not).
SIZE_FRAMES = {None: None, False: None, True: "uniform", "uniform": "uniform", "axes": "axes"}
RESULT_KEY = ("task", "policy", "split", "setting", "scale", "object_id", "episode", "seed")


class RunDirError(KeyGenError):
    """A policy run directory lacks what evaluation needs (config.json, its dataset)."""


@dataclass(frozen=True)
class RunInfo:
    """What evaluation needs to know about a trained policy run."""

    run_dir: str
    task: str
    policy: str
    image_size: int
    num_points: int
    train_split: str
    train_object_ids: tuple[int, ...]


def _lookup(cfg: dict[str, Any], key: str) -> Any:
    """``key`` at the top of a run config or in its ``train`` / ``policy`` sections.

    The trainer nests the dataset under ``train`` and sizes under ``policy``; runs written by hand (or by
    other trainers) may keep everything at the top level.
    """
    for section in (cfg, cfg.get("train"), cfg.get("policy")):
        if isinstance(section, dict) and section.get(key) is not None:
            return section[key]
    return None


def read_run_info(run_dir: str | os.PathLike) -> RunInfo:
    """Task, policy, observation sizes and training objects of a run, from its config and dataset."""
    from keygen.data.store import EpisodeStore

    run_dir = Path(run_dir)
    cfg_path = run_dir / "config.json"
    if not cfg_path.is_file():
        if (run_dir / "train_config.json").is_file():  # the layout of a keypoint run
            raise RunDirError(
                f"{run_dir} is a keypoint run, not a policy run; score it with "
                f"`keygen keypoints eval {run_dir} --split test`, or pass it to a policy with "
                "`keygen train --keypoints CATEGORY=DIR`"
            )
        raise RunDirError(
            f"{run_dir} has no config.json; expected a policy run directory written by the trainer "
            "(train one with `keygen train` or `keygen benchmark`)"
        )
    try:
        cfg = json.loads(cfg_path.read_text())
    except json.JSONDecodeError as exc:
        raise RunDirError(f"{cfg_path} is not valid JSON ({exc}); retrain or restore it") from exc
    if not isinstance(cfg, dict):
        raise RunDirError(f"{cfg_path} holds a {type(cfg).__name__}, not a run config object")
    policy = _lookup(cfg, "policy") or _lookup(cfg, "policy_name")
    if isinstance(policy, dict):  # a nested policy config: its name
        policy = policy.get("name")
    task, size, points, split, ids = _lookup(cfg, "task"), None, None, "policy", (0,)
    dataset = _lookup(cfg, "dataset")
    if dataset is not None:
        path = Path(dataset) if Path(dataset).is_absolute() or Path(dataset).exists() else run_dir / dataset
        if not path.exists():
            raise RunDirError(f"{cfg_path} names the dataset {dataset}, which does not exist; restore it")
        # The episodes the run saw: with --max-episodes, its seen objects are those of the first N.
        store = EpisodeStore(path, mode="r", max_episodes=_lookup(cfg, "max_episodes"))
        if store.num_episodes == 0:
            raise RunDirError(f"dataset {path} holds no episodes")
        metas = store.all_meta()
        task = metas[0].get("task", task)
        split = metas[0].get("split", split)
        ids = tuple(sorted({int(m["object_id"]) for m in metas if "object_id" in m})) or ids
        size = store.step_shape("depth")[-1]  # (V, H, W): square views
        points = store.step_shape("object_cloud")[0]  # (N, 3)
    size = size or _lookup(cfg, "image_size")
    points = points or _lookup(cfg, "num_points")
    missing = [
        n
        for n, v in (("task", task), ("policy", policy), ("image_size", size), ("num_points", points))
        if not v
    ]
    if missing:
        raise RunDirError(f"cannot tell the {', '.join(missing)} of the run in {run_dir} from {cfg_path}")
    return RunInfo(str(run_dir), str(task), str(policy), int(size), int(points), str(split), ids)


def load_results(path: str | os.PathLike) -> dict[tuple, dict]:
    """Results already in a JSONL file, keyed by :data:`RESULT_KEY`; a torn last line is ignored, and so
    are rows of another physics revision (:data:`keygen.sim.PHYSICS_VERSION`)."""
    path = Path(path)
    out: dict[tuple, dict] = {}
    if not path.exists():
        return out
    for line in path.read_text().splitlines():
        try:
            row = json.loads(line)
            key = tuple(row[k] for k in RESULT_KEY)
        except (json.JSONDecodeError, KeyError, TypeError):
            continue  # a line cut by an interruption: that episode simply runs again
        # An episode measured under another physics revision (rows before revision 2 carry none) is
        # not a result of this simulator: it runs again, and its new row supersedes the old one.
        if row.get("physics", 1) == PHYSICS_VERSION:
            out[key] = row
    return out


def _append(path: Path, row: dict) -> None:
    with path.open("a+b") as f:
        if f.tell() > 0:
            f.seek(-1, os.SEEK_END)
            if f.read(1) != b"\n":  # the previous run died mid-line: start a fresh one
                f.write(b"\n")
        f.write((json.dumps(row) + "\n").encode())
        f.flush()
        os.fsync(f.fileno())


def load_policy_runner(
    run_dir: str,
    num_inference_steps: int | None = None,
    execute_steps: int | None = None,
    size_normalize: bool | str = False,
    samples: int = 1,
):
    """The default runner factory: the trained policy with perception and keypoints in the loop."""
    from keygen.policies.runtime import load_runner

    return load_runner(
        run_dir,
        device="cpu",
        num_inference_steps=num_inference_steps,
        execute_steps=execute_steps,
        size_normalize=size_normalize,
        samples=samples,
    )


@dataclass(frozen=True)
class _Job:
    run_dir: str
    policy: str
    spec: EnvSpec
    object_id: int
    episode: int
    seed: int
    video: str | None
    runner_factory: Callable[[str], Any]


_CACHE: dict[str, Any] = {}


def _run_job(job: _Job) -> dict:
    """One episode (in a worker or in-process); runner and env are cached per process."""
    runner_key = (job.run_dir, job.runner_factory)
    if _CACHE.get("runner_key") != runner_key:
        _CACHE["runner"], _CACHE["runner_key"] = job.runner_factory(job.run_dir), runner_key
    env_key = (job.spec, job.object_id, job.video is not None)
    if _CACHE.get("env_key") != env_key:
        if _CACHE.get("env") is not None:
            _CACHE["env"].close()  # one env per process: each holds a renderer
        _CACHE["env"], _CACHE["env_key"] = make_env(job.spec, job.object_id, job.video is not None), env_key
    result, frames = run_policy_episode(
        _CACHE["env"],
        _CACHE["runner"],
        job.seed,
        policy_name=job.policy,
        episode=job.episode,
        record_video=job.video is not None,
    )
    if frames:
        import imageio.v2 as imageio

        Path(job.video).parent.mkdir(parents=True, exist_ok=True)
        imageio.mimsave(job.video, frames, fps=10, macro_block_size=1)
        result["video"] = job.video
    return result


def _release() -> None:
    """Drop this process's cached runner and env (its renderer) once an evaluation is over."""
    if _CACHE.get("env") is not None:
        _CACHE["env"].close()
    _CACHE.clear()


def _init_worker(threads: int) -> None:
    # One intra-op thread per worker, as in-process (_one_thread): the float reduction order of a
    # policy query depends on the thread count, and in a closed loop that flips episodes (7 of 24
    # pour episodes changed outcome between 1 and 2 threads), so a result must not depend on the
    # machine's core count. The variables cover a torch imported later; a user's main module,
    # re-imported by spawn before this initializer runs, may have imported torch already.
    os.environ["OMP_NUM_THREADS"] = str(threads)
    os.environ["MKL_NUM_THREADS"] = str(threads)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(threads)


@contextmanager
def _one_thread() -> Iterator[None]:
    """One torch thread while rolling out in-process, as in the workers: a batch-1 policy query gains
    little from intra-op threads, and on a busy machine their spinning slows the renderer and physics."""
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def _iterate(jobs: list[_Job], workers: int) -> Iterator[dict]:
    workers = min(workers, len(jobs))  # a pool for a single episode costs more than it saves
    if workers <= 1:
        with _one_thread():
            for job in jobs:
                yield _run_job(job)
        return
    with mp.get_context("spawn").Pool(workers, initializer=_init_worker, initargs=(1,)) as pool:
        yield from pool.imap_unordered(_run_job, jobs)


def evaluate(
    run_dir: str | os.PathLike,
    split: str,
    setting: str,
    episodes_per_object: int,
    seed: int,
    workers: int,
    out_jsonl: str | os.PathLike,
    object_ids: list[int] | tuple[int, ...] | None = None,
    scale: float = 1.0,
    videos: int = 0,
    *,
    runner_factory: Callable[[str], Any] | None = None,
    num_inference_steps: int | None = None,
    execute_steps: int | None = None,
    size_normalize: bool | str = False,
    samples: int = 1,
    max_steps: int | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Roll out the policy of ``run_dir`` and return the summary (episodes, success_rate, ci95, by_object).

    ``split`` is ``train``, ``test``, ``policy`` or ``seen`` (the run's own training objects). Object ids
    default to every instance of the split. ``videos`` records the first that many episodes (in run
    order) next to ``out_jsonl``. ``runner_factory(run_dir) -> policy`` replaces the trained policy
    (tests); it must be picklable when ``workers > 1``. ``num_inference_steps`` and ``execute_steps``
    (actions run per prediction, 1 to the horizon; the horizon is whole-trajectory mode) override the
    run's; ``size_normalize`` runs every episode in the keypoint-measured size frame
    (:mod:`keygen.policies.size_frame`): ``True`` or ``"uniform"`` one scale, ``"axes"`` width and
    height apart. ``samples`` > 1 draws that many trajectories per query and runs the one that agrees
    best with the previous plan (:mod:`keygen.policies.coherence`). Pass a separate ``out_jsonl`` per
    setting, as finished episodes are looked up there.
    """
    from tqdm import tqdm

    from keygen.evaluation.stats import summarize
    from keygen.objects.splits import SPLIT_SIZES
    from keygen.policies.coherence import check_samples

    if episodes_per_object < 1:
        raise InvalidParameterError(f"episodes_per_object must be >= 1, got {episodes_per_object}")
    if workers < 1:
        raise InvalidParameterError(f"workers must be >= 1, got {workers}")
    if videos < 0:
        raise InvalidParameterError(f"videos must be >= 0, got {videos}")
    check_samples(samples)
    if size_normalize not in SIZE_FRAMES:
        raise InvalidParameterError(
            f"size_normalize must be False, True, 'uniform' or 'axes', got {size_normalize!r}"
        )
    size_frame = SIZE_FRAMES[size_normalize]
    info = read_run_info(run_dir)
    if split == "seen":
        split, default_ids = info.train_split, info.train_object_ids
    elif split in SPLIT_SIZES:
        default_ids = tuple(range(SPLIT_SIZES[split]))
    else:
        raise InvalidParameterError(f"split must be one of {[*SPLIT_SIZES, 'seen']}, got {split!r}")
    ids = tuple(int(i) for i in (default_ids if object_ids is None else object_ids))
    if not ids or min(ids) < 0:
        raise InvalidParameterError(f"object ids must be a non-empty list of ids >= 0, got {object_ids}")
    spec = EnvSpec(info.task, split, setting, float(scale), info.image_size, info.num_points, max_steps)
    if execute_steps is not None and (not isinstance(execute_steps, int) or execute_steps < 1):
        raise InvalidParameterError(f"execute_steps must be an int >= 1, got {execute_steps!r}")
    factory = runner_factory or partial(
        load_policy_runner,
        num_inference_steps=num_inference_steps,
        execute_steps=execute_steps,
        size_normalize=size_normalize,
        samples=samples,
    )

    out_jsonl = Path(out_jsonl)
    out_jsonl.parent.mkdir(parents=True, exist_ok=True)
    video_dir = out_jsonl.parent / f"{out_jsonl.stem}_videos"
    # Episode-major order: an interrupted run has covered every object about equally.
    order = [(o, k) for k in range(episodes_per_object) for o in ids]
    jobs = []
    for n, (o, k) in enumerate(order):
        video = str(video_dir / f"{split}_{setting}_obj{o:02d}_ep{k:02d}.mp4") if n < videos else None
        jobs.append(_Job(info.run_dir, info.policy, spec, o, k, episode_seed(seed, o, k), video, factory))

    def key(job: _Job) -> tuple:
        return (info.task, info.policy, split, setting, float(scale), job.object_id, job.episode, job.seed)

    done = load_results(out_jsonl)
    todo = [job for job in jobs if key(job) not in done]
    t0 = time.perf_counter()
    bar = tqdm(
        total=len(jobs),
        initial=len(jobs) - len(todo),
        desc=f"eval {info.policy} {info.task} {split}/{setting}",
        unit="ep",
        disable=not progress or None,
    )
    try:
        for result in _iterate(todo, workers):
            _append(out_jsonl, result)
            done[tuple(result[k] for k in RESULT_KEY)] = result
            bar.update(1)
            finished = [done[key(j)] for j in jobs if key(j) in done]
            bar.set_postfix(success=f"{sum(r['success'] for r in finished) / len(finished):.2f}")
    finally:
        bar.close()
        _release()
    results = [done[key(job)] for job in jobs]
    return summarize(results) | {
        "task": info.task,
        "policy": info.policy,
        "split": split,
        "setting": setting,
        "scale": float(scale),
        "seed": int(seed),
        "object_ids": list(ids),
        "episodes_per_object": episodes_per_object,
        "num_inference_steps": num_inference_steps,  # None: the run's own
        "execute_steps": execute_steps,
        "samples": samples,
        "size_normalize": size_frame is not None,
        "size_frame": size_frame,  # None, "uniform" or "axes"
        "new_episodes": len(todo),
        "seconds": round(time.perf_counter() - t0, 1),
        "run_dir": info.run_dir,
        "out": str(out_jsonl),
        "videos": [r["video"] for r in results if r.get("video")],
    }
