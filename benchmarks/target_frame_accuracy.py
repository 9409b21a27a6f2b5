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

import numpy as np

from _first_step_accuracy import FirstStepCheck, finish, run
from keygen.policies.target_frame import measure_target_frame, target_points


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


CHECK = FirstStepCheck(
    task="knife",
    noun="knife",
    anchors=("slot_axis", "slot_center_top"),
    measures=("axis_error_deg", "centre_error_cm"),
    errors=errors,
    title="target frame",
)


def main(argv: list[str] | None = None) -> dict:
    result, values, out = run(CHECK, __doc__.split("\n")[0], argv)
    result["wrong_axis"] = int((values["axis_error_deg"] > 45).sum())
    print(f"slot taken along the wrong axis of the block (error > 45 degrees): {result['wrong_axis']}")
    return finish(result, out)


if __name__ == "__main__":
    main()
