"""Pouring evaluations binned by the direction the mug's handle pointed at the start of each episode.

Run: ``.venv/bin/python benchmarks/pour_success_by_handle_yaw.py A.jsonl [B.jsonl ...] [--names a,b]
[--sectors 8] [--demos RECORDING.zarr] [--out benchmarks/results/NAME.json]``, where each file is a
pouring cell of ``keygen eval`` (``RUN/eval/<split>_<setting>_scale<s>_seed<S>.jsonl``) or of the
benchmark.

In the ``hard`` setting the mug's yaw covers the full circle; in ``easy`` the handle always points
away from the robot (+x, yaw 0). A policy that scores differently in the two settings may simply be
worse at some handle directions: this rebuilds each episode's scene from its recorded seed (a reset
only, no rollout: the scene is a pure function of the seed), reads the handle's heading (from the
``bottom_center`` anchor to ``handle_grasp``, in the world's x-y plane, 0 = +x) and prints, per
sector of that heading, each file's successes and failure reasons. The sector centred on 0 is the
``easy`` setting's heading. ``--demos`` adds, per sector, how many episodes of the policies' training
recording the expert kept and how many it failed (headings from the stored anchors at each episode's
first step), since a policy can only learn the headings its demonstrations cover. An analysis of
stored results, not a benchmark of speed.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

import numpy as np

import keygen  # noqa: F401  (sets MUJOCO_GL before anything imports mujoco)
from keygen.evaluation.rollout import EnvSpec, make_env
from keygen.evaluation.stats import wilson_interval


def read_records(path: Path) -> list[dict]:
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if line.strip():
            try:
                rec = json.loads(line)
                key = (rec["task"], rec["split"], rec["setting"], float(rec["scale"]))
                ids = {"object_id": int(rec["object_id"]), "seed": int(rec["seed"])}
                rows.append(rec | ids | {"_cell": key})
            except (ValueError, KeyError, TypeError) as err:
                raise SystemExit(f"{path}:{n}: not a `keygen eval` episode record ({err})") from err
    if not rows:
        raise SystemExit(f"{path} holds no episodes")
    if any(r["task"] != "pour" for r in rows):
        raise SystemExit(f"{path}: only pouring episodes have a handle to bin by")
    return rows


def handle_heading(cell: tuple[str, str, str, float], object_id: int, seed: int, cache: dict) -> float:
    """Heading of the handle (radians in [-pi, pi), 0 = +x) in the scene of one episode seed."""
    task, split, setting, scale = cell
    key = (cell, object_id)
    if key not in cache:
        cache.clear()  # one environment alive at a time
        cache[key] = make_env(EnvSpec(task, split, setting, scale=scale), object_id)
    _, info = cache[key].reset(seed=seed)
    a = info["anchors"]
    d = np.asarray(a["handle_grasp"][:2]) - np.asarray(a["bottom_center"][:2])
    return float(np.arctan2(d[1], d[0]))


def store_headings(store: Path) -> dict[str, list[float]]:
    """Handle headings at the first step of a recording's kept and failed episodes (stored anchors)."""
    import zarr

    root = zarr.open_group(str(store), mode="r")
    out = {}
    for label, prefix in (("kept", ""), ("failed", "failed/")):
        try:
            ends = np.asarray(root[f"{prefix}meta/episode_ends"][:], dtype=np.int64)
            grasp = root[f"{prefix}data/anchors/handle_grasp"]
            bottom = root[f"{prefix}data/anchors/bottom_center"]
        except KeyError:
            if label == "kept":
                raise SystemExit(f"{store}: not a pouring recording (no handle anchors)") from None
            continue  # a recording without failed attempts
        starts = np.r_[0, ends[:-1]]
        d = np.asarray(grasp[:])[starts, :2] - np.asarray(bottom[:])[starts, :2]
        out[label] = [float(h) for h in np.arctan2(d[:, 1], d[:, 0])]
        if label == "failed":  # the expert's failure reason of each attempt, in the episode metadata
            out["failed_reasons"] = [
                json.loads(m).get("failure") for m in root["failed/meta/episode_meta"][:]
            ]
    return out


