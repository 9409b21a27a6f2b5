"""Entry point of the ``keygen`` command: one sub-command group per stage of the pipeline."""

from __future__ import annotations

import argparse
import logging
import sys

from keygen.errors import KeyGenError


def build_parser() -> argparse.ArgumentParser:
    from keygen.cli import benchmark, demo, expert, keypoints, objects, sim, train
    from keygen.cli import eval as eval_cli

    parser = argparse.ArgumentParser(
        prog="keygen",
        description="KeyGen: category-level manipulation with self-supervised 3D keypoints.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", required=True)
    objects.register(sub)
    sim.register(sub)
    expert.register(sub)
    keypoints.register(sub)
    train.register(sub)
    eval_cli.register(sub)
    benchmark.register(sub)
    demo.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING, format="%(levelname)s %(message)s"
    )
    try:
        return int(args.func(args) or 0)
    except KeyGenError as exc:
        print(f"keygen: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("keygen: interrupted; finished work is kept and a rerun resumes", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
