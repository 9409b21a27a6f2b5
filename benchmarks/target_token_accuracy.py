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

import numpy as np

from _first_step_accuracy import FirstStepCheck, finish, run
from keygen.policies.target_frame import target_points
from keygen.policies.target_token import measure_target


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


CHECK = FirstStepCheck(
    task="pour",
    noun="mug",
    anchors=("container_center", "container_half_extents"),
    measures=("centre_error_cm", "top_error_cm", "wall_cm"),
    errors=errors,
    title="target token",
)


def main(argv: list[str] | None = None) -> dict:
    result, _, out = run(CHECK, __doc__.split("\n")[0], argv)
    return finish(result, out)


if __name__ == "__main__":
    main()
