"""Which plans the pinch pouring expert mixes, where, and how a policy trained on them fares there.

Run: ``.venv/bin/python benchmarks/pour_expert_plans.py --demos RECORDING.zarr [EVAL.jsonl ...]
[--names a,b] [--sectors 8] [--tolerances 0.1,0.3,0.5] [--out benchmarks/results/NAME.json]``.

Before it moves, the pinch expert (``keygen.expert.pour_pinch.choose_pinch``) picks one of 128
discrete variants: the transport turn (8), the approach pitch (4), the jaw order and the lip it pours
over (2 x 2), keeping the one whose previewed motion costs least. A policy sees the motions, not the
choice. This rebuilds each scene from its seed (a reset only, no motion) and asks the expert for its
plan:

- for every kept episode of a pinch recording (``--demos``): the plan, its cost, and the full cost of
  every variant. Per sector of the handle's heading it prints how many distinct plans the
  demonstrations hold and the commonest one's share; and, from the logged costs, how many distinct
  plans would remain had the expert kept the first variant, in a fixed order (turn as searched, jaws
  and lip in the commonest order, pitch 25, 35, 15, 55 degrees), costing at most ``tolerance`` more
  than the cheapest (the ``--tolerances``): whether the mixture is near-ties or set by the reach;
- for the scenes of pouring ``keygen eval`` files: the expert's plan and its cost on each, then each
  file's successes per heading sector and per band of that cost. A high cost means the arm works near
  its reach (IK residual, joint limits, a low wrist, a touch of the scene) for every variant.

An analysis of stored results, not a benchmark of speed; about 2.5 s per recorded episode and 0.7 s
per evaluation scene on one core.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

import keygen  # noqa: F401  (sets MUJOCO_GL before anything imports mujoco)
from keygen.data.store import EpisodeStore
from keygen.errors import KeyGenError
from keygen.evaluation.rollout import EnvSpec, make_env
from keygen.evaluation.stats import wilson_interval
from keygen.expert import pour_pinch
from keygen.expert._pour_util import ReachChecker
from keygen.expert.pour import POUR_TURNS, PourExpert

sys.path.insert(0, str(Path(__file__).resolve().parent))
from pour_success_by_handle_yaw import read_records, sector_of  # noqa: E402

TURN_ORDER = tuple(round(float(np.degrees(t))) for t in POUR_TURNS)
PITCH_PREFERENCE = (25, 35, 15, 55)  # the commonest pitch on the dense headings first
# Bands of the expert's plan cost: comfortable (under the search's GOOD_ENOUGH), turned or pitched
# to reach, strained, and near the reach limit for every variant.
COST_BANDS = ((0.0, 0.03), (0.03, 0.1), (0.1, 0.5), (0.5, np.inf))
RENDER = {"image_size": 64, "num_points": 256}  # the reset state does not depend on the render size


def plan_key(plan: pour_pinch.PinchPlan) -> dict:
    """A plan as plain numbers: turn and pitch in whole degrees, jaw order and lip as +-1."""
    return {
        "turn_deg": round(float(np.degrees(plan.pour_turn))),
        "pitch_deg": round(float(np.degrees(plan.pitch))),
        "closing": int(plan.closing_sign),
        "lip": int(plan.lip_side),
    }


def as_tuple(plan: dict) -> tuple:
    return plan["turn_deg"], plan["pitch_deg"], plan["closing"], plan["lip"]


def preference(plan: dict) -> tuple:
    """Order of the fixed-order choice: turn as the expert searches, the commonest jaws and lip, pitch."""
    pitch = plan["pitch_deg"]
    pitch_rank = PITCH_PREFERENCE.index(pitch) if pitch in PITCH_PREFERENCE else len(PITCH_PREFERENCE)
    return TURN_ORDER.index(plan["turn_deg"]), plan["closing"] != -1, plan["lip"] != -1, pitch_rank


def first_within(variants: list[dict], tolerance: float) -> dict:
    """The first variant in :func:`preference` order costing at most ``tolerance`` over the cheapest."""
    if not variants:
        raise ValueError("no variants")
    cheapest = min(v["cost"] for v in variants)
    return min((v for v in variants if v["cost"] <= cheapest + tolerance), key=preference)


def handle_heading(anchors: dict) -> float:
    """Heading of the handle in degrees, 0 = +x, from the mug's axis to the grasp anchor."""
    d = np.asarray(anchors["handle_grasp"])[:2] - np.asarray(anchors["bottom_center"])[:2]
    return float(np.degrees(np.arctan2(d[1], d[0])))


