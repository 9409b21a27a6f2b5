"""``keygen benchmark``: the whole pipeline (demonstrations, keypoints, policies, evaluation on seen and
unseen instances x easy and hard), reusing every stage whose inputs have not changed.

Writes ``<out>/benchmark.md`` (a table shaped like the paper's Table I) and ``<out>/benchmark.json``,
prints the table, and ends stdout with one JSON line: ``{"results": [{task, policy, split, setting,
success_rate, ci95, ...}], ...}``. Stage progress goes to stderr.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from keygen.cli.train import POLICIES
from keygen.errors import InvalidParameterError


def register(sub: argparse._SubParsersAction) -> None:
    from keygen.evaluation.pipeline import PRESETS, TASKS

    bm = sub.add_parser("benchmark", help="run the end-to-end benchmark and write a Table-I-shaped report")
    bm.add_argument("--preset", default="quick", choices=sorted(PRESETS))
    bm.add_argument("--tasks", default=",".join(TASKS), help="comma-separated subset of pour,knife,stack")
    bm.add_argument(
        "--policies",
        default="keygen,dp3",
        help=f"comma-separated subset of {','.join(POLICIES)} (keygen_yaw: beyond the paper, pour and knife)",
    )
    bm.add_argument("--out", type=Path, default=None, help="output folder (default out/benchmark/<preset>)")
    bm.add_argument("--demos", type=int, default=None, help="demonstrations per task (preset override)")
    bm.add_argument("--episodes-per-object", type=int, default=None)
    bm.add_argument("--unseen-ids", default=None, help="comma-separated test instance ids")
    bm.add_argument("--settings", default=None, help="easy,hard or a subset")
    bm.add_argument("--workers", type=int, default=None)
    bm.add_argument("--seed", type=int, default=None, help="demonstration and training seed")
    bm.add_argument("--eval-seed", type=int, default=None)
    bm.add_argument("--image-size", type=int, default=None)
    bm.add_argument("--num-points", type=int, default=None)
    bm.add_argument("--videos", type=int, default=None, help="videos of the first K episodes of each cell")
    bm.add_argument("--policy-steps", type=int, default=None, help="policy training steps (preset override)")
    bm.add_argument("--num-inference-steps", type=int, default=None)
    bm.add_argument("--json", action="store_true", help="print only the JSON line")
    bm.set_defaults(func=cmd_benchmark)


def _names(text: str, allowed: tuple[str, ...], flag: str) -> tuple[str, ...]:
    names = tuple(dict.fromkeys(v.strip() for v in text.split(",") if v.strip()))
    bad = [n for n in names if n not in allowed]
    if bad or not names:
        raise InvalidParameterError(
            f"{flag} must be a comma-separated subset of {list(allowed)}, got {text!r}"
        )
    return names


def _ints(text: str | None, flag: str) -> tuple[int, ...] | None:
    if text is None:
        return None
    try:
        return tuple(int(v) for v in text.split(","))
    except ValueError as exc:
        raise InvalidParameterError(f"{flag} must be integers like 0,1,2, got {text!r}") from exc


def preset_from_args(args: argparse.Namespace):
    from keygen.evaluation.pipeline import get_preset

    base = get_preset(args.preset)
    policy_overrides = dict(base.policy_overrides)
    if args.policy_steps is not None:
        policy_overrides["steps"] = args.policy_steps
    return base.with_overrides(
        demos=args.demos,
        episodes_per_object=args.episodes_per_object,
        unseen_ids=_ints(args.unseen_ids, "--unseen-ids"),
        settings=_names(args.settings, ("easy", "hard"), "--settings") if args.settings else None,
        workers=args.workers,
        seed=args.seed,
        eval_seed=args.eval_seed,
        image_size=args.image_size,
        num_points=args.num_points,
        videos=args.videos,
        policy_overrides=policy_overrides,
        num_inference_steps=args.num_inference_steps,
    )


def cmd_benchmark(args: argparse.Namespace) -> int:
    from keygen.evaluation.pipeline import TASKS, run_benchmark
    from keygen.evaluation.report import benchmark_markdown, write_report

    tasks = _names(args.tasks, TASKS, "--tasks")
    policies = _names(args.policies, POLICIES, "--policies")
    preset = preset_from_args(args)
    out = args.out or Path("out/benchmark") / preset.name
    report = run_benchmark(
        preset,
        out,
        tasks,
        policies,
        functions=getattr(args, "stage_functions", None),  # tests inject fakes
    )
    md, js = write_report(report, out)
    report |= {"markdown": str(md), "json": str(js)}
    if not args.json:
        print(benchmark_markdown(report))
    print(json.dumps(report, default=str))
    return 0
