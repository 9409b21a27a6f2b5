"""Which plan the knife expert picks, episode by episode, and whether the scene decides it.

Run: ``.venv/bin/python benchmarks/knife_expert_modes.py --episodes 100 [--split policy --object-id 0
--setting hard --seed 0] [--plan-choice cost|first] [--out benchmarks/results/NAME.json]``.

The knife expert (:mod:`keygen.expert.knife_plan`) chooses, before it moves, among discrete
candidates: the grasp hand (two top-down grasps turned pi apart), the side of the slot it inserts
from, a grasp pitch and the route of the blade-down turn, keeping the one whose previewed motion
costs least (joint-limit margin, singularity, tracking lag). A policy learns from the recorded
motions, not from the choice, so what matters is whether the choice is a function of what the policy
can see. For each episode this resets the task with the seed a recording's episode ``k`` uses
(``SeedSequence([seed, k])``, :mod:`keygen.expert.collect`), lets the expert plan, and records the
plan with the scene quantities a policy could read in the knife block's frame: the knife's heading
relative to the slot, whether it lies face down, and where it lies relative to the block; and, as a
second feature set, where block and grasp lie on the table (reach depends on them). It then asks how
well the plan can be predicted from each set alone (leave-one-out k-nearest neighbours on
standardised features) against always guessing the commonest plan. A plan the scene
does not decide is a mode the demonstrations mix, which a policy has to resolve from cues as fine as
the expert's preview costs.

Only the plan is computed (no motion is run), so an episode costs one reset and the preview (tens of
seconds on one core). With ``--out``, each episode is also appended to ``NAME.episodes.jsonl`` as it
is planned, and a rerun with the same arguments continues from there. Prints a table and writes
JSON. A diagnosis tool, not a benchmark of speed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from collections import Counter
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402

import keygen  # noqa: E402,F401  (registers the environments, sets MUJOCO_GL)
from keygen.expert.collect import RunSpec  # noqa: E402
from keygen.expert.knife_geometry import Z, unit  # noqa: E402
from keygen.expert.runner import make_expert  # noqa: E402


def _yaw(v: np.ndarray) -> float:
    return float(np.arctan2(v[1], v[0]))


def plan_record(env, seed: int, plan_choice: str = "cost") -> dict:
    """Reset with ``seed``, let a fresh knife expert plan, and describe the plan and the scene."""
    obs, info = env.reset(seed=seed)
    base = env.unwrapped
    task = base.task
    expert = make_expert("knife", plan_choice=plan_choice)
    a = info["anchors"]
    plan = expert.choose_plan(base, obs, a, float(task.blade.center_offset))
    slot = a["slot_axis"]
    across = unit(np.cross(Z, slot))  # as the planner measures the slot's sides
    centre = a["slot_center_top"]
    rel = a["handle_grasp"] - centre
    heading = _yaw(a["blade_axis"]) - _yaw(slot)  # the knife's heading in the block's frame
    # "first" previews every candidate: keep their costs, to see how far the kept plan is from the cheapest.
    scored = getattr(expert._planner, "scored", [])
    candidates = [
        [int(p.hand), int(np.sign(p.approach @ across)), round(float(np.degrees(p.pitch)), 1), p.route, c]
        for _, p, c in scored
    ]
    return {
        "split": base.object_split,
        "object_id": int(base.object_id),
        "setting": base.setting,
        "plan_choice": plan_choice,
        "seed": seed,
        "hand": int(plan.hand),
        "side": int(np.sign(plan.approach @ across)),  # which side of the slot, in the block's frame
        "pitch_deg": round(float(np.degrees(plan.pitch)), 1),
        "route": str(plan.route),
        "cost": float(plan.cost),
        "face_down": bool(task.face_down),
        "heading_deg": float(np.degrees(np.arctan2(np.sin(heading), np.cos(heading)))),
        "grasp_in_block_xy": [float(rel @ slot), float(rel @ across)],
        "block_yaw_deg": float(np.degrees(_yaw(slot))),
        **scene_positions(a),
        **({"candidates": candidates} if candidates else {}),
    }


def scene_positions(anchors: dict) -> dict:
    """Where the block and the grasp lie on the table (world xy, the robot's base fixed): reach,
    and so the pitch and the hand the expert needs, depends on them, not only on the block frame."""
    return {
        "block_xy": [float(v) for v in anchors["slot_center_top"][:2]],
        "grasp_xy": [float(v) for v in anchors["handle_grasp"][:2]],
    }


def mode_of(r: dict, keys: tuple[str, ...]) -> str:
    return "/".join(f"{k}={r[k]}" for k in keys)


def features(r: dict) -> list[float]:
    h, b = np.radians(r["heading_deg"]), np.radians(r["block_yaw_deg"])
    return [np.cos(h), np.sin(h), float(r["face_down"]), *r["grasp_in_block_xy"], np.cos(b), np.sin(b)]


def world_features(r: dict) -> list[float]:
    """The block-frame features plus where block and grasp lie on the table (what a world-frame
    policy's cloud also shows)."""
    return [*features(r), *r["block_xy"], *r["grasp_xy"]]


def loo_knn_accuracy(x: np.ndarray, labels: list[str], k: int = 5) -> float:
    """Leave-one-out accuracy of a k-nearest-neighbour vote (ties to the nearest) on standardised x."""
    x = (x - x.mean(0)) / np.where(x.std(0) > 0, x.std(0), 1.0)
    d = np.linalg.norm(x[:, None] - x[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    hits = 0
    for i in range(len(x)):
        near = np.argsort(d[i])[:k]
        votes = Counter(labels[j] for j in near)
        top = max(votes.values())
        guess = next(labels[j] for j in near if votes[labels[j]] == top)
        hits += guess == labels[i]
    return hits / len(x)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--split", default="policy")
    ap.add_argument("--object-id", type=int, default=0)
    ap.add_argument("--setting", default="hard", choices=["easy", "hard"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--plan-choice", default="cost", choices=["cost", "first"], help="the expert's plan_choice"
    )
    ap.add_argument("--k", type=int, default=5, help="neighbours in the leave-one-out vote")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    if args.episodes < args.k + 1:
        ap.error(f"--episodes must exceed --k ({args.k}) for the leave-one-out vote")
    env = gym.make(
        "keygen/CollectKnife-v0",
        object_split=args.split,
        object_id=args.object_id,
        setting=args.setting,
        image_size=64,
        num_points=256,
    )
    # The episodes a recording of this knife draws: the recorder's own seed for episode k.
    spec = RunSpec("knife", args.split, (args.object_id,), args.setting, 1.0, args.seed, record=False)
    scene = {"split": args.split, "object_id": args.object_id, "setting": args.setting}
    records, t0 = [], time.perf_counter()
    log = None if args.out is None else args.out.with_suffix(".episodes.jsonl")
    if log is not None and log.exists():
        records = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
        records = records[: args.episodes]
        for k, r in enumerate(records):
            # Files written before the scene keys were stored carry only the seed; before
            # --plan-choice existed, every plan was a "cost" one.
            same_scene = all(r.get(key, value) == value for key, value in scene.items())
            same_scene = same_scene and r.get("plan_choice", "cost") == args.plan_choice
            if r["seed"] != spec.episode(k)[1] or not same_scene:
                raise SystemExit(
                    f"{log} was planned with another --seed, --split, --object-id, --setting or "
                    "--plan-choice; remove it or pass the same ones"
                )
        print(f"resuming: {len(records)} episodes already planned in {log}")
        for k, r in enumerate(records):  # logs written before the positions were stored
            if "block_xy" not in r:
                r.update(scene_positions(env.reset(seed=spec.episode(k)[1])[1]["anchors"]))
    for k in range(len(records), args.episodes):
        records.append(plan_record(env, spec.episode(k)[1], args.plan_choice))
        if log is not None:
            log.parent.mkdir(parents=True, exist_ok=True)
            with log.open("a") as f:
                f.write(json.dumps(records[-1]) + "\n")
        if (k + 1) % 10 == 0 or k == 0:
            print(f"{k + 1}/{args.episodes} planned, {time.perf_counter() - t0:.0f} s", flush=True)
    x = np.array([features(r) for r in records])
    xw = np.array([world_features(r) for r in records])
    groupings = {
        "hand": ("hand",),
        "side": ("side",),
        "hand+side": ("hand", "side"),
        "pitch": ("pitch_deg",),
        "route": ("route",),
        "whole plan": ("hand", "side", "pitch_deg", "route"),
    }
    summary = {}
    head = f"{'choice':<12} {'modes':>5}  {'commonest':>9}  {'kNN block frame':>15}  {'kNN +positions':>14}"
    print(f"\n{head}  counts")
    for name, keys in groupings.items():
        labels = [mode_of(r, keys) for r in records]
        counts = Counter(labels)
        common = counts.most_common(1)[0][1] / len(labels)
        knn = loo_knn_accuracy(x, labels, args.k) if len(counts) > 1 else 1.0
        knn_world = loo_knn_accuracy(xw, labels, args.k) if len(counts) > 1 else 1.0
        summary[name] = {
            "modes": len(counts),
            "commonest": common,
            "knn": knn,
            "knn_with_positions": knn_world,
            "counts": dict(counts),
        }
        shown = ", ".join(f"{m}: {c}" for m, c in counts.most_common(6))
        print(f"{name:<12} {len(counts):>5}  {common:>9.2f}  {knn:>15.2f}  {knn_world:>14.2f}  {shown}")
    face = Counter((r["face_down"], r["hand"]) for r in records)
    print("\n(face_down, hand) counts:", dict(face))
    out = {
        "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "machine": platform.processor() or platform.machine(),
        "seconds": time.perf_counter() - t0,
        "summary": summary,
        "episodes": records,
    }
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1))
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