def scene_plan(env, seed: int, variants: bool) -> dict:
    """The pinch expert's plan (and optionally every variant's cost) in the scene of ``seed``."""
    _, info = env.reset(seed=int(seed))
    anchors = {k: np.asarray(v, dtype=np.float64) for k, v in info["anchors"].items()}
    expert = PourExpert(grasp="pinch")
    plan = expert.choose_plan(env, anchors)
    row = {"heading_deg": round(handle_heading(anchors), 2), "plan": plan_key(plan), "cost": float(plan.cost)}
    if variants:
        reach = ReachChecker(env.unwrapped.controller.handles)
        every = pour_pinch.pinch_variants(env, anchors, reach, expert.scene_checker(env))
        row["variants"] = [plan_key(v) | {"cost": round(float(v.cost), 4)} for v in every]
    return row


def recording_episodes(store: Path) -> list[dict]:
    """The kept episodes' metadata (split, object, setting, scale, seed) of a pinch pouring recording."""
    try:
        recording = EpisodeStore(store, mode="r")
        metas = [recording.episode_meta(i) for i in range(recording.num_episodes)]
    except (KeyGenError, OSError, ValueError) as err:
        raise SystemExit(f"{store}: not a keygen recording ({err})") from err
    if not metas or any(m.get("task") != "pour" for m in metas):
        raise SystemExit(f"{store}: only pouring recordings have a pinch plan")
    if any(m.get("expert_options", {}).get("grasp") != "pinch" for m in metas):
        raise SystemExit(f"{store}: not recorded with the pinch expert (--pour-grasp pinch)")
    return metas


class Scenes:
    """One environment alive at a time, rebuilt when the cell or object changes."""

    def __init__(self) -> None:
        self.key, self.env = None, None

    def plan(self, cell: tuple, object_id: int, seed: int, variants: bool) -> dict:
        if self.key != (cell, object_id):
            if self.env is not None:
                self.env.close()
            task, split, setting, scale = cell
            self.env = make_env(EnvSpec(task, split, setting, float(scale), **RENDER), int(object_id))
            self.key = (cell, object_id)
        return scene_plan(self.env, seed, variants)


def demo_summary(rows: list[dict], sectors: int, tolerances: list[float]) -> dict:
    """Per heading sector: episodes, distinct plans, the commonest share; the fixed-order counterfactual."""
    table = []
    for s in range(sectors):
        mine = [r for r in rows if sector_of(np.radians(r["heading_deg"]), sectors) == s]
        plans = Counter(as_tuple(r["plan"]) for r in mine)
        entry = {"sector": s, "episodes": len(mine), "distinct_plans": len(plans)}
        entry["commonest_share"] = round(plans.most_common(1)[0][1] / len(mine), 3) if mine else None
        if all("variants" in r for r in mine):
            for tol in tolerances:
                chosen = Counter(as_tuple(first_within(r["variants"], tol)) for r in mine)
                entry[f"distinct_plans_first_within_{tol:g}"] = len(chosen)
        table.append(entry)
    overall = {"episodes": len(rows), "distinct_plans": len({as_tuple(r["plan"]) for r in rows})}
    for tol in tolerances:
        if rows and all("variants" in r for r in rows):
            picks = [first_within(r["variants"], tol) for r in rows]
            overall[f"distinct_plans_first_within_{tol:g}"] = len({as_tuple(p) for p in picks})
            cheapest = [min(v["cost"] for v in r["variants"]) for r in rows]
            extra = [p["cost"] - c for p, c in zip(picks, cheapest, strict=True)]
            overall[f"mean_extra_cost_first_within_{tol:g}"] = round(float(np.mean(extra)), 4)
    return {"overall": overall, "sectors": table}


def band_of(cost: float) -> int:
    return next(i for i, (lo, hi) in enumerate(COST_BANDS) if lo <= cost < hi)


def eval_summary(runs: dict[str, list[dict]], plans: dict, sectors: int) -> dict:
    """Each file's successes per heading sector and per band of the expert's plan cost."""

    def tally(mine: list[dict]) -> dict:
        wins = sum(bool(r["success"]) for r in mine)
        ci = list(wilson_interval(wins, len(mine))) if mine else None
        return {"episodes": len(mine), "successes": wins, "ci95": ci}

    out = {}
    for name, rows in runs.items():
        keyed = [(plans[(r["_cell"], r["object_id"], r["seed"])], r) for r in rows]
        by_sector = [
            tally([r for p, r in keyed if sector_of(np.radians(p["heading_deg"]), sectors) == s])
            for s in range(sectors)
        ]
        by_band = [tally([r for p, r in keyed if band_of(p["cost"]) == b]) for b in range(len(COST_BANDS))]
        out[name] = {"by_sector": by_sector, "by_plan_cost": by_band}
    return out


