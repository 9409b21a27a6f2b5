"""``keygen demo``: the main job, run by ``make demo``.

At this stage of the project it builds the object library: every category's train, test and
policy splits, a contact sheet per split with the anchors marked, and the spread of the main
dimensions. It grows into the full benchmark (demonstrations, keypoints, policies) as those
stages land. Reruns keep instances already on disk.
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
    print(json.dumps({"sheets": sheets, "seconds": round(time.perf_counter() - t0, 1)}))
    return 0