def sector_of(heading: float, sectors: int) -> int:
    """Sector index with sector 0 centred on heading 0."""
    width = 2 * np.pi / sectors
    return int(np.floor((heading + width / 2) % (2 * np.pi) / width)) % sectors


def _key(record: dict) -> tuple:
    return record["_cell"], record["object_id"], record["seed"]


def summarise(runs: dict[str, list[dict]], sectors: int) -> dict:
    cache: dict = {}
    headings = {}
    for rows in runs.values():
        for r in rows:
            k = _key(r)
            if k not in headings:
                headings[k] = handle_heading(r["_cell"], r["object_id"], r["seed"], cache)
    width = 360.0 / sectors
    table = []
    for s in range(sectors):
        row = {"sector": s, "from_deg": (s - 0.5) * width, "to_deg": (s + 0.5) * width, "runs": {}}
        for name, rows in runs.items():
            mine = [r for r in rows if sector_of(headings[_key(r)], sectors) == s]
            wins = sum(bool(r["success"]) for r in mine)
            row["runs"][name] = {
                "episodes": len(mine),
                "successes": wins,
                "ci95": list(wilson_interval(wins, len(mine))) if mine else None,
                "failures": dict(Counter(r.get("failure") or "unknown" for r in mine if not r["success"])),
            }
        table.append(row)
    by_episode = {str(k[1:]): float(np.degrees(v)) for k, v in headings.items()}  # (object, seed) -> deg
    return {"sectors": table, "heading_deg_by_episode": by_episode}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="+", type=Path, help="keygen eval JSONL files of pouring")
    ap.add_argument("--names", default=None, help="comma-separated names for the files")
    ap.add_argument("--sectors", type=int, default=8, help="sectors of the handle heading (default 8)")
    ap.add_argument("--demos", type=Path, default=None, help="also bin this recording's episodes (zarr)")
    ap.add_argument("--out", type=Path, default=None, help="write the summary as JSON here")
    args = ap.parse_args(argv)
    names = args.names.split(",") if args.names else [str(p) for p in args.files]
    if len(names) != len(args.files) or len(set(names)) != len(names):
        raise SystemExit(f"--names needs {len(args.files)} distinct names, got {names}")
    if not 2 <= args.sectors <= 72:
        raise SystemExit(f"--sectors must be in [2, 72], got {args.sectors}")
    runs = {n: read_records(p) for n, p in zip(names, args.files, strict=True)}
    summary = summarise(runs, args.sectors)
    demos = store_headings(args.demos) if args.demos else {}
    reasons = demos.pop("failed_reasons", None)
    for label, headings in demos.items():
        counts = Counter(sector_of(h, args.sectors) for h in headings)
        for row in summary["sectors"]:
            row[f"demos_{label}"] = counts.get(row["sector"], 0)
    if reasons is not None:
        for row in summary["sectors"]:
            row["demos_failed_reasons"] = dict(
                Counter(
                    r
                    for h, r in zip(demos["failed"], reasons, strict=True)
                    if sector_of(h, args.sectors) == row["sector"]
                )
            )
    demo_cols = [f"demos {label}" for label in demos]
    print("| handle heading (deg; 0 = +x, the easy setting's) | " + " | ".join(demo_cols + names) + " |")
    print("|---|" + "---|" * (len(demo_cols) + len(names)))
    for row in summary["sectors"]:
        cells = [str(row[f"demos_{label}"]) for label in demos]
        for n in names:
            r = row["runs"][n]
            fails = ", ".join(f"{k} {v}" for k, v in sorted(r["failures"].items(), key=lambda kv: -kv[1]))
            cells.append(f"{r['successes']}/{r['episodes']}" + (f" ({fails})" if fails else ""))
        print(f"| {row['from_deg']:.0f} to {row['to_deg']:.0f} | " + " | ".join(cells) + " |")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(summary | {"files": [str(p) for p in args.files]}, indent=1))
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