def _fraction(t: dict) -> str:
    return f"{t['successes']}/{t['episodes']}" if t["episodes"] else "-"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="*", type=Path, help="pouring keygen eval JSONL files")
    ap.add_argument("--names", default=None, help="comma-separated names for the files")
    ap.add_argument("--demos", type=Path, default=None, help="a pinch pouring recording (zarr)")
    ap.add_argument("--sectors", type=int, default=8, help="sectors of the handle heading (default 8)")
    ap.add_argument(
        "--tolerances",
        default="0.1,0.3,0.5",
        help="cost tolerances of the fixed-order counterfactual (comma-separated, >= 0)",
    )
    ap.add_argument("--max-demos", type=int, default=None, help="only the first N recorded episodes")
    ap.add_argument("--out", type=Path, default=None, help="write the summary as JSON here")
    args = ap.parse_args(argv)
    if not args.files and args.demos is None:
        ap.error("give a recording (--demos), evaluation files, or both")
    names = args.names.split(",") if args.names else [str(p) for p in args.files]
    if len(names) != len(args.files) or len(set(names)) != len(names):
        ap.error(f"--names needs {len(args.files)} distinct names, got {names}")
    if not 2 <= args.sectors <= 72:
        ap.error(f"--sectors must be in [2, 72], got {args.sectors}")
    try:
        tolerances = [float(t) for t in args.tolerances.split(",") if t.strip()]
    except ValueError:
        ap.error(f"--tolerances must be numbers, got {args.tolerances!r}")
    if any(not t >= 0 for t in tolerances):
        ap.error(f"--tolerances must be >= 0, got {tolerances}")
    runs = {n: read_records(p) for n, p in zip(names, args.files, strict=True)}
    metas = recording_episodes(args.demos) if args.demos else []
    metas = metas[: args.max_demos] if args.max_demos else metas
    t0, scenes = time.perf_counter(), Scenes()
    demo_rows = []
    for i, m in enumerate(metas):
        cell = ("pour", m["split"], m["setting"], float(m["scale"]))
        plan = scenes.plan(cell, m["object_id"], m["seed"], variants=True)
        demo_rows.append({"episode": i, "seed": int(m["seed"])} | plan)
        if (i + 1) % 10 == 0 or i + 1 == len(metas):
            seconds = time.perf_counter() - t0
            print(f"recording: {i + 1}/{len(metas)} episodes planned, {seconds:.0f} s", flush=True)
    plans = {}
    wanted = sorted({(r["_cell"], r["object_id"], r["seed"]) for rows in runs.values() for r in rows})
    for j, key in enumerate(wanted):
        plans[key] = scenes.plan(*key, variants=False)
        if (j + 1) % 40 == 0 or j + 1 == len(wanted):
            seconds = time.perf_counter() - t0
            print(f"evaluation scenes: {j + 1}/{len(wanted)} planned, {seconds:.0f} s", flush=True)
    width = 360.0 / args.sectors
    bands = [list(b) for b in COST_BANDS]
    summary: dict = {"sectors": args.sectors, "tolerances": tolerances, "cost_bands": bands}
    if demo_rows:
        summary["recording"] = str(args.demos)
        summary["demos"] = demo_summary(demo_rows, args.sectors, tolerances)
        summary["demo_episodes"] = demo_rows
    if runs:
        summary["files"] = [str(p) for p in args.files]
        summary["evaluations"] = eval_summary(runs, plans, args.sectors)
        summary["scene_plans"] = [
            {"cell": list(k[0]), "object_id": k[1], "seed": k[2]} | v for k, v in plans.items()
        ]
    summary["seconds"] = round(time.perf_counter() - t0, 1)

    tol_cols = [f"first within {t:g}" for t in tolerances] if demo_rows else []
    demo_cols = ["demos", "distinct plans", "commonest share", *tol_cols] if demo_rows else []
    print("| handle heading (deg; 0 = +x) | " + " | ".join(demo_cols + names) + " |")
    print("|---|" + "---|" * (len(demo_cols) + len(names)))
    for s in range(args.sectors):
        cells = []
        if demo_rows:
            d = summary["demos"]["sectors"][s]
            share = "-" if d["commonest_share"] is None else f"{d['commonest_share']:.2f}"
            cells += [str(d["episodes"]), str(d["distinct_plans"]), share]
            cells += [str(d.get(f"distinct_plans_first_within_{t:g}", "-")) for t in tolerances]
        cells += [_fraction(summary["evaluations"][n]["by_sector"][s]) for n in names]
        print(f"| {(s - 0.5) * width:.0f} to {(s + 0.5) * width:.0f} | " + " | ".join(cells) + " |")
    if demo_rows:
        print("recording overall: " + json.dumps(summary["demos"]["overall"]))
    if runs:
        print("| expert's plan cost | " + " | ".join(names) + " |")
        print("|---|" + "---|" * len(names))
        for b, (lo, hi) in enumerate(COST_BANDS):
            cells = [_fraction(summary["evaluations"][n]["by_plan_cost"][b]) for n in names]
            print(f"| {lo:g} to {hi:g} | " + " | ".join(cells) + " |")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(summary, indent=1))
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
