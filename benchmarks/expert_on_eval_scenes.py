"""The scripted expert on exactly the scenes a policy evaluation draws: the demonstrator's ceiling.

Run: ``.venv/bin/python benchmarks/expert_on_eval_scenes.py --task pour --split test --setting hard
--episodes-per-object 20 --seed 1000 [--object-ids 0,1] [--expert-option grasp=pinch] [--workers 2]
--out benchmarks/results/NAME.jsonl``.

``keygen eval`` draws episode k of object o from the seed ``episode_seed(seed, o, k)``; this script
resets the same environment with the same seed and lets the task's scripted expert act instead of a
policy (the expert reads the scene's anchors, not the cameras). A policy trained by imitating that
expert cannot be expected to beat it, so this is the reference a policy's Table I cell should be read
against: on the same scenes, how often the demonstrator itself succeeds and how it fails. Each record
has the fields of a ``keygen eval`` episode (``policy`` is ``expert`` plus its options), so
``benchmarks/paired_eval_comparison.py`` pairs it with a policy's evaluation file episode by episode.

Every finished episode is appended to ``--out`` at once; a rerun skips the episodes already there
(an interrupted run loses only the episodes in flight). At the end the summary (success with a 95%
Wilson interval, per object, failure reasons) is printed and written next to ``--out`` as ``.json``.
The expert's scene is the evaluation's: the image size and point count only change what the cameras
render, not the physics (a test checks the reset state), so the defaults render small images to save
time. An analysis of the benchmark's ceiling, not a benchmark of speed.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import sys
import time
from collections.abc import Iterator
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import keygen  # noqa: E402,F401  (sets MUJOCO_GL before anything imports mujoco)
from keygen.errors import InvalidParameterError  # noqa: E402
from keygen.evaluation.evaluate import load_results  # noqa: E402
from keygen.evaluation.rollout import EnvSpec, episode_seed, make_env  # noqa: E402
from keygen.evaluation.stats import summarize  # noqa: E402
from keygen.objects.splits import SPLIT_SIZES  # noqa: E402
from keygen.sim import PHYSICS_VERSION  # noqa: E402


def parse_option(text: str) -> tuple[str, object]:
    """``key=value`` -> (key, value), the value read as JSON when it parses (numbers, booleans)."""
    key, sep, raw = text.partition("=")
    if not sep or not key:
        raise InvalidParameterError(f"--expert-option takes key=value, got {text!r}")
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    return key, value


def policy_label(options: dict[str, object]) -> str:
    """The ``policy`` field of the records: ``expert`` or ``expert[grasp=pinch,...]``."""
    if not options:
        return "expert"
    return "expert[" + ",".join(f"{k}={v}" for k, v in sorted(options.items())) + "]"


def plan_jobs(object_ids: list[int], episodes: int, seed: int) -> list[tuple[int, int, int]]:
    """(object id, episode, env seed) for every episode, in the order ``keygen eval`` lists them."""
    return [(o, k, episode_seed(seed, o, k)) for o in object_ids for k in range(episodes)]


def load_done(path: Path) -> dict[tuple[int, int], dict]:
    """Episodes already in ``path``, keyed by (object id, episode), read as ``keygen eval`` reads its
    own files (a torn last line, or an episode of another physics revision, runs again)."""
    return {(int(r["object_id"]), int(r["episode"])): r for r in load_results(path).values()}


_ENV: dict[tuple, object] = {}


def run_job(args: tuple[EnvSpec, dict, str, int, int, int]) -> dict:
    """One expert episode on the evaluation's scene; the record matches a ``keygen eval`` row."""
    from keygen.expert.runner import make_expert, run_episode

    spec, options, label, object_id, episode, seed = args
    key = (spec, object_id)
    if key not in _ENV:
        _ENV.clear()  # one environment (and renderer) per process
        _ENV[key] = make_env(spec, object_id)
    result = run_episode(_ENV[key], make_expert(spec.task, **options), seed).to_json()
    return {
        "task": spec.task,
        "policy": label,
        "split": spec.split,
        "setting": spec.setting,
        "scale": float(spec.scale),
        "object_id": int(object_id),
        "episode": int(episode),
        "seed": int(seed),
        "success": bool(result["success"]),
        "failure": result["failure"],
        "steps": int(result["steps"]),
        "seconds": float(result["seconds"]),
        "metrics": result.get("metrics", {}),
        "physics": PHYSICS_VERSION,
    }


