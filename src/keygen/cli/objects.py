"""``keygen objects``: generate, import, validate and preview object assets."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from keygen.errors import AssetError, InvalidParameterError


def register(sub: argparse._SubParsersAction) -> None:
    from keygen.objects.asset import CATEGORIES
    from keygen.objects.splits import DEFAULT_SEED, SPLITS

    objects = sub.add_parser("objects", help="procedural and imported object assets")
    osub = objects.add_subparsers(dest="objects_command", required=True)

    gen = osub.add_parser("generate", help="write procedural instances of a split, one folder each")
    gen.add_argument("--category", required=True, choices=CATEGORIES)
    gen.add_argument("--split", required=True, choices=SPLITS)
    gen.add_argument("--count", type=int, default=None, help="instances to write (default: the split's size)")
    gen.add_argument("--start", type=int, default=0, help="first instance index")
    gen.add_argument("--seed", type=int, default=DEFAULT_SEED, help="split seed (default %(default)s)")
    gen.add_argument("--scale", type=float, default=1.0, help="uniform scale applied to every instance")
    gen.add_argument("--out", required=True, type=Path)
    gen.add_argument("--overwrite", action="store_true", help="rebuild instances already on disk")
    gen.set_defaults(func=cmd_generate)

    imp = osub.add_parser("import", help="turn a scanned or downloaded mesh into an asset")
    imp.add_argument("path", type=Path, help="OBJ, STL, PLY, GLB or GLTF file")
    imp.add_argument("--category", required=True, choices=CATEGORIES)
    imp.add_argument("--out", required=True, type=Path, help="asset folder to write")
    imp.add_argument("--anchors", type=Path, default=None, help="JSON with canonical frame and anchors")
    imp.add_argument(
        "--units",
        default=None,
        choices=["m", "cm", "mm", "in"],
        help="units of the file (default: the anchors file's units, else metres)",
    )
    imp.add_argument("--scale", type=float, default=1.0, help="extra uniform scale after unit conversion")
    imp.add_argument(
        "--target-size", type=float, default=None, help="rescale so the largest extent is this (m)"
    )
    imp.add_argument("--collision", default="coacd", choices=["coacd", "hull"], help="collision parts method")
    imp.add_argument("--coacd-threshold", type=float, default=0.05, help="concavity threshold for coacd")
    imp.add_argument("--max-parts", type=int, default=32, help="most convex parts coacd may make")
    imp.set_defaults(func=cmd_import)

    val = osub.add_parser("validate", help="check asset folders: watertight, convex parts, anchors in place")
    val.add_argument("dirs", nargs="+", type=Path, help="asset folders or folders of asset folders")
    val.set_defaults(func=cmd_validate)

    prev = osub.add_parser("preview", help="render a contact sheet of assets with anchors marked")
    prev.add_argument("dir", type=Path, help="an asset folder or a folder of asset folders")
    prev.add_argument("--out", required=True, type=Path, help="PNG to write")
    prev.add_argument("--columns", type=int, default=6)
    prev.add_argument("--tile", type=int, default=256, help="pixels per instance")
    prev.set_defaults(func=cmd_preview)


def asset_dirs(root: Path) -> list[Path]:
    """``root`` itself if it is an asset folder, else its asset sub-folders, sorted."""
    if (root / "meta.json").is_file():
        return [root]
    if not root.is_dir():
        raise AssetError(f"{root} does not exist or is not a folder")
    found = sorted(p.parent for p in root.glob("*/meta.json"))
    if not found:
        raise AssetError(f"no asset folders (with meta.json) in {root}")
    return found


def generate_split(
    category: str,
    split: str,
    out: Path,
    count: int | None = None,
    start: int = 0,
    seed: int = 0,
    scale: float = 1.0,
    overwrite: bool = False,
) -> dict:
    """Write instances ``start .. start+count-1`` of a split; instances already on disk are kept."""
    from tqdm import tqdm

    from keygen.objects.splits import SPLIT_SIZES, instance_id, make_instance

    count = SPLIT_SIZES[split] if count is None else count
    if count < 1 or start < 0:
        raise InvalidParameterError(f"--count must be >= 1 and --start >= 0, got {count} and {start}")
    if not scale > 0:
        raise InvalidParameterError(f"--scale must be positive, got {scale}")
    t0 = time.perf_counter()
    written, kept = [], []
    for index in tqdm(range(start, start + count), desc=f"{category}/{split}", unit="obj", leave=False):
        folder = out / instance_id(category, split, index)
        if not overwrite and _matches(folder, seed, scale):
            kept.append(folder.name)
            continue
        asset = make_instance(category, split, index, seed)
        if scale != 1.0:
            asset = asset.scaled(scale)
        asset.params = {**asset.params, "split_seed": seed}
        asset.save(folder)
        written.append(folder.name)
    return {
        "category": category,
        "split": split,
        "seed": seed,
        "scale": scale,
        "count": count,
        "written": len(written),
        "kept": len(kept),
        "instances": [instance_id(category, split, i) for i in range(start, start + count)],
        "out": str(out),
        "seconds": round(time.perf_counter() - t0, 2),
    }


def _matches(folder: Path, seed: int, scale: float) -> bool:
    """Is there a complete asset here made with the same seed and scale (so a rerun can keep it)?"""
    try:
        meta = json.loads((folder / "meta.json").read_text())
    except (OSError, json.JSONDecodeError):
        return False
    return meta.get("params", {}).get("split_seed") == seed and abs(meta.get("scale", 0) - scale) < 1e-12


def cmd_generate(args: argparse.Namespace) -> int:
    summary = generate_split(
        args.category, args.split, args.out, args.count, args.start, args.seed, args.scale, args.overwrite
    )
    print(json.dumps(summary))
    return 0


def cmd_import(args: argparse.Namespace) -> int:
    from keygen.objects.importer import import_mesh

    t0 = time.perf_counter()
    asset = import_mesh(
        args.path,
        args.category,
        args.out,
        anchors_path=args.anchors,
        units=args.units,
        scale=args.scale,
        target_size=args.target_size,
        collision=args.collision,
        coacd_threshold=args.coacd_threshold,
        max_parts=args.max_parts,
    )
    meta = asset.meta()
    print(
        json.dumps(
            {
                "out": str(args.out),
                "instance_id": asset.instance_id,
                "category": asset.category,
                "watertight": meta["watertight"],
                "collision_parts": len(asset.collision),
                "mass": round(asset.mass, 5),
                "bbox": meta["bbox"],
                "anchors": asset.anchors is not None,
                "seconds": round(time.perf_counter() - t0, 2),
            }
        )
    )
    return 0


def cmd_validate(args: argparse.Namespace) -> int:
    from keygen.objects.asset import Asset
    from keygen.objects.splits import get_generator

    report = {}
    for root in args.dirs:
        for folder in asset_dirs(root):
            asset = Asset.load(folder)
            report[str(folder)] = get_generator(asset.category).validate(asset)
    bad = {k: v for k, v in report.items() if v}
    for folder, problems in bad.items():
        for p in problems:
            print(f"{folder}: {p}")
    print(json.dumps({"checked": len(report), "failed": len(bad)}))
    return 1 if bad else 0


def cmd_preview(args: argparse.Namespace) -> int:
    from keygen.objects.asset import Asset
    from keygen.objects.preview import contact_sheet

    assets = [Asset.load(d) for d in asset_dirs(args.dir)]
    out = contact_sheet(assets, args.out, columns=args.columns, tile=args.tile, title=str(args.dir))
    print(json.dumps({"out": str(out), "instances": len(assets)}))
    return 0
