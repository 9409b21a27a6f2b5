"""Cost of one 10 Hz control step of the environments, broken down by stage, on one core.

Run: ``.venv/bin/python benchmarks/sim_step.py [--tasks pour,knife,stack] [--steps 30]``.
Pins the process to one CPU core (and Mesa's llvmpipe to one thread) so figures are per core;
prints a table of medians and writes ``benchmarks/results/sim_step.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

# One core: pin before anything starts threads.
os.environ.setdefault("LP_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MUJOCO_GL", "egl")
if hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})

import gymnasium as gym  # noqa: E402

import keygen  # noqa: E402
from keygen.perception.fusion import make_object_cloud, make_scene_cloud  # noqa: E402
from keygen.sim.scene import TABLE_TOP_Z  # noqa: E402


def _ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1000)
    return statistics.median(times)


def measure(task: str, steps: int, image_size: int, num_points: int) -> dict:
    env = gym.make(keygen.ENV_IDS[task], image_size=image_size, num_points=num_points).unwrapped
    t0 = time.perf_counter()
    obs, _ = env.reset(seed=0)
    reset_ms = (time.perf_counter() - t0) * 1000
    hold = obs["proprio"]
    full = _ms(lambda: env.step(hold), steps)
    physics = _ms(lambda: env.controller.step(env.model, env.data, hold), steps)
    renderer = env._renderer
    rgb_depth_seg = _ms(lambda: renderer.render(env.data, rgb=True), steps)
    depth_seg = _ms(lambda: renderer.render(env.data, rgb=False), steps)
    views = renderer.render(env.data, rgb=False)
    labels = env._segmenter(None, views.depth, views.geom_ids)
    K, T = views.intrinsics, views.extrinsics
    obj = _ms(lambda: make_object_cloud(views.depth, K, T, labels, env.fusion), steps)
    scene = _ms(lambda: make_scene_cloud(views.depth, K, T, TABLE_TOP_Z, env.fusion), steps)
    env.close()
    return {
        "task": task,
        "reset_ms": reset_ms,
        "step_ms": full,
        "physics_ik_ms": physics,
        "render_rgb_depth_seg_ms": rgb_depth_seg,
        "render_depth_seg_ms": depth_seg,
        "object_cloud_ms": obj,
        "scene_cloud_ms": scene,
        "step_without_rgb_ms": physics + depth_seg + obj + scene,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--tasks", default="pour,knife,stack")
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--image-size", type=int, default=128)
    parser.add_argument("--num-points", type=int, default=1024)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "sim_step.json")
    args = parser.parse_args()
    rows = [measure(t, args.steps, args.image_size, args.num_points) for t in args.tasks.split(",")]
    cols = [k for k in rows[0] if k != "task"]
    print(f"one core, {args.image_size}x{args.image_size}, 4 views, {args.num_points} points; medians in ms")
    print("| task | " + " | ".join(cols) + " |")
    print("|---|" + "---|" * len(cols))
    for r in rows:
        print(f"| {r['task']} | " + " | ".join(f"{r[c]:.1f}" for c in cols) + " |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = {
        "machine": platform.processor() or platform.machine(),
        "cpus_used": 1,
        "python": platform.python_version(),
    }
    report = {"meta": meta, "args": vars(args) | {"out": str(args.out)}, "results": rows}
    args.out.write_text(json.dumps(report, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
