"""The real work of each benchmark stage (``keygen.evaluation.pipeline`` decides when to run it).

Each function returns the JSON-able outputs recorded in the stage's ``stage.json``. Every one resumes
from partial outputs of the same inputs: the demonstration store keeps finished episodes, the trainers
reuse finished runs, the evaluation skips episodes already in its JSONL file.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

from keygen.evaluation.pipeline import PipelineError


def record_demos(task: str, preset, path: Path, progress: bool = True) -> dict[str, Any]:
    """``preset.demos`` successful expert demonstrations on the training instance(s), resumable.

    The same loop as ``keygen demos``: episode ``k`` has seed ``SeedSequence([seed, k])``; failed tries
    go to the store's ``failed/`` part and a resumed run continues the numbering.
    """
    from tqdm import tqdm

    from keygen.data.store import EpisodeStore
    from keygen.expert.collect import RunSpec, iterate_episodes

    env_kwargs = (
        ("image_size", preset.image_size),
        ("num_points", preset.num_points),
        ("include_rgb", False),
    )
    spec = RunSpec(
        task,
        preset.demo_split,
        tuple(preset.demo_object_ids),
        preset.demo_setting,
        1.0,
        preset.seed,
        True,
        env_kwargs,
        tuple(sorted(preset.expert_options.get(task, {}).items())),
    )
    store = EpisodeStore(path, mode="a")
    attempted = store.num_episodes + (store.failed.num_episodes if store.failed is not None else 0)
    max_attempts = 3 * preset.demos
    t0 = time.perf_counter()
    bar = tqdm(
        total=preset.demos,
        initial=min(store.num_episodes, preset.demos),
        desc=f"demos {task}",
        unit="ep",
        disable=not progress or None,
    )
    while store.num_episodes < preset.demos and attempted < max_attempts:
        missing = preset.demos - store.num_episodes
        batch = list(range(attempted, min(attempted + max(preset.workers, missing), max_attempts)))
        for meta, steps in iterate_episodes(spec, batch, preset.workers):
            if meta["success"] and store.num_episodes >= preset.demos:
                continue  # a parallel extra beyond the requested count
            store.append_episode(steps, meta)
            bar.update(int(meta["success"]))
        attempted = batch[-1] + 1
    bar.close()
    failed = store.failed.num_episodes if store.failed is not None else 0
    if store.num_episodes < preset.demos:
        raise PipelineError(
            f"the {task} expert produced {store.num_episodes} of {preset.demos} demonstrations in "
            f"{attempted} tries; lower --demos or use an easier demo setting"
        )
    return {
        "path": str(path),
        "episodes": store.num_episodes,
        "failed": failed,
        "image_size": preset.image_size,
        "num_points": preset.num_points,
        "seconds_this_run": round(time.perf_counter() - t0, 1),
    }


def train_keypoints(category: str, preset, out_dir: Path, progress: bool = True) -> dict[str, Any]:
    """The category's keypoint detector (canonicaliser + detector) with the preset's settings."""
    from keygen.keypoints import training

    # The preset takes the overrides itself (a dataclass rebuilt and validated with them).
    config = training.KeypointTrainConfig.preset(
        preset.keypoint_preset, category, **preset.keypoint_overrides
    )
    run_dir = training.train_keypoints(config, Path(out_dir), progress=progress)
    return {"run_dir": str(run_dir), "category": category}


def train_policy(
    task: str,
    policy: str,
    preset,
    dataset: str,
    keypoints: dict[str, str] | None,
    out_dir: Path,
    progress: bool = True,
) -> dict[str, Any]:
    """One policy trained on the task's demonstrations (with the keypoint runs it reads, if any)."""
    from keygen.policies import training

    config = training.TrainConfig.from_preset(
        preset.policy_preset,
        policy=policy,
        # Absolute paths: the run's config.json names them, and evaluation may run from elsewhere.
        dataset=Path(dataset).resolve(),
        out=Path(out_dir),
        keypoints={c: Path(p).resolve() for c, p in keypoints.items()} if keypoints else None,
        seed=preset.seed,
        **preset.policy_overrides,
    )
    run_dir = training.train_policy(config, progress=progress)
    return {"run_dir": str(run_dir), "task": task, "policy": policy}


def evaluate_cell(
    run_dir: str, split: str, setting: str, object_ids, preset, jsonl: Path, progress: bool = True
) -> dict[str, Any]:
    """Rollouts of one (split, setting) cell; the summary of :func:`keygen.evaluation.evaluate.evaluate`."""
    from keygen.evaluation.evaluate import evaluate

    summary = evaluate(
        run_dir,
        split,
        setting,
        preset.episodes_per_object,
        preset.eval_seed,
        preset.workers,
        jsonl,
        object_ids=list(object_ids),
        videos=preset.videos,
        num_inference_steps=preset.num_inference_steps,
        max_steps=preset.eval_max_steps,
        progress=progress,
    )
    print(
        f"[benchmark] {summary['task']} {summary['policy']} {split}/{setting}: "
        f"{summary['successes']}/{summary['episodes']} {summary['failures'] or ''}",
        file=sys.stderr,
        flush=True,
    )
    return summary
