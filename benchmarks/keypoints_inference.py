"""Keypoint inference time per object on one core: resample + canonicalise + detect + reproject.

Run: ``.venv/bin/python benchmarks/keypoints_inference.py [--runs runs/kp-mug,runs/kp-knife,runs/kp-bowl]``.
Pins the process to one CPU core (one torch thread), feeds each run's extractor clouds of 256, 512 and
1024 points taken from its cached evaluation (or training) scans, one object per call, plus a batch of
two (the stacking task's two bowls), with the run's inference settings (``inference.json``: resampling
ensemble, yaw refinement, axial completion) and with the paper's single pass, in the same process;
prints a table of medians and writes ``benchmarks/results/keypoints_inference.json``. The budget is
10 ms per object.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MUJOCO_GL", "egl")
if hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})

import numpy as np  # noqa: E402
import torch  # noqa: E402

from keygen.keypoints.dataset import ScanSet  # noqa: E402
from keygen.keypoints.extractor import KeypointExtractor  # noqa: E402

torch.set_num_threads(1)


def _ms(fn, repeats: int) -> float:
    fn()  # warm up (allocations, first-call dispatch)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1000)
    return statistics.median(times)


def _clouds(run: Path, size: int, count: int) -> list[np.ndarray]:
    source = next((d for d in (run / "eval_test", run / "data") if ScanSet.exists(d)), None)
    if source is None:
        raise SystemExit(f"{run} has no cached scans; run `keygen keypoints eval {run}` first")
    rng = np.random.default_rng(0)
    scans = ScanSet.load(source).scans[:count]
    return [s.points[rng.choice(len(s.points), size, replace=len(s.points) < size)] for s in scans]


def measure(run: Path, repeats: int, single: bool) -> dict:
    ex = (
        KeypointExtractor.load(run, ensemble=1, refine_iters=0, axial_copies=0)
        if single
        else KeypointExtractor.load(run)
    )
    row = {
        "run": str(run),
        "category": ex.category,
        "inference": (
            "single pass"
            if single
            else f"ens {ex.settings.ensemble}, yaw x{ex.settings.refine_iters}"
            + (f", axial x{ex.settings.axial_copies}" if ex.settings.axial_copies > 1 else "")
        ),
        "num_points": ex.num_points,
        "num_keypoints": ex.num_keypoints,
    }
    for size in (256, 512, 1024):
        clouds = _clouds(run, size, 8)
        row[f"ms_{size}"] = statistics.median(_ms(lambda c=c: ex(c), repeats) for c in clouds)
    pair = _clouds(run, 512, 2)
    row["ms_batch2_512"] = _ms(lambda: ex.batch(pair), repeats)
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", default="runs/kp-mug,runs/kp-knife,runs/kp-bowl")
    p.add_argument("--repeats", type=int, default=30)
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/keypoints_inference.json"))
    args = p.parse_args()
    runs = [Path(r) for r in args.runs.split(",") if Path(r).is_dir()]
    rows = [measure(r, args.repeats, single) for r in runs for single in (False, True)]
    if not rows:
        raise SystemExit(f"none of {args.runs} exists; train with `keygen keypoints train` first")
    print(
        f"{'category':10s}{'inference':>20s}{'points in':>10s}{'256 pts':>10s}{'512 pts':>10s}"
        f"{'1024 pts':>10s}{'2 x 512':>10s}"
        "  (ms, 1 core)"
    )
    for r in rows:
        print(
            f"{r['category']:10s}{r['inference']:>20s}{r['num_points']:10d}{r['ms_256']:10.2f}{r['ms_512']:10.2f}{r['ms_1024']:10.2f}"
            f"{r['ms_batch2_512']:10.2f}"
        )
    result = {
        "machine": platform.processor() or platform.machine(),
        "torch": torch.__version__,
        "threads": 1,
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
