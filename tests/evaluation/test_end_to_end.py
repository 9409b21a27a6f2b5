"""A tiny real run of the whole pipeline on stacking: demonstrations -> keypoints -> policy -> evaluation.

Real stages, tiny sizes: two demonstrations at 32 px / 256 points, a keypoint detector and a KeyGen
policy trained for a few steps, two evaluation episodes (the seen instance and one unseen instance,
easy setting) cut to a short time limit. It checks that the stages fit together and that a rerun
reuses every stage, not that the policy succeeds.
"""

import importlib.util
import json

import pytest

from keygen.evaluation.pipeline import get_preset, run_benchmark
from keygen.evaluation.report import write_report


def _missing(*modules: str) -> list[str]:
    out = []
    for name in modules:
        try:
            if importlib.util.find_spec(name) is None:
                out.append(name)
        except ModuleNotFoundError:
            out.append(name)
    return out


MISSING = _missing("keygen.policies.runtime", "keygen.policies.training", "keygen.keypoints.training")
pytestmark = pytest.mark.skipif(bool(MISSING), reason=f"not built yet: {MISSING}")

TINY_KEYPOINTS = dict(
    num_instances=2,
    scans_per_instance=2,
    image_size=48,
    scan_points=256,
    num_points=128,
    canon_steps=3,
    canon_batch=2,
    detector_steps=3,
    pair_batch=2,
    checkpoint_every=3,
    log_every=1,
    train_ablation=False,
)


def test_tiny_stack_pipeline_end_to_end(tmp_path):
    preset = get_preset(
        "quick",
        demos=2,
        image_size=32,
        num_points=256,
        unseen_ids=(0,),
        settings=("easy",),
        episodes_per_object=1,
        workers=1,
        eval_max_steps=8,
        keypoint_overrides=TINY_KEYPOINTS,
        policy_overrides={"steps": 4, "batch_size": 4},
    )
    report = run_benchmark(preset, tmp_path, tasks=("stack",), policies=("keygen",), progress=False)
    rows = report["results"]
    assert [(r["split"], r["setting"]) for r in rows] == [("seen", "easy"), ("unseen", "easy")]
    assert sum(r["episodes"] for r in rows) == 2
    assert all(0.0 <= r["success_rate"] <= 1.0 and len(r["ci95"]) == 2 for r in rows)
    lines = (
        (tmp_path / "eval" / "stack" / "keygen" / "unseen_easy" / "results.jsonl").read_text().splitlines()
    )
    episode = json.loads(lines[0])
    assert episode["task"] == "stack" and episode["split"] == "test" and 1 <= episode["steps"] <= 8

    md, _ = write_report(report, tmp_path)
    assert "| Method | Stacking easy |" in md.read_text()
    again = run_benchmark(preset, tmp_path, tasks=("stack",), policies=("keygen",), progress=False)
    assert all(s["reused"] for s in again["stages"]) and again["results"] == rows
