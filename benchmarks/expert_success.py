"""Scripted-expert success over the benchmark grid, with per-object counts and failure reasons.

Run: ``.venv/bin/python benchmarks/expert_success.py [--tasks pour,knife,stack] [--episodes 24]``.

The grid: every task x {train, test} x {easy, hard} at scale 1.0, plus scales 0.5, 0.7 and 1.2
on test / hard (``--cells`` picks a subset, e.g. ``test/hard/1.0,test/hard/0.7``). Each cell runs
``--episodes`` episodes over the split's instances (12 test, 30 train) exactly as
``keygen expert --seed 0`` does (episode k: object k mod the split's size, env seed
``SeedSequence([seed, k])``), one process, image size 64
and 256 points (the expert reads anchors and proprioception, not images).

Every finished episode is appended to ``benchmarks/results/expert_success.jsonl`` at once, so an
interrupted run loses at most the episode in flight, and a rerun skips what is there (delete the
file, or pass ``--fresh``, to start over). At the end (and with ``--report`` alone, without
running) the episodes are summarised into ``benchmarks/results/expert_success.json``: per cell the
success rate with a 95% Wilson interval, per-object counts and the failure reasons, and a table is
printed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from collections import Counter
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from keygen.errors import InvalidParameterError  # noqa: E402
from keygen.evaluation.stats import summarize  # noqa: E402
from keygen.expert.collect import RunSpec, iterate_episodes  # noqa: E402
from keygen.objects.splits import SPLIT_SIZES  # noqa: E402

RESULTS = Path(__file__).parent / "results"
TASKS = ("pour", "knife", "stack")
BASE_CELLS = tuple(f"{split}/{setting}/1.0" for split in ("train", "test") for setting in ("easy", "hard"))
SCALE_CELLS = ("test/hard/0.5", "test/hard/0.7", "test/hard/1.2")
DEFAULT_EPISODES = 24
ENV_KWARGS = (("image_size", 64), ("num_points", 256), ("include_rgb", False))


def parse_cell(cell: str) -> tuple[str, str, float]:
    try:
        split, setting, scale = cell.split("/")
        value = float(scale)
    except ValueError as err:
        raise InvalidParameterError(
            f"a cell is split/setting/scale like test/hard/0.7, got {cell!r}"
        ) from err
    if split not in SPLIT_SIZES or setting not in ("easy", "hard") or not value > 0:
        raise InvalidParameterError(
            f"cell {cell!r}: split must be train/test/policy, setting easy/hard, scale > 0"
        )
    return split, setting, value


def cell_key(task: str, split: str, setting: str, scale: float) -> str:
    return f"{task}/{split}/{setting}/{scale:g}"


def load(path: Path) -> dict[str, dict[int, dict]]:
    """Episodes already on disk: cell key -> episode index -> record (a torn last line is ignored)."""
    done: dict[str, dict[int, dict]] = {}
    if path.exists():
        for line in path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            done.setdefault(rec["cell"], {})[int(rec["episode_index"])] = rec
    return done


def run(tasks: list[str], cells: list[str], episodes: int, seed: int, path: Path) -> None:
    from tqdm import tqdm

    done = load(path)
    todo = []
    for task in tasks:
        for cell in cells:
            split, setting, scale = parse_cell(cell)
            key = cell_key(task, split, setting, scale)
            missing = [k for k in range(episodes) if k not in done.get(key, {})]
            if missing:
                todo.append((task, split, setting, scale, key, missing))
    total = sum(len(t[-1]) for t in todo)
    bar = tqdm(total=total, desc="expert grid", unit="ep", file=sys.stderr)
    with path.open("a") as sink:
        for task, split, setting, scale, key, missing in todo:
            ids = tuple(range(SPLIT_SIZES[split]))
            spec = RunSpec(task, split, ids, setting, scale, seed, False, ENV_KWARGS)
            for meta, _ in iterate_episodes(spec, missing, workers=1):
                sink.write(json.dumps(meta | {"cell": key}) + "\n")
                sink.flush()
                bar.update(1)
                bar.set_postfix(cell=key, ok=meta["success"])
    bar.close()


def report(path: Path, out: Path, episodes: int | None) -> dict:
    done = load(path)
    cells = {}
    for key in sorted(done):
        records = [r for k, r in sorted(done[key].items()) if episodes is None or k < episodes]
        summary = summarize(records)
        summary["seconds"] = round(sum(r["seconds"] for r in records), 1)
        cells[key] = summary
    reasons = Counter()
    for summary in cells.values():
        reasons.update(summary["failures"])
    result = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "cells": cells,
        "failure_reasons": dict(reasons.most_common()),
    }
    out.write_text(json.dumps(result, indent=1))
    print(f"{'cell':<24} {'success':>8} {'rate':>6} {'95% CI':>13}  failures (object: reasons)")
    for key, s in cells.items():
        lo, hi = s["ci95"]
        fails = "; ".join(
            f"{obj}: " + ", ".join(f"{r} x{n}" for r, n in row["failures"].items())
            for obj, row in s["by_object"].items()
            if row["failures"]
        )
        print(
            f"{key:<24} {s['successes']:>3}/{s['episodes']:<4} {s['success_rate']:>6.0%} "
            f"{lo:>5.0%}-{hi:<5.0%}  {fails}"
        )
    print("failure reasons:", json.dumps(result["failure_reasons"]))
    return result


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--tasks", default=",".join(TASKS))
    parser.add_argument("--cells", default=",".join(BASE_CELLS + SCALE_CELLS))
    parser.add_argument(
        "--episodes",
        type=int,
        default=None,
        help="episodes per cell (default 24); with --report, summarise only the first N of each cell "
        "(default: all recorded)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--results", type=Path, default=RESULTS / "expert_success.jsonl")
    parser.add_argument("--fresh", action="store_true", help="discard the episodes already recorded")
    parser.add_argument("--report", action="store_true", help="only summarise what is recorded")
    args = parser.parse_args()
    tasks = [t for t in args.tasks.split(",") if t]
    if unknown := set(tasks) - set(TASKS):
        raise InvalidParameterError(f"--tasks must name tasks among {TASKS}, got {sorted(unknown)}")
    if args.episodes is not None and args.episodes < 1:
        raise InvalidParameterError(f"--episodes must be >= 1, got {args.episodes}")
    args.results.parent.mkdir(parents=True, exist_ok=True)
    if args.fresh and args.results.exists():
        args.results.unlink()
    if not args.report:
        t0 = time.perf_counter()
        cells = [c for c in args.cells.split(",") if c]
        run(tasks, cells, args.episodes or DEFAULT_EPISODES, args.seed, args.results)
        print(f"ran for {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    report(args.results, args.results.with_suffix(".json"), args.episodes if args.report else None)


if __name__ == "__main__":
    main()
