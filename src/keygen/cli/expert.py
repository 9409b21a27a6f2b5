"""``keygen expert`` (evaluate the scripted expert), ``keygen demos`` (record demonstrations) and
``keygen data`` (inspect a demonstration store)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from keygen.errors import InvalidParameterError

TASKS = ("pour", "knife", "stack")


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--task", required=True, choices=TASKS)
    p.add_argument("--split", default="train", choices=["train", "test", "policy"])
    p.add_argument(
        "--object-ids", default=None, help="comma-separated instance ids (default: all of the split)"
    )
    p.add_argument("--episodes", type=int, required=True)
    p.add_argument("--setting", default="hard", choices=["easy", "hard"])
    p.add_argument("--scale", type=float, default=1.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--image-size", type=int, default=128)
    p.add_argument("--num-points", type=int, default=1024)
    p.add_argument(
        "--pour-grasp",
        default="auto",
        choices=["auto", "through", "pinch"],
        help="pour expert's handle grasp: a finger through the handle where one fits, else the "
        "outside pinch of the bar (auto); never the pinch (through); always the pinch (pinch)",
    )
    p.add_argument(
        "--knife-plan",
        default="cost",
        choices=["cost", "first"],
        help="knife expert's plan (hand, insertion side, pitch, route): the least previewed cost "
        "(cost), or the first good-enough one in a fixed order, one plan family across episodes (first)",
    )


def register(sub: argparse._SubParsersAction) -> None:
    ex = sub.add_parser("expert", help="run the scripted expert without recording and report its success")
    _common(ex)
    ex.add_argument("--json", action="store_true", help="print only the JSON summary")
    ex.add_argument("--out", type=Path, default=None, help="also write one JSON line per episode here")
    ex.set_defaults(func=cmd_expert)

    de = sub.add_parser("demos", help="record expert demonstrations into an episode store (resumable)")
    _common(de)
    de.add_argument("--out", required=True, type=Path, help="episode store (a zarr directory)")
    de.add_argument("--max-attempts", type=int, default=None, help="stop after this many tries (default 3x)")
    de.set_defaults(func=cmd_demos)

    data = sub.add_parser("data", help="inspect demonstration stores")
    dsub = data.add_subparsers(dest="data_command", required=True)
    info = dsub.add_parser("info", help="episodes, steps, keys, size on disk, success and failure counts")
    info.add_argument("path", type=Path)
    info.set_defaults(func=cmd_data_info)
    video = dsub.add_parser("video", help="an episode's camera views tiled into a video")
    video.add_argument("path", type=Path)
    video.add_argument("--episode", type=int, default=0)
    video.add_argument("--out", required=True, type=Path)
    video.add_argument("--failed", action="store_true", help="read from the failed episodes")
    video.set_defaults(func=cmd_data_video)


def _spec(args: argparse.Namespace, record: bool):
    from keygen.expert.collect import RunSpec
    from keygen.objects.splits import SPLIT_SIZES

    if args.episodes < 1:
        raise InvalidParameterError(f"--episodes must be >= 1, got {args.episodes}")
    if args.object_ids:
        try:
            ids = tuple(int(v) for v in args.object_ids.split(","))
        except ValueError as exc:
            raise InvalidParameterError(
                f"--object-ids must be integers like 0,1,2, got {args.object_ids!r}"
            ) from exc
    else:
        ids = tuple(range(SPLIT_SIZES[args.split]))
    env_kwargs = (("image_size", args.image_size), ("num_points", args.num_points), ("include_rgb", record))
    options: tuple = ()
    if args.pour_grasp != "auto":
        if args.task != "pour":
            raise InvalidParameterError(f"--pour-grasp applies to --task pour only, got --task {args.task}")
        options = (("grasp", args.pour_grasp),)
    if args.knife_plan != "cost":
        if args.task != "knife":
            raise InvalidParameterError(f"--knife-plan applies to --task knife only, got --task {args.task}")
        options = (("plan_choice", args.knife_plan),)
    return RunSpec(
        args.task, args.split, ids, args.setting, args.scale, args.seed, record, env_kwargs, options
    )


def cmd_expert(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from keygen.evaluation.stats import summarize
    from keygen.expert.collect import iterate_episodes

    spec = _spec(args, record=False)
    t0 = time.perf_counter()
    results = []
    sink = args.out.open("w") if args.out else None
    bar = tqdm(total=args.episodes, desc=f"expert {args.task}", unit="ep", disable=None)
    for meta, _ in iterate_episodes(spec, list(range(args.episodes)), args.workers):
        results.append(meta)
        if sink:
            sink.write(json.dumps(meta) + "\n")
            sink.flush()
        bar.update(1)
        bar.set_postfix(success=f"{sum(r['success'] for r in results) / len(results):.2f}")
    bar.close()
    summary = summarize(results) | {
        "task": args.task,
        "split": args.split,
        "setting": args.setting,
        "scale": args.scale,
        "seconds": round(time.perf_counter() - t0, 1),
    }
    if not args.json:
        for obj, row in summary["by_object"].items():
            print(f"object {obj:>3}: {row['successes']}/{row['episodes']}  {row['failures'] or ''}")
    print(json.dumps(summary))
    return 0


def cmd_demos(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from keygen.data.store import EpisodeStore
    from keygen.expert.collect import iterate_episodes

    spec = _spec(args, record=True)
    store = EpisodeStore(args.out, mode="a")
    done_ok = store.num_episodes
    failed = store.failed.num_episodes if store.failed is not None else 0
    attempted = done_ok + failed  # resume: continue the episode numbering, so seeds are new
    max_attempts = args.max_attempts or 3 * args.episodes
    t0 = time.perf_counter()
    bar = tqdm(total=args.episodes, initial=min(done_ok, args.episodes), desc=f"demos {args.task}", unit="ep")
    new_ok = new_failed = 0
    while store.num_episodes < args.episodes and attempted < max_attempts:
        # Launch only what is still missing (plus nothing extra), in batches of the worker count.
        batch = list(
            range(
                attempted,
                min(attempted + max(args.workers, args.episodes - store.num_episodes), max_attempts),
            )
        )
        for meta, steps in iterate_episodes(spec, batch, args.workers):
            if meta["success"] and store.num_episodes >= args.episodes:
                continue  # a parallel extra beyond the requested count
            store.append_episode(steps, meta)
            if meta["success"]:
                new_ok += 1
                bar.update(1)
            else:
                new_failed += 1
        attempted = batch[-1] + 1
    bar.close()
    info = store.info()
    seconds = time.perf_counter() - t0
    tries = new_ok + new_failed
    print(
        json.dumps(
            {
                "episodes": store.num_episodes,
                "new_episodes": new_ok,
                "failed_new": new_failed,
                "success_rate": new_ok / tries if tries else None,
                "failures": info.get("success", {}).get("failure_reasons", {}),
                "seconds": round(seconds, 1),
                "episodes_per_minute": round(60 * tries / seconds, 2) if tries else None,
                "bytes_on_disk": info.get("bytes_on_disk"),
                "out": str(args.out),
            }
        )
    )
    return 0 if store.num_episodes >= args.episodes else 1


def cmd_data_info(args: argparse.Namespace) -> int:
    from keygen.data.store import EpisodeStore

    print(json.dumps(EpisodeStore(args.path, mode="r").info(), default=str))
    return 0


def cmd_data_video(args: argparse.Namespace) -> int:
    import imageio.v2 as imageio

    from keygen.data.store import EpisodeStore
    from keygen.sim.cameras import tile_views

    store = EpisodeStore(args.path, mode="r")
    if args.failed:
        store = store.failed
        if store is None:
            raise InvalidParameterError(f"{args.path} has no failed episodes")
    if "rgb" not in store.keys():
        raise InvalidParameterError(f"{args.path} holds no rgb images (recorded without --image-size?)")
    rgb = store.episode(args.episode, keys=["rgb"])["rgb"]  # (T, V, H, W, 3)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    imageio.mimsave(args.out, [tile_views(frame) for frame in rgb], fps=10, macro_block_size=1)
    print(json.dumps({"out": str(args.out), "frames": len(rgb), "meta": store.episode_meta(args.episode)}))
    return 0
