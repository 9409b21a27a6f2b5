"""Mug keypoint repeatability split by whether the scans show the handle.

Run: ``.venv/bin/python benchmarks/keypoints_hidden_handle.py runs/kp-mug [--split test]
[--out benchmarks/results/NAME.json]`` after ``keygen keypoints eval runs/kp-mug --split test`` (which
renders and caches the evaluation scans in ``runs/kp-mug/eval_test``). Uses the same scans, pairs
and per-pair symmetry handling as the evaluation's ``repeatability``, and groups the pairs by the
handle points the *less* complete scan of the pair holds: scan points within ``--radius`` (1.5 cm) of
the ``handle_grasp`` anchor (privileged ground truth, not seen by the extractor). With no such point
the handle is hidden and the visible part fits every yaw (the view-dependent symmetry the
canonicaliser's metric already allows), so keypoints tied to the handle cannot be placed repeatably.
Also reports the repeatability when pairs with a scan whose view-dependent equivalence set contains
every yaw are compared up to a yaw, as the bowl's are. Prints a table and writes JSON.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from keygen.atomic import atomic_write_json  # noqa: E402
from keygen.keypoints import metrics as M  # noqa: E402
from keygen.keypoints.dataset import ScanSet  # noqa: E402
from keygen.keypoints.extractor import KeypointExtractor  # noqa: E402
from keygen.keypoints.symmetry import is_axial  # noqa: E402

GROUPS = ((0, 0), (1, 9), (10, 10**9))


def handle_points(points: np.ndarray, grasp: np.ndarray, radius: float) -> int:
    """Scan points within ``radius`` of the handle's grasp anchor."""
    return int((np.linalg.norm(np.asarray(points) - np.asarray(grasp), axis=1) < radius).sum())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run_dir", type=Path)
    p.add_argument("--split", default="test")
    p.add_argument("--radius", type=float, default=0.015, help="metres around handle_grasp")
    p.add_argument("--out", default=None, help="JSON path (default: print only)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    directory = args.run_dir / f"eval_{args.split}"
    if not ScanSet.exists(directory):
        raise SystemExit(
            f"{directory} has no scans; run `keygen keypoints eval {args.run_dir} --split {args.split}`"
        )
    data = ScanSet.load(directory)
    scans = data.scans
    extractor = KeypointExtractor.load(args.run_dir)
    if extractor.category != "mug":
        raise SystemExit(f"a handle belongs to mugs; {args.run_dir} is a {extractor.category!r} run")
    kp = np.stack([extractor.batch([s.points]).keypoints[0] for s in scans])
    x = np.stack([M.to_object_frame(k, s.rotation, s.translation) for k, s in zip(kp, scans, strict=True)])
    visible = np.array([handle_points(s.points, s.anchors_world["handle_grasp"], args.radius) for s in scans])
    any_yaw = np.array([is_axial(list(np.flatnonzero(eq))) for eq in data.equivalence])
    hits, hits_yaw, fewest, views = [], [], [], []
    for members in data.by_instance:
        sym = data.instance_symmetry[scans[members[0]].instance_id]
        for a, b in zip(members[0::2], members[1::2], strict=False):
            d = scans[a].diameter
            hits.append(np.mean(M.pair_errors(x[a], x[b], sym, is_axial(sym)) / d < M.REPEAT_THRESHOLD))
            axial = is_axial(sym) or bool(any_yaw[a] or any_yaw[b])
            hits_yaw.append(np.mean(M.pair_errors(x[a], x[b], sym, axial) / d < M.REPEAT_THRESHOLD))
            fewest.append(min(visible[a], visible[b]))
            views.append(min(scans[a].num_views, scans[b].num_views))
    hits, fewest = np.array(hits), np.array(fewest)
    groups = []
    print(f"{'handle points (fewer scan)':>27s} {'pairs':>6s} {'repeatability':>14s}")
    for lo, hi in GROUPS:
        m = (fewest >= lo) & (fewest <= hi)
        rep = float(hits[m].mean()) if m.any() else None
        groups.append({"handle_points": [lo, hi], "pairs": int(m.sum()), "repeatability": rep})
        label = f"{lo}" if lo == hi else (f"{lo}+" if hi >= 10**9 else f"{lo}-{hi}")
        print(f"{label:>27s} {int(m.sum()):6d} {rep if rep is not None else float('nan'):14.3f}")
    summary = {
        "run": str(args.run_dir),
        "split": args.split,
        "radius_m": args.radius,
        "pairs": len(hits),
        "repeatability": round(float(hits.mean()), 4),
        "repeatability_handle_seen_in_both": round(float(hits[fewest > 0].mean()), 4),
        "scans_with_hidden_handle": int((visible == 0).sum()),
        "scans": len(scans),
        "repeatability_yaw_free_when_a_scan_fits_every_yaw": round(float(np.mean(hits_yaw)), 4),
        "scans_fitting_every_yaw": int(any_yaw.sum()),
        "groups": groups,
    }
    print(json.dumps({k: v for k, v in summary.items() if k != "groups"}))
    if args.out:
        atomic_write_json(args.out, summary, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