def iterate(jobs: list[tuple], workers: int) -> Iterator[dict]:
    if workers == 1:
        for job in jobs:
            yield run_job(job)
        return
    with mp.get_context("spawn").Pool(workers) as pool:  # no inherited GL contexts
        yield from pool.imap_unordered(run_job, jobs)


def report(records: list[dict], label: str) -> dict:
    summary = summarize(records)
    lo, hi = summary["ci95"]
    print(
        f"{label}: {summary['successes']}/{summary['episodes']} = {summary['success_rate']:.1%} "
        f"[{lo:.1%}-{hi:.1%}]"
    )
    for obj, row in summary["by_object"].items():
        fails = ", ".join(f"{r} x{n}" for r, n in row["failures"].items())
        print(f"  object {obj:>2}: {row['successes']:>3}/{row['episodes']:<3} {fails}")
    print("failures:", json.dumps(summary["failures"]))
    return summary


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--task", required=True, choices=("pour", "knife", "stack"))
    parser.add_argument("--split", default="test", choices=tuple(SPLIT_SIZES))
    parser.add_argument("--setting", default="hard", choices=("easy", "hard"))
    parser.add_argument("--scale", type=float, default=1.0)
    parser.add_argument("--object-ids", default=None, help="comma-separated (default: the whole split)")
    parser.add_argument("--episodes-per-object", type=int, default=20)
    parser.add_argument("--seed", type=int, default=1000, help="the evaluation's --seed")
    parser.add_argument(
        "--expert-option",
        action="append",
        default=[],
        help="key=value passed to the task's expert, e.g. grasp=pinch (repeatable)",
    )
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--image-size", type=int, default=64)
    parser.add_argument("--num-points", type=int, default=256)
    parser.add_argument("--out", type=Path, required=True, help="episode records (.jsonl), resumable")
    args = parser.parse_args()

    if args.episodes_per_object < 1 or args.workers < 1:
        raise InvalidParameterError("--episodes-per-object and --workers must be >= 1")
    if args.out.suffix != ".jsonl":
        raise InvalidParameterError(f"--out must end in .jsonl, got {args.out}")
    n_objects = SPLIT_SIZES[args.split]
    if args.object_ids:
        object_ids = [int(x) for x in args.object_ids.split(",") if x]
        if bad := [o for o in object_ids if not 0 <= o < n_objects]:
            raise InvalidParameterError(
                f"--object-ids {bad} outside the {args.split} split (0-{n_objects - 1})"
            )
    else:
        object_ids = list(range(n_objects))
    options = dict(parse_option(o) for o in args.expert_option)
    label = policy_label(options)
    spec = EnvSpec(args.task, args.split, args.setting, args.scale, args.image_size, args.num_points)

    done = load_done(args.out)
    if stale := {r["policy"] for r in done.values()} - {label}:
        raise InvalidParameterError(
            f"{args.out} holds episodes of {sorted(stale)}, not {label}: use another --out"
        )
    jobs = [
        (spec, options, label, o, k, s)
        for o, k, s in plan_jobs(object_ids, args.episodes_per_object, args.seed)
        if (o, k) not in done
    ]
    from tqdm import tqdm

    args.out.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with args.out.open("a") as sink, tqdm(total=len(jobs), desc=label, unit="ep", file=sys.stderr) as bar:
        for rec in iterate(jobs, args.workers):
            sink.write(json.dumps(rec) + "\n")
            sink.flush()
            done[(rec["object_id"], rec["episode"])] = rec
            bar.update(1)
    wall = time.perf_counter() - t0

    wanted = {(o, k) for o, k, _ in plan_jobs(object_ids, args.episodes_per_object, args.seed)}
    records = [done[key] for key in sorted(wanted)]
    summary = report(records, label)
    summary |= {
        "task": args.task,
        "split": args.split,
        "setting": args.setting,
        "scale": args.scale,
        "seed": args.seed,
        "policy": label,
        "physics": PHYSICS_VERSION,
        "expert_options": options,
        "wall_s_this_run": round(wall, 1),
        "episode_seconds_sum": round(sum(r["seconds"] for r in records), 1),
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "command": " ".join(sys.argv),
    }
    args.out.with_suffix(".json").write_text(json.dumps(summary, indent=1))
    print(json.dumps({k: summary[k] for k in ("episodes", "successes", "success_rate", "ci95")}))


if __name__ == "__main__":
    main()
