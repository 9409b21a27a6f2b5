"""How well a yaw-frame policy's keypoint frame follows the object on seen and unseen instances.

Run: ``.venv/bin/python benchmarks/yaw_frame_accuracy.py runs/pour100-keygen-yaw [--episodes 3]
[--seed 1000] [--out benchmarks/results/NAME.json]``. For each instance (the run's training instance,
then every test instance) it resets the evaluation environment with ``keygen eval``'s episode seeds,
lets the run's runner measure its frame at the first query (exactly as in a rollout), and compares
the frame's yaw with the object's true heading from the privileged anchors the environment reports
(not seen by the policy): the horizontal direction to ``handle_grasp`` from the mug's
``bottom_center`` or the knife's ``blade_tip``.

The frame's zero is the reference's arbitrary orientation, so the error is measured after removing
one constant offset: the circular mean of (frame yaw - heading) on the training instance. Prints a
table (median and worst absolute error per instance, degrees) and writes JSON. A diagnosis tool,
not a speed benchmark.
"""

from __future__ import annotations

import argparse
import json
import os
import platform

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from keygen.atomic import atomic_write_json  # noqa: E402
from keygen.evaluation.evaluate import load_policy_runner, read_run_info  # noqa: E402
from keygen.evaluation.rollout import EnvSpec, episode_seed, make_env  # noqa: E402
from keygen.objects.splits import SPLIT_SIZES  # noqa: E402


def _heading(task: str, anchors: dict) -> float:
    """The object's true yaw proxy (rad): the horizontal direction to its handle grasp from the
    mug's bottom centre or the knife's blade tip."""
    centre = np.asarray(anchors["bottom_center" if task == "pour" else "blade_tip"], float)
    d = np.asarray(anchors["handle_grasp"], float) - centre
    return float(np.arctan2(d[1], d[0]))


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def circular_offset(pairs: list[tuple[float, float]]) -> float:
    """The circular mean (rad) of (frame yaw - heading) over (yaw, heading) pairs."""
    return float(np.angle(np.exp(1j * np.array([y - h for y, h in pairs])).mean()))


def abs_errors_deg(pairs: list[tuple[float, float]], offset: float) -> np.ndarray:
    """|frame yaw - heading - offset| in degrees, wrapped to [0, 180]."""
    return np.degrees(np.abs(_wrap(np.array([y - h for y, h in pairs]) - offset)))


def measure(info, runner, split: str, object_id: int, episodes: int, seed: int) -> list[tuple[float, float]]:
    """(frame yaw, true heading) of the first query of ``episodes`` evaluation episodes."""
    env = make_env(EnvSpec(info.task, split, "hard", 1.0, info.image_size, info.num_points), object_id)
    out = []
    for k in range(episodes):
        s = episode_seed(seed, object_id, k)
        obs, env_info = env.reset(seed=int(s))
        runner.reset(seed=int(s))
        runner.act(obs)
        out.append((float(runner.yaw_frame.yaw), _heading(info.task, env_info["anchors"])))
    env.close()
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run_dir")
    p.add_argument("--episodes", type=int, default=3, help="episodes per instance")
    p.add_argument("--seed", type=int, default=1000)
    p.add_argument("--out", default=None, help="JSON path (default: print only)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    info = read_run_info(args.run_dir)
    if info.task not in ("pour", "knife"):
        raise SystemExit(f"a heading is defined for pour and knife, not {info.task!r}")
    cells = [(info.train_split, int(i)) for i in info.train_object_ids]
    cells += [("test", i) for i in range(SPLIT_SIZES["test"])]
    runner = load_policy_runner(args.run_dir)
    if runner.yaw_reference is None:
        raise SystemExit(f"{args.run_dir} was not trained with --yaw-frame")
    pairs = {cell: measure(info, runner, *cell, args.episodes, args.seed) for cell in cells}
    offset = circular_offset([p for cell in cells[: len(info.train_object_ids)] for p in pairs[cell]])
    rows = []
    print(f"{'split':>7s} {'id':>3s} {'median err':>11s} {'max err':>8s}  (deg, after the training offset)")
    for (split, oid), values in pairs.items():
        err = abs_errors_deg(values, offset)
        rows.append({"split": split, "object_id": oid, "abs_error_deg": [round(float(e), 2) for e in err]})
        print(f"{split:>7s} {oid:3d} {np.median(err):11.1f} {err.max():8.1f}")
    test = np.concatenate([r["abs_error_deg"] for r in rows if r["split"] == "test"])
    summary = {
        "run": str(args.run_dir),
        "task": info.task,
        "episodes_per_instance": args.episodes,
        "seed": args.seed,
        "offset_deg": round(float(np.degrees(offset)), 2),
        "test_median_abs_error_deg": round(float(np.median(test)), 2),
        "test_p90_abs_error_deg": round(float(np.percentile(test, 90)), 2),
        "test_within_10deg": round(float(np.mean(test <= 10.0)), 3),
        "machine": platform.processor() or platform.machine(),
        "rows": rows,
    }
    print(json.dumps({k: v for k, v in summary.items() if k != "rows"}))
    if args.out:
        atomic_write_json(args.out, summary, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
