"""Roll out one policy until the gripper closes, then another: which policy does which stage better.

Run: ``.venv/bin/python benchmarks/pour_handover_eval.py APPROACH_RUN CARRY_RUN --split policy
--object-ids 1,2,3,4 --episodes-per-object 40 --seed 1000 --workers 2 --out FILE.jsonl``.

A diagnostic (docs/benchmark.md, "Pouring under revision 2: noise on the hand's position in
training"): two pouring policies that fail at different stages (one misses the grasp more often, the
other pours beside the box more often) are combined, the first driving until it commands the gripper
closed, the second from then on. Both see every observation. The second takes over the first's yaw
frame, measured on the mug at rest at the episode's first query, and plans afresh from the current
history; both runs must therefore share their frame's reference (same recording and keypoints),
which is checked. The episodes are the ones ``keygen eval`` draws for the same split, setting and
seed, so the JSONL pairs with either policy's own evaluation (``benchmarks/paired_eval_comparison.py``).
"""

from __future__ import annotations

import argparse
import json
import sys
from functools import partial
from pathlib import Path

import numpy as np

GRIPPER = 9  # action index of the gripper command (0 = closed, 1 = open)
CLOSED_BELOW = 0.5  # a command under this counts as closing the gripper


class HandoverRunner:
    """``approach`` acts until it commands the gripper closed; ``carry`` acts from the next step on."""

    def __init__(self, approach, carry):
        self.approach, self.carry = approach, carry
        self.handed_over = False

    def reset(self, seed: int | None = None) -> None:
        self.approach.reset(seed=seed)
        self.carry.reset(seed=seed)
        self.handed_over = False

    def act(self, obs) -> np.ndarray:
        if self.handed_over:
            return self.carry.act(obs)
        self.carry.observe(obs)  # keeps the history the carrier plans from when it takes over
        action = self.approach.act(obs)
        if float(action[GRIPPER]) < CLOSED_BELOW:
            self.handed_over = True
            # The carrier's frame is the one measured on the mug at rest, not on the mug in hand.
            self.carry.yaw_frame = self.approach.yaw_frame
        return action


def make_handover_runner(run_dir: str, carry_dir: str) -> HandoverRunner:
    """Runner factory for ``keygen.evaluation.evaluate.evaluate``: ``run_dir`` approaches."""
    from keygen.policies.runtime import load_runner

    return HandoverRunner(load_runner(run_dir, device="cpu"), load_runner(carry_dir, device="cpu"))


def check_same_frame_reference(approach: Path, carry: Path) -> None:
    """Both runs must measure the yaw frame against the same reference, or a handed-over frame means
    something else to the carrier."""
    refs = [run / "yaw_reference.json" for run in (approach, carry)]
    missing = [str(r) for r in refs if not r.is_file()]
    if missing:
        raise SystemExit(f"not yaw-frame policy runs (no {', '.join(missing)})")
    if json.loads(refs[0].read_text()) != json.loads(refs[1].read_text()):
        raise SystemExit(f"{approach} and {carry} measure their yaw frames against different references")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("approach", type=Path, help="policy run that drives until the gripper closes")
    p.add_argument("carry", type=Path, help="policy run that drives from then on")
    p.add_argument("--split", default="policy")
    p.add_argument("--setting", default="hard", choices=["easy", "hard"])
    p.add_argument("--object-ids", default=None, help="comma-separated ids (default: the whole split)")
    p.add_argument("--episodes-per-object", type=int, default=20)
    p.add_argument("--seed", type=int, default=1000)
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--out", type=Path, required=True, help="JSONL of episode results (resumes)")
    args = p.parse_args(argv)
    check_same_frame_reference(args.approach, args.carry)

    from keygen.evaluation.evaluate import evaluate

    ids = None if args.object_ids is None else [int(i) for i in args.object_ids.split(",")]
    summary = evaluate(
        str(args.approach),
        args.split,
        args.setting,
        args.episodes_per_object,
        args.seed,
        args.workers,
        args.out,
        object_ids=ids,
        runner_factory=partial(make_handover_runner, carry_dir=str(args.carry)),
    )
    summary |= {"approach": str(args.approach), "carry": str(args.carry)}
    print(json.dumps(summary, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
