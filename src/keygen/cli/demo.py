"""``keygen demo``: the main job, run by ``make demo``.

At this stage of the project it builds the object library (every category's train, test and
policy splits, a contact sheet per split with the anchors marked, the spread of the main
dimensions), runs the scripted expert of each task on two unseen instances in the hard setting,
records a few stacking demonstrations into an episode store and renders one of them to video,
then runs the quick end-to-end benchmark (``keygen benchmark --preset quick``: demonstrations,
keypoints, KeyGen and DP3 policies, evaluation on seen and unseen instances x easy and hard) into
``<out>/benchmark`` and prints its table. Reruns keep instances and demonstrations already on disk
and reuse every benchmark stage whose inputs have not changed.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    demo = sub.add_parser("demo", help="run the main job end to end (what `make demo` runs)")
    demo.add_argument("--out", type=Path, default=Path("out/demo"))
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument(
        "--skip-benchmark",
        action="store_true",
        help="skip the quick end-to-end benchmark (keypoints, policies)",
    )
    demo.set_defaults(func=cmd_demo)


def cmd_demo(args: argparse.Namespace) -> int:
    from keygen.cli.objects import generate_split
    from keygen.objects.asset import CATEGORIES, Asset
    from keygen.objects.preview import contact_sheet
    from keygen.objects.splits import SPLITS
    from keygen.objects.stats import dimension_ranges, ranges_markdown

    t0 = time.perf_counter()
    sheets = []
    for category in CATEGORIES:
        for split in SPLITS:
            folder = args.out / "objects" / category / split
            summary = generate_split(category, split, folder, seed=args.seed)
            assets = [Asset.load(folder / name) for name in summary["instances"]]
            sheet = contact_sheet(
                assets,
                args.out / "sheets" / f"{category}_{split}.png",
                columns=6,
                tile=200,
                title=f"{category} / {split} (seed {args.seed})",
            )
            sheets.append(str(sheet))
            print(
                f"{category:6s} {split:7s} {summary['count']:3d} instances "
                f"({summary['written']} new) -> {sheet}",
                flush=True,
            )
    ranges = {c: dimension_ranges(c, args.seed) for c in CATEGORIES}
    print()
    print(ranges_markdown(ranges))
    (args.out / "objects_stats.json").write_text(json.dumps(ranges, indent=1))
    experts = run_experts(args.seed)
    demos = record_demos(args.out / "demos" / "stack.zarr", args.seed)
    benchmark = None if args.skip_benchmark else run_quick_benchmark(args.out / "benchmark", args.seed)
    print(
        json.dumps(
            {
                "sheets": sheets,
                "expert": experts,
                "demos": demos,
                "benchmark": benchmark,
                "seconds": round(time.perf_counter() - t0, 1),
            }
        )
    )
    return 0


def run_quick_benchmark(out: Path, seed: int) -> dict:
    """The quick preset of ``keygen benchmark`` on every task, KeyGen against DP3; prints the table."""
    from keygen.evaluation.pipeline import TASKS, get_preset, run_benchmark
    from keygen.evaluation.report import results_table, write_report

    print("\nquick end-to-end benchmark (a smoke test of the pipeline, not a result):", flush=True)
    report = run_benchmark(get_preset("quick", seed=seed), out, TASKS, ("keygen", "dp3"))
    md, js = write_report(report, out)
    print(results_table(report["results"]), flush=True)
    print(f"report: {md}, {js} ({report['seconds']} s)")
    return {"results": report["results"], "markdown": str(md), "json": str(js), "seconds": report["seconds"]}


def run_experts(seed: int) -> dict:
    """The scripted expert of each task on two unseen (test) instances, hard setting."""
    from keygen.evaluation.stats import summarize
    from keygen.expert.collect import RunSpec, iterate_episodes

    print("\nscripted expert, test instances 0 and 1, hard setting:")
    out = {}
    for task in ("pour", "knife", "stack"):
        spec = RunSpec(
            task,
            "test",
            (0, 1),
            "hard",
            1.0,
            seed,
            False,
            (("image_size", 64), ("num_points", 256), ("include_rgb", False)),
        )
        results = [meta for meta, _ in iterate_episodes(spec, [0, 1], workers=1)]
        summary = summarize(results)
        out[task] = {"success_rate": summary["success_rate"], "failures": summary["failures"]}
        print(
            f"  {task:6s} {summary['successes']}/{summary['episodes']} {summary['failures'] or ''}",
            flush=True,
        )
    return out


def record_demos(path: Path, seed: int, episodes: int = 2) -> dict:
    """A few recorded stacking demonstrations (resumable) and a video of the first."""
    import imageio.v2 as imageio

    from keygen.data.store import EpisodeStore
    from keygen.expert.collect import RunSpec, iterate_episodes
    from keygen.sim.cameras import tile_views

    store = EpisodeStore(path, mode="a")
    spec = RunSpec(
        "stack",
        "policy",
        (0,),
        "hard",
        1.0,
        seed,
        True,
        (("image_size", 96), ("num_points", 1024), ("include_rgb", True)),
    )
    attempt = store.num_episodes + (store.failed.num_episodes if store.failed else 0)
    while store.num_episodes < episodes and attempt < 3 * episodes:
        for meta, steps in iterate_episodes(spec, [attempt], workers=1):
            store.append_episode(steps, meta)
        attempt += 1
    video = path.parent / "stack_episode0.mp4"
    if store.num_episodes:
        rgb = store.episode(0, keys=["rgb"])["rgb"]  # (T, V, H, W, 3)
        imageio.mimsave(video, [tile_views(frame) for frame in rgb], fps=10, macro_block_size=1)
    info = store.info()
    print(
        f"\nrecorded {store.num_episodes} stacking demonstrations -> {path} "
        f"({info['bytes_on_disk'] / 1e6:.1f} MB), video {video}"
    )
    return {"path": str(path), "episodes": store.num_episodes, "video": str(video)}
