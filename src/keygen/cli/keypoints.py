"""``keygen keypoints``: train the canonicaliser + keypoint detector, evaluate it, draw its keypoints.

keygen keypoints train --category mug --out runs/kp-mug [--preset quick]
keygen keypoints eval runs/kp-mug --split test --json
keygen keypoints show runs/kp-mug --out grid.png
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    kp = sub.add_parser("keypoints", help="self-supervised 3D keypoints: train, evaluate, show")
    ksub = kp.add_subparsers(dest="keypoints_command", required=True)

    tr = ksub.add_parser("train", help="train a category's canonicaliser and detector (resumable)")
    tr.add_argument("--category", required=True, choices=["mug", "knife", "bowl"])
    tr.add_argument("--out", required=True, type=Path, help="run directory (resumed if it exists)")
    tr.add_argument("--preset", default="default", choices=["quick", "default"])
    tr.add_argument("--seed", type=int, default=0)
    tr.add_argument(
        "--pose-mode", default=None, choices=["table", "any"], help="training poses (default table)"
    )
    tr.add_argument("--canon-steps", type=int, default=None)
    tr.add_argument("--detector-steps", type=int, default=None)
    tr.add_argument("--num-instances", type=int, default=None)
    tr.add_argument("--scans-per-instance", type=int, default=None)
    tr.add_argument("--no-ablation", action="store_true", help="skip the detector without canonicaliser")
    tr.add_argument("--json", action="store_true", help="print only the JSON summary")
    tr.set_defaults(func=cmd_train)

    ev = ksub.add_parser("eval", help="metrics of a run and its baselines on an object split")
    ev.add_argument("run", type=Path)
    ev.add_argument("--split", default="test", choices=["train", "test", "policy"])
    ev.add_argument("--pairs", type=int, default=10, help="scan pairs per instance")
    ev.add_argument("--instances", type=int, default=None, help="only the split's first N instances")
    ev.add_argument("--json", action="store_true", help="print only the JSON summary")
    ev.set_defaults(func=cmd_eval)

    sh = ksub.add_parser("show", help="PNG grid of the split's instances with keypoints coloured by index")
    sh.add_argument("run", type=Path)
    sh.add_argument("--out", required=True, type=Path)
    sh.add_argument("--split", default="test", choices=["train", "test", "policy"])
    sh.add_argument("--views", type=int, default=4, help="camera views fused per scan (1-4)")
    sh.add_argument("--seed", type=int, default=0)
    sh.add_argument("--instances", type=int, default=None, help="only the split's first N instances")
    sh.set_defaults(func=cmd_show)


def cmd_train(args: argparse.Namespace) -> int:
    from keygen.keypoints.training import KeypointTrainConfig, train_keypoints

    overrides = {
        key: value
        for key, value in (
            ("seed", args.seed),
            ("pose_mode", args.pose_mode),
            ("canon_steps", args.canon_steps),
            ("detector_steps", args.detector_steps),
            ("num_instances", args.num_instances),
            ("scans_per_instance", args.scans_per_instance),
        )
        if value is not None
    }
    if args.no_ablation:
        overrides["train_ablation"] = False
    config = KeypointTrainConfig.preset(args.preset, args.category, **overrides)
    t0 = time.perf_counter()
    out = train_keypoints(config, args.out, progress=True)
    summary = json.loads((out / "train_summary.json").read_text())
    summary |= {
        "run": str(out),
        "category": args.category,
        "preset": args.preset,
        "seconds": round(time.perf_counter() - t0, 1),
    }
    if not args.json:
        print(f"trained {args.category} keypoints in {out} ({summary['seconds']} s this call)")
    print(json.dumps(summary))
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from keygen.keypoints.evaluate import evaluate_run

    summary = evaluate_run(args.run, args.split, args.pairs, progress=True, num_instances=args.instances)
    if not args.json:
        keys = (
            "canon_acc_top1",
            "canon_acc_sym",
            "repeatability",
            "repeat_error",
            "das",
            "coverage",
            "inclusivity",
            "ms_per_object",
        )
        print(f"{'method':18s}" + "".join(f"{k:>16s}" for k in keys))
        for name, row in summary["methods"].items():
            cells = "".join(f"{row[k]:16.3f}" if k in row else f"{'-':>16s}" for k in keys)
            print(f"{name:18s}{cells}")
    print(json.dumps(summary))
    return 0


def cmd_show(args: argparse.Namespace) -> int:
    from keygen.keypoints.extractor import KeypointExtractor
    from keygen.keypoints.metrics import to_object_frame
    from keygen.keypoints.scans import ScanGenerator
    from keygen.keypoints.training import KeypointTrainConfig
    from keygen.keypoints.visualize import save_grid
    from keygen.objects.splits import SPLIT_SIZES

    extractor = KeypointExtractor.load(args.run)
    config = KeypointTrainConfig.from_json(json.loads((args.run / "train_config.json").read_text()))
    cells = []
    with ScanGenerator(
        config.category,
        args.split,
        num_points=config.scan_points,
        image_size=config.image_size,
        views=(args.views, args.views),
        pose_mode=config.pose_mode,
        num_instances=args.instances or SPLIT_SIZES[args.split],
    ) as gen:
        for i in range(gen.num_instances):
            scan = gen.scan(i, [args.seed, i])
            pred = extractor(scan.points)
            pose = (scan.rotation, scan.translation)
            cells.append(
                (
                    to_object_frame(scan.points, *pose),
                    to_object_frame(pred.keypoints, *pose),
                    f"{scan.instance_id} p={float(pred.confidence):.2f}",
                )
            )
    path = save_grid(cells, args.out)
    print(json.dumps({"out": str(path), "cells": len(cells)}))
    return 0
