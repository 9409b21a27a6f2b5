"""``keygen train``: train a diffusion policy on an episode store (resumable; a finished run is reused)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from keygen.errors import InvalidParameterError

# keygen.policies.POLICY_NAMES, copied so that `keygen --help` does not import torch (a test keeps them equal)
POLICIES = ("keygen", "keygen_no_kp", "keygen_scene", "keygen_yaw", "dp3")


def _keypoint_arg(values: list[str] | None) -> dict[str, Path] | None:
    if not values:
        return None
    out = {}
    for value in values:
        category, sep, path = value.partition("=")
        if not sep or not category or not path:
            raise InvalidParameterError(
                f"--keypoints takes CATEGORY=RUN_DIR (e.g. mug=runs/kp-mug), got {value!r}"
            )
        out[category] = Path(path)
    return out


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train a diffusion policy (keygen, its ablations, or the dp3 baseline)")
    p.add_argument("--policy", required=True, choices=POLICIES)
    p.add_argument("--dataset", required=True, type=Path, help="episode store written by `keygen demos`")
    p.add_argument("--out", required=True, type=Path, help="run directory (an interrupted run resumes)")
    p.add_argument(
        "--keypoints",
        action="append",
        metavar="CATEGORY=RUN_DIR",
        help="keypoint extractor run per category (repeat for several), e.g. mug=runs/kp-mug",
    )
    p.add_argument("--preset", default="default", choices=["quick", "default"])
    p.add_argument(
        "--frame",
        choices=["world", "object"],
        default=None,
        help="positions as observed (world, the default) or relative to the latest cloud's centroid "
        "(object; DiT policies only)",
    )
    p.add_argument(
        "--yaw-frame",
        action="store_true",
        help="train (and later run) each episode in the manipulated object's planar frame measured from "
        "its keypoints at the first step (keypoint policies; for mugs and knives, see docs/policies.md)",
    )
    p.add_argument(
        "--yaw-origin",
        choices=["centroid", "grasp"],
        default=None,
        help="centre of the yaw frame: the keypoint centroid (default) or the keypoint nearest the "
        "demonstrated grasp, so the approach follows the grasped part (needs --yaw-frame)",
    )
    p.add_argument(
        "--yaw-source",
        choices=["keypoints", "target"],
        default=None,
        help="what the yaw frame is measured on: the manipulated object's keypoints (default) or the "
        "top face of the object it goes into, the knife block, so the insertion is one motion "
        "(knife task; needs --yaw-frame)",
    )
    p.add_argument(
        "--target-token",
        action="store_true",
        help="condition also on one token saying where the object placed into stands (the box, the knife "
        "block: its centre, top and size, measured on its points at the episode's first step; pour and "
        "knife; DiT policies)",
    )
    p.add_argument(
        "--robot-base",
        action="store_true",
        help="condition also on where the arm's base stands in the yaw frame (its x, y and the world's "
        "heading there; the frame moves the base in every episode; needs --yaw-frame or keygen_yaw)",
    )
    p.add_argument("--steps", type=int, default=None, help="training steps (default: the preset's)")
    p.add_argument(
        "--max-episodes",
        type=int,
        default=None,
        help="train on the dataset's first N episodes only, for data-efficiency studies on one "
        "recording (default: all; more than the dataset holds is an error)",
    )
    p.add_argument(
        "--keypoint-noise",
        type=float,
        default=None,
        metavar="METRES",
        help="std of a random offset added to each keypoint of each training window, shared by its "
        "history (augmentation for unseen instances; keypoint policies; default 0: off)",
    )
    p.add_argument(
        "--proprio-noise",
        type=float,
        default=None,
        metavar="METRES",
        help="std of a random offset added to the hand's position in the proprioception of each "
        "training window, shared by its history, the actions kept (augmentation against drift off "
        "the demonstrations; default 0: off)",
    )
    p.add_argument("--batch-size", type=int, default=None)
    p.add_argument("--lr", type=float, default=None)
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--device", default=None, help="torch device (default cpu)")
    p.add_argument(
        "--threads", type=int, default=None, help="torch threads (default: the cores not already busy)"
    )
    p.add_argument("--json", action="store_true", help="no progress bar; print only the JSON summary")
    p.set_defaults(func=cmd_train)


def cmd_train(args: argparse.Namespace) -> int:
    from keygen.policies import TrainConfig, train_policy
    from keygen.policies.checkpoint import read_config

    config = TrainConfig.from_preset(
        args.preset,
        policy=args.policy,
        dataset=args.dataset,
        out=args.out,
        keypoints=_keypoint_arg(args.keypoints),
        steps=args.steps,
        batch_size=args.batch_size,
        lr=args.lr,
        seed=args.seed,
        device=args.device,
        num_threads=args.threads,
        max_episodes=args.max_episodes,
        keypoint_noise=args.keypoint_noise,
        proprio_noise=args.proprio_noise,
        policy_overrides={
            **({"frame": args.frame} if args.frame else {}),
            **({"yaw_frame": True} if args.yaw_frame else {}),
            **({"yaw_origin": args.yaw_origin} if args.yaw_origin else {}),
            **({"yaw_source": args.yaw_source} if args.yaw_source else {}),
            **({"target_token": True} if args.target_token else {}),
            **({"robot_base": True} if args.robot_base else {}),
        },
    )
    if not args.dataset.exists():
        raise InvalidParameterError(f"--dataset {args.dataset} does not exist; record it with `keygen demos`")
    run_dir = train_policy(config, progress=not args.json)
    meta = read_config(run_dir)
    result = meta.get("result", {})
    summary = {
        "run_dir": str(run_dir),
        "policy": args.policy,
        "task": meta["task"],
        "steps": meta["step"],
        "final_loss": result.get("final_loss"),
        "val_loss": result.get("val_loss"),
        "seconds": result.get("seconds"),
    }
    if not args.json:
        print(f"trained {args.policy} on {meta['task']} for {meta['step']} steps -> {run_dir}")
    print(json.dumps(summary))
    return 0
