"""``keygen eval``: roll out a trained policy with perception and keypoints in the loop.

Each finished episode is appended to a JSONL file, so an interrupted evaluation resumes where it
stopped. Prints success with a 95% Wilson interval, overall and per object; the last stdout line is
the JSON summary (``episodes``, ``success_rate``, ``ci95``, ``by_object``, ``failures``, ...).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from keygen.errors import InvalidParameterError


def register(sub: argparse._SubParsersAction) -> None:
    ev = sub.add_parser("eval", help="evaluate a trained policy (resumable; success with 95%% intervals)")
    ev.add_argument("run_dir", type=Path, help="a policy run directory (config.json + model.safetensors)")
    ev.add_argument(
        "--split",
        default="test",
        choices=["train", "test", "policy", "seen"],
        help="object split; 'seen' = the run's own training instance(s)",
    )
    ev.add_argument("--setting", default="hard", choices=["easy", "hard"])
    ev.add_argument("--episodes-per-object", type=int, default=20)
    ev.add_argument(
        "--object-ids", default=None, help="comma-separated instance ids (default: all of the split)"
    )
    ev.add_argument("--scale", type=float, default=1.0, help="object scale (zero-shot scale robustness)")
    ev.add_argument("--seed", type=int, default=0, help="evaluation seed: fixes every episode's layout")
    ev.add_argument("--workers", type=int, default=1)
    ev.add_argument("--videos", type=int, default=0, help="record the first K episodes with keypoints drawn")
    ev.add_argument(
        "--num-inference-steps", type=int, default=None, help="denoising steps (default: the run's)"
    )
    ev.add_argument(
        "--execute-steps",
        type=int,
        default=None,
        help="actions run per prediction before predicting again (default: the run's; "
        "the horizon runs whole trajectories)",
    )
    ev.add_argument(
        "--samples",
        type=int,
        default=1,
        help="trajectories drawn per prediction; above 1, the one that agrees best with the previous "
        "plan runs (backward coherence, see docs/policies.md)",
    )
    ev.add_argument(
        "--size-normalize",
        nargs="?",
        const="uniform",
        default=None,
        choices=["uniform", "axes"],
        help="run each episode in a copy of the scene scaled by the keypoints to the training object's "
        "size, and scale the plan back (keypoint policies; see docs/policies.md): one scale (uniform, "
        "the default), or width and height apart (axes)",
    )
    ev.add_argument("--max-steps", type=int, default=None, help="shorter time limit (smoke tests only)")
    ev.add_argument(
        "--out", type=Path, default=None, help="JSONL of episode results (default: in RUN_DIR/eval)"
    )
    ev.add_argument("--json", action="store_true", help="print only the JSON summary")
    ev.set_defaults(func=cmd_eval)


def parse_ids(text: str | None) -> list[int] | None:
    if not text:
        return None
    try:
        return [int(v) for v in text.split(",")]
    except ValueError as exc:
        raise InvalidParameterError(f"--object-ids must be integers like 0,1,2, got {text!r}") from exc


def default_out(
    run_dir: Path,
    split: str,
    setting: str,
    scale: float,
    seed: int,
    num_inference_steps: int | None = None,
    execute_steps: int | None = None,
    size_normalize: str | None = None,
    samples: int = 1,
) -> Path:
    """Where results go; overridden sampling settings get their own file, so that resuming never
    mixes episodes run under different settings."""
    name = f"{split}_{setting}_scale{scale:g}_seed{seed}"
    if num_inference_steps is not None:
        name += f"_denoise{num_inference_steps}"
    if execute_steps is not None:
        name += f"_exec{execute_steps}"
    if size_normalize:
        name += "_sizenorm" if size_normalize in (True, "uniform") else f"_sizenorm_{size_normalize}"
    if samples != 1:
        name += f"_samples{samples}"
    return run_dir / "eval" / f"{name}.jsonl"


def cmd_eval(args: argparse.Namespace) -> int:
    from keygen.evaluation.evaluate import evaluate

    out = args.out or default_out(
        args.run_dir,
        args.split,
        args.setting,
        args.scale,
        args.seed,
        args.num_inference_steps,
        args.execute_steps,
        args.size_normalize,
        args.samples,
    )
    summary = evaluate(
        args.run_dir,
        args.split,
        args.setting,
        args.episodes_per_object,
        args.seed,
        args.workers,
        out,
        object_ids=parse_ids(args.object_ids),
        scale=args.scale,
        videos=args.videos,
        num_inference_steps=args.num_inference_steps,
        execute_steps=args.execute_steps,
        size_normalize=args.size_normalize,
        samples=args.samples,
        max_steps=args.max_steps,
        runner_factory=getattr(args, "runner_factory", None),  # tests inject a fake policy here
    )
    if not args.json:
        for obj, row in summary["by_object"].items():
            print(f"object {obj:>3}: {row['successes']}/{row['episodes']}  {row['failures'] or ''}")
        lo, hi = summary["ci95"]
        print(
            f"{summary['policy']} on {summary['task']} {summary['split']}/{summary['setting']}: "
            f"{summary['successes']}/{summary['episodes']} = {100 * summary['success_rate']:.1f}% "
            f"(95% CI {100 * lo:.1f}-{100 * hi:.1f}%) -> {out}"
        )
    print(json.dumps(summary))
    return 0
