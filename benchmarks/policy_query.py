"""Policy query latency on one core, and the training step time, for every policy.

Run: ``.venv/bin/python benchmarks/policy_query.py [--policies keygen,dp3] [--repeats 30]
[--train-threads 2] [--samples 1,4,8]``. A query is ``DiffusionPolicy.predict`` on one
observation (T = 16, 10 DDIM steps, observation history 2, the default sizes; keypoint policies
with 2 objects x 8 keypoints, the largest task), pinned to one core with
``torch.set_num_threads(1)``; with ``--samples``, also one query drawing N trajectories at once
(``keygen eval --samples N``, backward coherence), in the same run so the ratio is fair. It
excludes perception and keypoint extraction (timed by their own benchmarks). A training step is
one optimiser step (loss, backward, AdamW, EMA) at the default batch size on ``--train-threads``
threads. Medians of ``--repeats`` runs after warm-up (also the minimum and the process CPU time);
prints a table and writes ``benchmarks/results/policy_query.json``.
The estimated training time is steps x the step's CPU time for the default preset (plus one-off feature
preparation, not included). Timings depend on what else runs on the machine: say so when quoting.
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
import torch  # noqa: E402

from keygen.policies import EMA, POLICY_NAMES, DiffusionPolicy, make_policy_config  # noqa: E402
from keygen.policies.training import PRESETS  # noqa: E402

NUM_KEYPOINTS, NUM_OBJECTS = 8, 2
EXTRA: dict = {}


def build(name: str) -> DiffusionPolicy:
    kp = {"num_keypoints": NUM_KEYPOINTS, "num_objects": NUM_OBJECTS}
    cfg = make_policy_config(name, **(kp if name in ("keygen", "keygen_scene") else {}), **EXTRA)
    torch.manual_seed(0)
    model = DiffusionPolicy(cfg)
    rng = np.random.default_rng(0)
    model.normalizer.fit(rng.uniform(-1, 1, (100, 10)), rng.uniform(-1, 1, (100, 10)))
    return model


def inputs(model: DiffusionPolicy, b: int) -> dict[str, torch.Tensor]:
    c = model.config
    g = torch.Generator().manual_seed(0)
    out = {
        "cloud": torch.rand(b, c.cloud_frames, c.num_points, 3, generator=g) * 0.3 + 0.4,
        "proprio": torch.rand(b, c.obs_horizon, 10, generator=g),
        "action": torch.rand(b, c.horizon, 10, generator=g),
    }
    if c.use_keypoints:
        out["keypoints"] = torch.rand(b, c.obs_horizon, c.num_keypoint_tokens, 3, generator=g)
    return out


def timings_ms(fn, repeats: int, warmup: int = 3) -> dict[str, float]:
    """Median and minimum wall time, and median process CPU time, in ms. On a shared machine the
    minimum and the CPU time are the closer estimates of the uncontended latency."""
    for _ in range(warmup):
        fn()
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    median, cpu_median = float(np.median(wall)), float(np.median(cpu))
    return {"median": 1e3 * median, "min": 1e3 * min(wall), "cpu": 1e3 * cpu_median}


def measure(name: str, repeats: int, train_threads: int, batch: int, samples: tuple[int, ...] = (1,)) -> dict:
    model = build(name)
    torch.set_num_threads(1)
    model.eval()
    obs = {k: v[:1] for k, v in inputs(model, 1).items() if k != "action"}
    gen = torch.Generator().manual_seed(0)
    query = timings_ms(lambda: model.predict(obs, generator=gen), repeats)
    by_samples = {}
    for n in (n for n in samples if n > 1):
        draw = timings_ms(lambda n=n: model.predict(obs, generator=gen, num_samples=n), repeats)
        by_samples[str(n)] = draw["median"]
    model.train()
    torch.set_num_threads(train_threads)
    ema = EMA(model, model.config.ema_decay)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    data = inputs(model, batch)

    def step() -> None:
        loss = model.compute_loss(data)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        ema.update(model, 100)

    train = timings_ms(step, max(3, repeats // 5), warmup=2)
    torch.set_num_threads(1)
    steps = PRESETS["default"]["steps"]
    return {
        "policy": name,
        "parameters": sum(p.numel() for p in model.parameters()),
        "query_ms": query["median"],
        "query_min_ms": query["min"],
        "query_cpu_ms": query["cpu"],
        "query_ms_by_samples": {"1": query["median"], **by_samples},
        "train_step_ms": train["median"],
        "train_step_min_ms": train["min"],
        "train_step_cpu_ms": train["cpu"],
        "train_batch": batch,
        "train_threads": train_threads,
        "default_steps": steps,
        # From the CPU time: what the steps cost one uncontended core (a second core only helps).
        "est_default_train_minutes": steps * train["cpu"] / 6e4,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--policies", default=",".join(POLICY_NAMES))
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--train-threads", type=int, default=2)
    parser.add_argument("--samples", default="1", help="comma-separated trajectories per query, e.g. 1,4,8")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "policy_query.json")
    args = parser.parse_args()
    batch = PRESETS["default"]["batch_size"]
    samples = tuple(int(n) for n in args.samples.split(","))
    if min(samples) < 1:
        parser.error(f"--samples must be positive integers, got {args.samples}")
    rows = [measure(n, args.repeats, args.train_threads, batch, samples) for n in args.policies.split(",")]
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (timings grow with it)")
    head = ["policy", "params", "query med", "min", "cpu", "step med", "min", "cpu", "est. min"]
    print("ms; query on 1 thread, step on --train-threads; est. min = default steps x step cpu")
    print(f"{head[0]:<14}{head[1]:>10}" + "".join(f"{h:>10}" for h in head[2:]))
    for r in rows:
        print(
            f"{r['policy']:<14}{r['parameters']:>10,}{r['query_ms']:>10.1f}{r['query_min_ms']:>10.1f}"
            f"{r['query_cpu_ms']:>10.1f}{r['train_step_ms']:>10.0f}{r['train_step_min_ms']:>10.0f}"
            f"{r['train_step_cpu_ms']:>10.0f}{r['est_default_train_minutes']:>10.1f}"
        )
    if len(samples) > 1 or samples[0] != 1:
        print("query median (ms) by trajectories drawn per query (keygen eval --samples N)")
        print(f"{'policy':<14}" + "".join(f"{'N=' + str(n):>10}" for n in samples))
        for r in rows:
            by = r["query_ms_by_samples"]
            print(f"{r['policy']:<14}" + "".join(f"{by[str(n)]:>10.1f}" for n in samples))
    result = {
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count()},
        "load_average_at_end": os.getloadavg(),
        "torch": torch.__version__,
        "query": "predict, batch 1, T=16, 10 DDIM steps, obs history 2, 1 thread",
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
