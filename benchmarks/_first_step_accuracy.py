"""What the first-step accuracy scripts share (``target_frame_accuracy.py``, ``target_token_accuracy.py``).

Each compares a quantity a rollout measures once, at an episode's first observation, with the
simulator's privileged anchors, on a recording or on fresh scenes seeded as ``keygen eval`` seeds
them. A script supplies the task, the anchors it reads and an ``errors`` function mapping
``(object_cloud, object_cloud_ids, *anchors)`` to a tuple of named errors; this module reads the
first steps, summarises each error and handles the shared command line and JSON output.
Not a script itself: the leading underscore marks a helper that the scripts beside it import.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
from collections.abc import Callable, Sequence
from dataclasses import dataclass

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

from keygen.atomic import atomic_write_json  # noqa: E402
from keygen.data.store import OBJECT_CLOUD_IDS_KEY, OBJECT_CLOUD_KEY, EpisodeStore  # noqa: E402

ErrorsFn = Callable[..., tuple]


@dataclass(frozen=True)
class FirstStepCheck:
    """One script's choices: ``task`` and its object noun (``knife``, ``mug``) for the help text,
    the anchor names read both from a recording (``anchors/<name>``) and from a live scene, the
    names of the tuple ``errors`` returns, and a heading for the printed table."""

    task: str
    noun: str
    anchors: tuple[str, ...]
    measures: tuple[str, ...]
    errors: ErrorsFn
    title: str


def measure_recording(store: EpisodeStore, check: FirstStepCheck) -> list[tuple]:
    """``check.errors`` at the first step of every episode of a recording."""
    out = []
    for a in np.concatenate([[0], store.episode_ends[:-1]]).astype(int):
        anchors = [store.read(f"anchors/{name}", a, a + 1)[0] for name in check.anchors]
        cloud = store.read(OBJECT_CLOUD_KEY, a, a + 1)[0]
        ids = store.read(OBJECT_CLOUD_IDS_KEY, a, a + 1)[0]
        out.append(check.errors(cloud, ids, *anchors))
    return out


def measure_split(check: FirstStepCheck, split: str, setting: str, episodes: int, seed: int) -> list[tuple]:
    """``check.errors`` at the first observation of ``keygen eval``'s episodes (seed ``seed``) on
    every object of ``split``."""
    from keygen.evaluation.rollout import EnvSpec, episode_seed, make_env
    from keygen.objects.splits import SPLIT_SIZES

    out = []
    for object_id in range(SPLIT_SIZES[split]):
        env = make_env(EnvSpec(check.task, split, setting), object_id)
        try:
            for k in range(episodes):
                obs, _ = env.reset(seed=episode_seed(seed, object_id, k))
                anchors = env.task.anchors_world(env.model, env.data)
                out.append(
                    check.errors(
                        obs[OBJECT_CLOUD_KEY], obs[OBJECT_CLOUD_IDS_KEY], *[anchors[n] for n in check.anchors]
                    )
                )
        finally:
            env.close()
    return out


def summarise(values: np.ndarray) -> dict[str, float]:
    return {
        "median": float(np.median(values)),
        "p95": float(np.percentile(values, 95)),
        "max": float(np.max(values)),
    }


def run(
    check: FirstStepCheck, description: str, argv: Sequence[str] | None = None
) -> tuple[dict, dict, str | None]:
    """Parse the shared command line, measure and print the table. Returns the result dict, the
    per-measure arrays (a script may add entries to the result from them) and the ``--out`` path,
    for :func:`finish`."""
    p = argparse.ArgumentParser(description=description)
    recording = f"a {check.task} recording (keygen demos --task {check.task})"
    p.add_argument("dataset", nargs="?", default=None, help=recording)
    p.add_argument("--max-episodes", type=int, default=None, help="only the recording's first N episodes")
    p.add_argument("--split", default=None, help=f"fresh scenes of this split's {check.noun}s instead")
    p.add_argument("--setting", default="hard", choices=["easy", "hard"])
    p.add_argument("--episodes", type=int, default=4, help=f"scenes per {check.noun} with --split")
    p.add_argument("--seed", type=int, default=1000, help="keygen eval's --seed for the scenes")
    p.add_argument("--out", default=None, help="JSON file to write")
    args = p.parse_args(argv)
    if (args.dataset is None) == (args.split is None):
        p.error("give a recording or --split, not both")
    if args.dataset is not None:
        store = EpisodeStore(args.dataset, "r", max_episodes=args.max_episodes)
        missing = [n for n in check.anchors if f"anchors/{n}" not in store.keys()]
        if missing:
            raise SystemExit(f"{args.dataset} has no {missing} anchors: is it a {check.task} recording?")
        rows, source = measure_recording(store, check), str(args.dataset)
    else:
        rows = measure_split(check, args.split, args.setting, args.episodes, args.seed)
        source = f"{args.split} split, {args.setting}, {args.episodes} scenes per {check.noun}"
        source += f", seed {args.seed}"
    values = {name: np.array([row[i] for row in rows]) for i, name in enumerate(check.measures)}
    result = {
        "source": source,
        "episodes": len(rows),
        "host": platform.node(),
        **{name: summarise(v) for name, v in values.items()},
    }
    width = max(len(n) for n in check.measures) + 2
    print(f"{check.title} on the first observation of {result['episodes']} episodes: {source}")
    print(f"| {'measure':<{width}} | median | p95   | max   |")
    print(f"|{'-' * (width + 2)}|--------|-------|-------|")
    for name in check.measures:
        s = result[name]
        print(f"| {name:<{width}} | {s['median']:6.2f} | {s['p95']:5.2f} | {s['max']:5.2f} |")
    return result, values, args.out


def finish(result: dict, out: str | None) -> dict:
    """Write the JSON file (when ``out`` is given) and print it as the last line."""
    if out:
        atomic_write_json(out, result)
    print(json.dumps(result))
    return result
