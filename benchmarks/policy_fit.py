"""How well a trained policy fits its demonstrations, open loop: training vs validation episodes.

Run: ``.venv/bin/python benchmarks/policy_fit.py runs/knife100-keygen [--episodes 10] [--seed 0]
[--out benchmarks/results/NAME.json]``. Rebuilds the run's prepared dataset exactly as training did
(same store, resampled clouds, the cached keypoints, the same train / validation split), feeds the
recorded observation windows to the policy (EMA weights, its own sampler) and compares the sampled
action chunk with the recorded one. Per episode, at three query points:

- ``t0``: the episode's first step (the hand at home, the object untouched: the plan must read the
  object's pose from the observation);
- ``t8``: eight steps in;
- ``pre_close``: eight steps before the demonstration first closes the gripper (the grasp approach).

Reported: the mean distance (cm) between the first ``execute_steps`` predicted and recorded tcp
positions, averaged over the first ``--episodes`` training and validation episodes (one sample per
query, seeded by the episode id), and the same error of a blind baseline that ignores the
observation and replays the training episodes' mean trajectory (step by step from the episode's
start). A policy that cannot reproduce its training episodes open loop is
under-fitted, whatever it does in closed loop; the rollout diagnosis (``rollout_diagnosis.py``) is
the closed-loop counterpart. A diagnosis tool, not a benchmark of speed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from keygen.data.store import EpisodeStore  # noqa: E402
from keygen.data.windows import train_val_split  # noqa: E402
from keygen.policies.checkpoint import load_policy, read_config  # noqa: E402
from keygen.policies.data import load_policy_data  # noqa: E402
from keygen.policies.training import TrainConfig  # noqa: E402

QUERIES = ("t0", "t8", "pre_close")
# A gripper command below this is a close: the experts close to 0 and approach open by at least
# 0.06 (the pour expert's fitted opening through a narrow handle), so 0.5 would mistake a pour
# approach for a grasp.
CLOSED_BELOW = 0.04


def query_steps(actions: np.ndarray, start: int, end: int) -> dict[str, int]:
    """Global step ids of the three query points of the episode [start, end)."""
    grip = actions[start:end, 9]
    closes = np.flatnonzero(grip < CLOSED_BELOW)
    close = int(closes[0]) if len(closes) else end - start - 1
    return {"t0": start, "t8": min(start + 8, end - 1), "pre_close": start + max(close - 8, 0)}


def episode_errors(model, data, start: int, end: int, seed: int) -> dict[str, float]:
    n = model.config.execute_steps
    out = {}
    for name, step in query_steps(data.actions, start, end).items():
        batch = data.batch(np.array([step]))
        inputs = {k: v for k, v in batch.items() if k != "action"}
        plan = model.predict(inputs, generator=torch.Generator().manual_seed(seed))[0].numpy()
        err = np.linalg.norm(plan[:n, :3] - batch["action"][0, :n, :3].numpy(), axis=1)
        out[name] = float(err.mean())
    return out


def mean_trajectory(data, episodes: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """(L, 3) mean tcp target over the episodes, step by step from their starts (L: the longest;
    shorter episodes hold their last action, as the training windows pad)."""
    lengths = data.episode_ends[episodes] - starts[episodes]
    length = int(lengths.max())
    steps = starts[episodes][:, None] + np.minimum(np.arange(length)[None], (lengths - 1)[:, None])
    return data.actions[steps, :3].mean(axis=0)


def baseline_errors(data, mean: np.ndarray, start: int, end: int, n: int) -> dict[str, float]:
    out = {}
    for name, step in query_steps(data.actions, start, end).items():
        t = np.minimum(np.arange(step - start, step - start + n), len(mean) - 1)
        recorded = data.actions[np.minimum(np.arange(step, step + n), end - 1), :3]
        out[name] = float(np.linalg.norm(mean[t] - recorded, axis=1).mean())
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run_dir", type=Path)
    p.add_argument("--episodes", type=int, default=10, help="episodes per side (train, validation)")
    p.add_argument("--out", default=None, help="JSON path (default: print only)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    meta = read_config(args.run_dir)
    cfg = TrainConfig(**{**meta["train"], "out": args.run_dir})
    store = EpisodeStore(cfg.dataset, mode="r")
    t0 = time.perf_counter()
    data = load_policy_data(store, cfg, args.run_dir, progress=False)
    model, _ = load_policy(args.run_dir, "cpu")
    model.eval()
    train_eps, val_eps = train_val_split(store, cfg.val_fraction, cfg.seed)
    starts = np.concatenate([[0], data.episode_ends[:-1]])
    mean = mean_trajectory(data, np.asarray(train_eps), starts)
    n = model.config.execute_steps
    sides = {}
    print(f"{meta['policy']['name']} on {meta['task']}, step {meta['step']}: open-loop tcp error (cm)")
    print(f"{'episodes':>10s} " + " ".join(f"{q:>10s}" for q in QUERIES))
    for side, eps in (("train", train_eps), ("val", val_eps)):
        rows = [
            episode_errors(model, data, int(starts[e]), int(data.episode_ends[e]), int(e))
            for e in eps[: args.episodes]
        ]
        blind = [
            baseline_errors(data, mean, int(starts[e]), int(data.episode_ends[e]), n)
            for e in eps[: args.episodes]
        ]
        sides[side] = {
            "episodes": [int(e) for e in eps[: args.episodes]],
            **{q: round(100 * float(np.mean([r[q] for r in rows])), 2) for q in QUERIES},
            "mean_trajectory": {q: round(100 * float(np.mean([r[q] for r in blind])), 2) for q in QUERIES},
        }
        print(f"{side:>10s} " + " ".join(f"{sides[side][q]:10.2f}" for q in QUERIES))
        blind_row = " ".join(f"{sides[side]['mean_trajectory'][q]:10.2f}" for q in QUERIES)
        print(f"{'(mean traj)':>10s} " + blind_row)
    report = {
        "run_dir": str(args.run_dir),
        "task": meta["task"],
        "policy": meta["policy"]["name"],
        "frame": meta["policy"].get("frame", "world"),
        "train_step": meta["step"],
        "machine": f"{platform.machine()}, {os.cpu_count()} cpus",
        "seconds": round(time.perf_counter() - t0, 1),
        "error_cm": sides,
    }
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
    print(json.dumps(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
