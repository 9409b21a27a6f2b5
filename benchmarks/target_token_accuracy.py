"""How well the target token finds the pouring box on recorded episodes or fresh evaluation scenes.

Run: ``.venv/bin/python benchmarks/target_token_accuracy.py data/pour.zarr [--max-episodes N]
[--out benchmarks/results/NAME.json]`` on a pouring recording, or ``... --split test [--setting hard]
[--episodes 4] [--seed 1000]`` on fresh scenes of a split's mugs (the first observations of ``keygen
eval``'s episodes with that seed). For the first step of every episode (where a rollout measures its
token) it measures :func:`keygen.policies.target_token.measure_target` on the box's points of the
``object_cloud`` and compares it with the simulator's privileged anchors, which the token never sees:
the box's top centre (``container_center``; horizontal distance and height difference, cm) and its
inner half sizes (``container_half_extents``; the token measures the outer walls, so the difference
is about one wall thickness, 0.6-1.0 cm). Prints a table of medians, 95th percentiles and maxima and
writes JSON. A diagnosis tool, not a speed benchmark.
"""

from __future__ import annotations

import argparse
import json
import os
import platform

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

from keygen.atomic import atomic_write_json  # noqa: E402
from keygen.data.store import OBJECT_CLOUD_IDS_KEY, OBJECT_CLOUD_KEY, EpisodeStore  # noqa: E402
from keygen.policies.target_frame import target_points  # noqa: E402
from keygen.policies.target_token import measure_target  # noqa: E402

MEASURES = ("centre_error_cm", "top_error_cm", "wall_cm")


def errors(cloud: np.ndarray, ids: np.ndarray, centre: np.ndarray, inner_half: np.ndarray) -> tuple:
    """(horizontal centre error, |height error|, mean measured-minus-inner half size), all cm."""
    token = measure_target(target_points(cloud, ids))
    centre = np.asarray(centre, dtype=np.float64)
    inner = np.sort(np.asarray(inner_half, dtype=np.float64)[:2])[::-1]
    return (
        100 * float(np.linalg.norm(token[:2] - centre[:2])),
        100 * float(abs(token[2] - centre[2])),
        100 * float(np.mean(token[3:] - inner)),
    )


def measure_recording(store: EpisodeStore) -> list[tuple[float, float, float]]:
    """Per episode of a pouring recording, at its first step."""
    out = []
    for a in np.concatenate([[0], store.episode_ends[:-1]]).astype(int):
        out.append(
            errors(
                store.read(OBJECT_CLOUD_KEY, a, a + 1)[0],
                store.read(OBJECT_CLOUD_IDS_KEY, a, a + 1)[0],
                store.read("anchors/container_center", a, a + 1)[0],
                store.read("anchors/container_half_extents", a, a + 1)[0],
            )
        )
    return out


def measure_split(split: str, setting: str, episodes: int, seed: int) -> list[tuple[float, float, float]]:
    """Per episode of ``keygen eval``'s seeding on every mug of ``split``, at its first observation."""
    from keygen.evaluation.rollout import EnvSpec, episode_seed, make_env
    from keygen.objects.splits import SPLIT_SIZES

    out = []
    for object_id in range(SPLIT_SIZES[split]):
        env = make_env(EnvSpec("pour", split, setting), object_id)
        try:
            for k in range(episodes):
                obs, _ = env.reset(seed=episode_seed(seed, object_id, k))
                anchors = env.task.anchors_world(env.model, env.data)
                out.append(
                    errors(
                        obs[OBJECT_CLOUD_KEY],
                        obs[OBJECT_CLOUD_IDS_KEY],
                        anchors["container_center"],
                        anchors["container_half_extents"],
                    )
                )
        finally:
            env.close()
    return out


def summarise(values: np.ndarray) -> dict[str, float]:
    return {
        "median": float(np.median(values)),
        "p95": float(np.percentile(values, 95)),
        "max": float(np.max(values)),
    }


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("dataset", nargs="?", default=None, help="a pouring recording (keygen demos --task pour)")
    p.add_argument("--max-episodes", type=int, default=None, help="only the recording's first N episodes")
    p.add_argument("--split", default=None, help="fresh scenes of this split's mugs instead")
    p.add_argument("--setting", default="hard", choices=["easy", "hard"])
    p.add_argument("--episodes", type=int, default=4, help="scenes per mug with --split")
    p.add_argument("--seed", type=int, default=1000, help="keygen eval's --seed for the scenes")
    p.add_argument("--out", default=None, help="JSON file to write")
    args = p.parse_args(argv)
    if (args.dataset is None) == (args.split is None):
        p.error("give a recording or --split, not both")
    if args.dataset is not None:
        store = EpisodeStore(args.dataset, "r", max_episodes=args.max_episodes)
        if "anchors/container_center" not in store.keys():
            raise SystemExit(f"{args.dataset} has no box anchors: is it a pouring recording?")
        rows, source = measure_recording(store), str(args.dataset)
    else:
        rows = measure_split(args.split, args.setting, args.episodes, args.seed)
        source = f"{args.split} split, {args.setting}, {args.episodes} scenes per mug, seed {args.seed}"
    values = {name: np.array([row[i] for row in rows]) for i, name in enumerate(MEASURES)}
    result = {
        "source": source,
        "episodes": len(rows),
        "host": platform.node(),
        **{name: summarise(v) for name, v in values.items()},
    }
    print(f"target token on the first observation of {result['episodes']} episodes: {source}")
    print(f"| {'measure (cm)':<16} | median | p95   | max   |")
    print(f"|{'-' * 18}|--------|-------|-------|")
    for name in MEASURES:
        s = result[name]
        print(f"| {name:<16} | {s['median']:6.2f} | {s['p95']:5.2f} | {s['max']:5.2f} |")
    if args.out:
        atomic_write_json(args.out, result)
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
