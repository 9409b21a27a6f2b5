"""How well the target yaw frame finds the knife block's slot on recorded episodes.

Run: ``.venv/bin/python benchmarks/target_frame_accuracy.py data/knife-hard300.zarr [--max-episodes N]
[--out benchmarks/results/NAME.json]`` on a recording, or ``... --split test [--setting hard]
[--episodes 4] [--seed 1000]`` on fresh scenes of a split's knives (the first observations of
``keygen eval``'s episodes with that seed). For the first step of every episode (where a rollout
measures its frame) it measures :func:`keygen.policies.target_frame.measure_target_frame` on the
block's points of the ``object_cloud`` and compares it with the simulator's privileged anchors, which
the frame never sees: the slot axis (error modulo a half turn, degrees) and the slot's top centre
(horizontal distance, cm). An axis error near 90 degrees would mean the block's other axis was
taken for the slot. Prints a table of medians, 95th percentiles and maxima and writes JSON. A
diagnosis tool, not a speed benchmark.
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
from keygen.policies.target_frame import measure_target_frame, target_points  # noqa: E402


def axis_error_deg(yaw: float, axis: np.ndarray) -> float:
    """Angle (degrees, 0-90) between the frame's x axis and a horizontal ``axis``, either direction."""
    u = np.array([np.cos(yaw), np.sin(yaw)])
    a = np.asarray(axis, float)[:2]
    return float(np.degrees(np.arccos(np.clip(abs(u @ a) / np.linalg.norm(a), 0.0, 1.0))))


def errors(cloud: np.ndarray, ids: np.ndarray, slot_axis: np.ndarray, slot_centre: np.ndarray) -> tuple:
    """(axis error in degrees, origin-to-slot-centre distance in cm) of one observation."""
    frame = measure_target_frame(target_points(cloud, ids))
    centre_cm = 100 * float(np.linalg.norm(frame.origin[:2] - np.asarray(slot_centre)[:2]))
    return axis_error_deg(frame.yaw, slot_axis), centre_cm


def measure_recording(store: EpisodeStore) -> list[tuple[float, float]]:
    """Per episode of a knife recording, at its first step."""
    out = []
    for a in np.concatenate([[0], store.episode_ends[:-1]]).astype(int):
        out.append(
            errors(
                store.read(OBJECT_CLOUD_KEY, a, a + 1)[0],
                store.read(OBJECT_CLOUD_IDS_KEY, a, a + 1)[0],
                store.read("anchors/slot_axis", a, a + 1)[0],
                store.read("anchors/slot_center_top", a, a + 1)[0],
            )
        )
    return out


def measure_split(split: str, setting: str, episodes: int, seed: int) -> list[tuple[float, float]]:
    """Per episode of ``keygen eval``'s seeding on every knife of ``split``, at its first observation."""
    from keygen.evaluation.rollout import EnvSpec, episode_seed, make_env
    from keygen.objects.splits import SPLIT_SIZES

    out = []
    for object_id in range(SPLIT_SIZES[split]):
        env = make_env(EnvSpec("knife", split, setting), object_id)
        try:
            for k in range(episodes):
                obs, _ = env.reset(seed=episode_seed(seed, object_id, k))
                anchors = env.task.anchors_world(env.model, env.data)
                out.append(
                    errors(
                        obs[OBJECT_CLOUD_KEY],
                        obs[OBJECT_CLOUD_IDS_KEY],
                        anchors["slot_axis"],
                        anchors["slot_center_top"],
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
    p.add_argument("dataset", nargs="?", default=None, help="a knife recording (keygen demos --task knife)")
    p.add_argument("--max-episodes", type=int, default=None, help="only the recording's first N episodes")
    p.add_argument("--split", default=None, help="fresh scenes of this split's knives instead")
    p.add_argument("--setting", default="hard", choices=["easy", "hard"])
    p.add_argument("--episodes", type=int, default=4, help="scenes per knife with --split")
    p.add_argument("--seed", type=int, default=1000, help="keygen eval's --seed for the scenes")
    p.add_argument("--out", default=None, help="JSON file to write")
    args = p.parse_args(argv)
    if (args.dataset is None) == (args.split is None):
        p.error("give a recording or --split, not both")
    if args.dataset is not None:
        store = EpisodeStore(args.dataset, "r", max_episodes=args.max_episodes)
        if "anchors/slot_axis" not in store.keys():
            raise SystemExit(f"{args.dataset} has no slot anchors: is it a knife recording?")
        pairs, source = measure_recording(store), str(args.dataset)
    else:
        pairs = measure_split(args.split, args.setting, args.episodes, args.seed)
        source = f"{args.split} split, {args.setting}, {args.episodes} scenes per knife, seed {args.seed}"
    values = {
        "axis_error_deg": np.array([a for a, _ in pairs]),
        "centre_error_cm": np.array([c for _, c in pairs]),
    }
    result = {
        "source": source,
        "episodes": len(pairs),
        "wrong_axis": int((values["axis_error_deg"] > 45).sum()),
        "host": platform.node(),
        **{name: summarise(v) for name, v in values.items()},
    }
    print(f"target frame on the first observation of {result['episodes']} episodes: {source}")
    print(f"| {'measure':<22} | median | p95   | max   |")
    print(f"|{'-' * 24}|--------|-------|-------|")
    for name in values:
        s = result[name]
        print(f"| {name:<22} | {s['median']:6.2f} | {s['p95']:5.2f} | {s['max']:5.2f} |")
    print(f"slot taken along the wrong axis of the block (error > 45 degrees): {result['wrong_axis']}")
    if args.out:
        atomic_write_json(args.out, result)
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
