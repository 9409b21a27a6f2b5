"""Per-object outcomes of policy evaluations beside the objects' shape parameters.

Run: ``.venv/bin/python benchmarks/per_object_failures.py A.jsonl [B.jsonl ...] [--names a,b]
[--params p1,p2] [--reference policy:0] [--out benchmarks/results/NAME.json]``, where each file is the
``RUN/eval/<split>_<setting>_scale<s>_seed<S>.jsonl`` that ``keygen eval`` writes (or a benchmark cell's
``results.jsonl``).

The acceptance of a policy benchmark asks, where a policy falls short, which instances it misses and
why. This prints one row per object: the generator's shape parameters (the procedural instance is a
pure function of category, split and index, so nothing is read from the runs but the outcomes), each
run's successes and its most frequent failure reasons; then the same parameters of the reference
instance (the one the demonstrations were recorded on, default ``policy:0``) and, per run and per
numeric parameter, the Spearman rank correlation between an object's success rate and that parameter
across the objects. With twelve objects a correlation is a pointer for a closer look, not a finding:
the JSON keeps the counts it rests on. An analysis of stored results, not a benchmark of speed.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

import numpy as np

import keygen  # noqa: F401  (sets MUJOCO_GL before anything imports mujoco)
from keygen.evaluation.pipeline import TASK_CATEGORY
from keygen.objects.splits import instance_params

# Shape parameters shown by default: the ones that decide where a gripper can go.
DEFAULT_PARAMS = {
    "mug": ("style", "radius_bottom", "taper", "height", "handle_gap", "handle_size", "handle_half_width"),
    "knife": ("style", "handle_shape", "blade_length", "blade_width", "handle_length", "handle_width"),
    "bowl": ("style", "inner_rim_radius", "depth", "flare_deg", "wall_thickness"),
}


def read_records(path: Path) -> list[dict]:
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if line.strip():
            try:
                rec = json.loads(line)
                rec["object_id"] = int(rec["object_id"])
                rec["success"] = bool(rec["success"])
                rec["task"], rec["split"]  # noqa: B018  (required keys)
            except (ValueError, KeyError, TypeError) as err:
                raise SystemExit(f"{path}:{n}: not a `keygen eval` episode record ({err})") from err
            rows.append(rec)
    if not rows:
        raise SystemExit(f"{path} holds no episodes")
    return rows


def spearman(x: list[float], y: list[float]) -> float | None:
    """Spearman's rho with average ranks for ties; None when either side is constant."""
    if len(x) < 3:
        return None

    def ranks(v):
        v = np.asarray(v, dtype=float)
        order = np.argsort(v, kind="stable")
        r = np.empty(len(v))
        r[order] = np.arange(len(v), dtype=float)
        for value in np.unique(v):  # ties share their mean rank
            tie = v == value
            r[tie] = r[tie].mean()
        return r

    rx, ry = ranks(x), ranks(y)
    if rx.std() == 0 or ry.std() == 0:
        return None
    return float(np.corrcoef(rx, ry)[0, 1])


def summarise(runs: dict[str, list[dict]], params: tuple[str, ...], reference: tuple[str, int]) -> dict:
    tasks = {r["task"] for rows in runs.values() for r in rows}
    splits = {r["split"] for rows in runs.values() for r in rows}
    if len(tasks) != 1 or len(splits) != 1:
        raise SystemExit(f"the files mix tasks {sorted(tasks)} or splits {sorted(splits)}: compare one cell")
    task, split = tasks.pop(), splits.pop()
    category = TASK_CATEGORY[task]
    ids = sorted({r["object_id"] for rows in runs.values() for r in rows})
    shapes = {i: instance_params(category, split, i) for i in ids}
    unknown = [p for p in params if p not in shapes[ids[0]]]
    if unknown:
        raise SystemExit(f"{category} has no parameters {unknown}; it has {sorted(shapes[ids[0]])}")
    objects = []
    for i in ids:
        row = {"object_id": i, "params": {p: shapes[i][p] for p in params}, "runs": {}}
        for name, rows in runs.items():
            mine = [r for r in rows if r["object_id"] == i]
            fails = Counter(r.get("failure") or "unknown" for r in mine if not r["success"])
            row["runs"][name] = {
                "episodes": len(mine),
                "successes": sum(r["success"] for r in mine),
                "failures": dict(fails.most_common()),
            }
        objects.append(row)
    correlations = {}
    for name in runs:
        rates = [o["runs"][name]["successes"] / max(1, o["runs"][name]["episodes"]) for o in objects]
        correlations[name] = {
            p: spearman([float(shapes[i][p]) for i in ids], rates)
            for p in params
            if isinstance(shapes[ids[0]][p], int | float)
        }
    ref_split, ref_id = reference
    ref_params = instance_params(category, ref_split, ref_id)
    return {
        "task": task,
        "category": category,
        "split": split,
        "params": list(params),
        "objects": objects,
        "reference": {"split": ref_split, "object_id": ref_id, "params": {p: ref_params[p] for p in params}},
        "spearman_success_vs_param": correlations,
    }


def _fmt(value) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def print_report(summary: dict) -> None:
    params, names = summary["params"], list(summary["spearman_success_vs_param"])
    print(f"{summary['task']} / {summary['category']}, {summary['split']} split (lengths in metres)")
    head = ["object", *params, *(f"{n} success" for n in names), *(f"{n} failures" for n in names)]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for o in summary["objects"]:
        cells = [str(o["object_id"]), *(_fmt(o["params"][p]) for p in params)]
        cells += [f"{o['runs'][n]['successes']}/{o['runs'][n]['episodes']}" for n in names]
        cells += [", ".join(f"{k} {v}" for k, v in o["runs"][n]["failures"].items()) or "-" for n in names]
        print("| " + " | ".join(cells) + " |")
    ref = summary["reference"]
    cells = [f"{ref['split']} {ref['object_id']} (reference)", *(_fmt(ref["params"][p]) for p in params)]
    print("| " + " | ".join(cells + [""] * (2 * len(names))) + " |")
    print()
    for name, rhos in summary["spearman_success_vs_param"].items():
        text = ", ".join(f"{p} {r:+.2f}" if r is not None else f"{p} -" for p, r in rhos.items())
        print(f"Spearman rho, success rate vs parameter, {name}: {text}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="+", type=Path, help="keygen eval JSONL files of one task and split")
    ap.add_argument("--names", default=None, help="comma-separated names for the files")
    ap.add_argument("--params", default=None, help="comma-separated shape parameters (default per category)")
    ap.add_argument("--reference", default="policy:0", help="SPLIT:ID of the demonstrated instance")
    ap.add_argument("--out", type=Path, default=None, help="write the summary as JSON here")
    args = ap.parse_args(argv)
    names = args.names.split(",") if args.names else [p.parent.parent.name for p in args.files]
    if len(names) != len(args.files) or len(set(names)) != len(names):
        raise SystemExit(f"--names needs {len(args.files)} distinct names, got {names}")
    split, _, index = args.reference.partition(":")
    if not index.isdigit():
        raise SystemExit(f"--reference takes SPLIT:ID (e.g. policy:0), got {args.reference!r}")
    runs = {n: read_records(p) for n, p in zip(names, args.files, strict=True)}
    task = runs[names[0]][0]["task"]
    params = tuple(args.params.split(",")) if args.params else DEFAULT_PARAMS[TASK_CATEGORY[task]]
    summary = summarise(runs, params, (split, int(index)))
    print_report(summary)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(summary | {"files": [str(p) for p in args.files]}, indent=1))
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
