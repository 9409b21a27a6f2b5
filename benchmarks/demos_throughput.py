"""Demonstrations per minute with full recording, and the dataset's size on disk, on one core.

Run: ``.venv/bin/python benchmarks/demos_throughput.py [--tasks pour,knife,stack] [--episodes 4]``.
Records expert episodes exactly as ``keygen demos`` does (four 128x128 RGB-D views with masks,
1024-point clouds, anchors) into a temporary store, pinned to one core; prints a table and writes
``benchmarks/results/demos_throughput.json``. Failed episodes count toward the time (they are
recorded too, into ``failed/``), so the rate is attempts per minute and successes per minute.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

os.environ.setdefault("LP_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MUJOCO_GL", "egl")
if hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})

from keygen.data.store import EpisodeStore  # noqa: E402
from keygen.expert.collect import RunSpec, iterate_episodes  # noqa: E402


def measure(task: str, episodes: int, image_size: int, num_points: int) -> dict:
    env_kwargs = (("image_size", image_size), ("num_points", num_points), ("include_rgb", True))
    spec = RunSpec(task, "policy", (0,), "hard", 1.0, 0, True, env_kwargs)
    with tempfile.TemporaryDirectory() as tmp:
        store = EpisodeStore(Path(tmp) / "demos.zarr", mode="a")
        t0 = time.perf_counter()
        ok = steps = 0
        for meta, data in iterate_episodes(spec, list(range(episodes)), workers=1):
            store.append_episode(data, meta)
            ok += bool(meta["success"])
            steps += meta["steps"]
        seconds = time.perf_counter() - t0
        info = store.info()
        size = info["bytes_on_disk"] + (store.failed.info()["bytes_on_disk"] if store.failed else 0)
    return {
        "task": task,
        "episodes": episodes,
        "successes": ok,
        "mean_steps": steps / episodes,
        "seconds": seconds,
        "attempts_per_minute": 60 * episodes / seconds,
        "demos_per_minute": 60 * ok / seconds,
        "mb_per_100_episodes": size / episodes * 100 / 1e6,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--tasks", default="pour,knife,stack")
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--image-size", type=int, default=128)
    parser.add_argument("--num-points", type=int, default=1024)
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results" / "demos_throughput.json"
    )
    args = parser.parse_args()
    rows = [measure(t, args.episodes, args.image_size, args.num_points) for t in args.tasks.split(",")]
    print(
        f"one core, full recording ({args.image_size}px x 4 views, {args.num_points} points), "
        "policy-000, hard"
    )
    print("| task | episodes | successes | mean steps | demos/min | attempts/min | MB per 100 episodes |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['task']} | {r['episodes']} | {r['successes']} | {r['mean_steps']:.0f} | "
            f"{r['demos_per_minute']:.1f} | {r['attempts_per_minute']:.1f} | {r['mb_per_100_episodes']:.0f} |"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"machine": platform.processor() or platform.machine(), "cpus_used": 1}
    args.out.write_text(
        json.dumps({"meta": meta, "args": vars(args) | {"out": str(args.out)}, "results": rows}, indent=1)
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
