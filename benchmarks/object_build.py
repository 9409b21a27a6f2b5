"""Time to generate one object instance (mesh, collision parts, anchors) per category, on one core.

Run: ``.venv/bin/python benchmarks/object_build.py [--instances 12] [--repeats 3]``. Samples
``--instances`` parameter sets per category (seeded, styles cycled) and times
``Generator.build`` on each, keeping the best of ``--repeats`` runs per instance (the least
disturbed by other jobs); prints the median and the slowest instance per category and writes
``benchmarks/results/object_build.json``. Was a timing assertion in the knife tests (< 0.3 s per
knife); timings belong here, where a busy machine cannot fail the test suite.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from keygen.objects.generators.bowl import BowlGenerator  # noqa: E402
from keygen.objects.generators.knife import KnifeGenerator  # noqa: E402
from keygen.objects.generators.mug import MugGenerator  # noqa: E402

GENERATORS = {"mug": MugGenerator, "knife": KnifeGenerator, "bowl": BowlGenerator}


def measure(category: str, instances: int, repeats: int, seed: int) -> dict:
    gen = GENERATORS[category]()
    rng = np.random.default_rng(seed)
    params = [gen.sample_params(rng, gen.styles[i % len(gen.styles)]) for i in range(instances)]
    best = []
    for i, p in enumerate(params):
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            gen.build(p, f"{category}-{i}")
            times.append(time.perf_counter() - t0)
        best.append(min(times))
    return {
        "category": category,
        "instances": instances,
        "median_s": float(np.median(best)),
        "max_s": float(np.max(best)),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--instances", type=int, default=12)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "object_build.json")
    args = p.parse_args(argv)
    rows = [measure(c, args.instances, args.repeats, args.seed) for c in GENERATORS]
    print(f"{'category':>8s} {'median s':>9s} {'max s':>7s}")
    for r in rows:
        print(f"{r['category']:>8s} {r['median_s']:9.3f} {r['max_s']:7.3f}")
    report = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cpus",
        "load_average_at_end": list(os.getloadavg()),
        "args": {k: str(v) for k, v in vars(args).items()},
        "results": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
