"""Benchmark stages: presets, fingerprints, reuse of unchanged stages, rerun of changed ones, resume."""

import json
from pathlib import Path

import pytest

from keygen.errors import InvalidParameterError
from keygen.evaluation.pipeline import (
    KEYPOINT_POLICIES,
    PRESETS,
    PipelineError,
    StageFunctions,
    fingerprint,
    get_preset,
    run_benchmark,
    run_stage,
)
from keygen.evaluation.report import benchmark_markdown


class FakeStages:
    """Stage functions of the real shape that write small files and count their calls."""

    def __init__(self):
        self.calls: list[str] = []
        self.fail_eval_once = False

    def demos(self, task, preset, path, progress):
        self.calls.append(f"demos/{task}")
        path.mkdir(parents=True, exist_ok=True)
        (path / "n").write_text(str(preset.demos))
        return {"path": str(path), "episodes": preset.demos}

    def keypoints(self, category, preset, out_dir, progress):
        self.calls.append(f"keypoints/{category}")
        out_dir.mkdir(parents=True, exist_ok=True)
        return {"run_dir": str(out_dir)}

    def policy(self, task, policy, preset, dataset, keypoints, out_dir, progress):
        self.calls.append(f"policy/{task}/{policy}")
        assert Path(dataset).exists()
        assert (keypoints is not None) == (policy in KEYPOINT_POLICIES)
        out_dir.mkdir(parents=True, exist_ok=True)
        return {"run_dir": str(out_dir)}

    def evaluate(self, run_dir, split, setting, object_ids, preset, jsonl, progress):
        self.calls.append(f"eval/{split}/{setting}")
        jsonl.parent.mkdir(parents=True, exist_ok=True)
        with jsonl.open("a") as f:
            f.write("{}\n")  # a partial output that must survive a resume
        if self.fail_eval_once:
            self.fail_eval_once = False
            raise KeyboardInterrupt
        n = len(object_ids) * preset.episodes_per_object
        wins = n // 2
        return {"episodes": n, "successes": wins, "success_rate": wins / n, "ci95": [0.1, 0.9]}

    def functions(self):
        return StageFunctions(self.demos, self.keypoints, self.policy, self.evaluate)


def small(**kw):
    return get_preset("quick", **({"demos": 2, "unseen_ids": (0, 1), "workers": 1} | kw))


def run(fake, out, preset=None, tasks=("stack",), policies=("keygen", "dp3")):
    return run_benchmark(preset or small(), out, tasks, policies, functions=fake.functions(), progress=False)


def test_presets_are_validated():
    assert PRESETS["paper"].demos == 100 and PRESETS["paper"].episodes_per_object == 20
    assert PRESETS["paper"].unseen_ids == tuple(range(12)) and PRESETS["paper"].image_size == 128
    assert PRESETS["quick"].image_size == 64 and PRESETS["quick"].num_points == 512
    with pytest.raises(InvalidParameterError, match="preset"):
        get_preset("huge")
    with pytest.raises(InvalidParameterError, match="unseen_ids"):
        small(unseen_ids=(12,))
    with pytest.raises(InvalidParameterError, match="demos"):
        small(demos=0)
    with pytest.raises(InvalidParameterError, match="unknown preset fields"):
        small(rollouts=3)
    assert small(episodes_per_object=None).episodes_per_object == PRESETS["quick"].episodes_per_object


def test_fingerprint_is_stable_and_order_free():
    assert fingerprint({"a": 1, "b": [1, 2]}) == fingerprint({"b": [1, 2], "a": 1})
    assert fingerprint({"a": 1}) != fingerprint({"a": 2})


def test_results_and_full_reuse(tmp_path):
    fake = FakeStages()
    report = run(fake, tmp_path)
    assert fake.calls[:3] == ["demos/stack", "keypoints/bowl", "policy/stack/keygen"]
    assert len(fake.calls) == 1 + 1 + 2 + 2 * 4  # demos, keypoints, 2 policies, 2 x (2 splits x 2 settings)
    rows = report["results"]
    assert len(rows) == 8 and {r["split"] for r in rows} == {"seen", "unseen"}
    assert all({"task", "policy", "split", "setting", "success_rate", "ci95"} <= set(r) for r in rows)
    seen = next(r for r in rows if r["split"] == "seen")
    assert seen["episodes"] == 1  # one training instance x 1 rollout
    assert json.loads((tmp_path / "demos" / "stack" / "stage.json").read_text())["status"] == "done"

    fake.calls.clear()
    again = run(fake, tmp_path)
    assert fake.calls == [] and all(s["reused"] for s in again["stages"])
    assert again["results"] == report["results"]


def test_a_changed_input_reruns_that_stage_and_those_after_it(tmp_path):
    fake = FakeStages()
    run(fake, tmp_path)
    fake.calls.clear()
    run(fake, tmp_path, small(episodes_per_object=2))
    assert fake.calls and all(c.startswith("eval/") for c in fake.calls) and len(fake.calls) == 8

    fake.calls.clear()
    run(fake, tmp_path, small(episodes_per_object=2, demos=3))
    assert "demos/stack" in fake.calls and "keypoints/bowl" not in fake.calls
    assert {"policy/stack/keygen", "policy/stack/dp3"} <= set(fake.calls) and len(fake.calls) == 11
    assert (tmp_path / "demos" / "stack" / "demos.zarr" / "n").read_text() == "3"


def test_the_yaw_frame_variant_runs_where_the_object_has_a_heading_and_skips_round_bowls(tmp_path):
    fake = FakeStages()
    report = run(fake, tmp_path, tasks=("pour", "stack"), policies=("keygen", "keygen_yaw"))
    trained = [c for c in fake.calls if c.startswith("policy/")]
    assert trained == ["policy/pour/keygen", "policy/pour/keygen_yaw", "policy/stack/keygen"]
    assert {(r["task"], r["policy"]) for r in report["results"]} == {
        ("pour", "keygen"),
        ("pour", "keygen_yaw"),
        ("stack", "keygen"),
    }
    assert not (tmp_path / "policies" / "stack" / "keygen_yaw").exists()
    table = benchmark_markdown(report)
    yaw_row = next(line for line in table.splitlines() if line.startswith("| KeyGen, keypoint yaw frame"))
    # pour easy/hard measured; stacking has no cell for it (an en dash)
    assert yaw_row.count("–") == 2 and yaw_row.count("n=") == 2


def test_expert_options_enter_only_their_tasks_demo_fingerprint(tmp_path):
    assert PRESETS["paper"].expert_options == {"pour": {"grasp": "pinch"}} == PRESETS["quick"].expert_options
    fake = FakeStages()
    run(fake, tmp_path, tasks=("stack", "pour"), policies=("dp3",))
    fake.calls.clear()
    preset = small(expert_options={"pour": {"grasp": "auto"}})
    run(fake, tmp_path, preset, tasks=("stack", "pour"), policies=("dp3",))
    assert "demos/pour" in fake.calls and "demos/stack" not in fake.calls  # stack's stages are reused
    stage = json.loads((tmp_path / "demos" / "pour" / "stage.json").read_text())
    assert stage["inputs"]["expert_options"] == {"grasp": "auto"}
    with pytest.raises(InvalidParameterError, match="unknown tasks"):
        small(expert_options={"juggle": {}})


def test_another_physics_revision_records_the_demonstrations_again(tmp_path, monkeypatch):
    import keygen.evaluation.pipeline as pipeline

    fake = FakeStages()
    run(fake, tmp_path, policies=("dp3",))
    stage = json.loads((tmp_path / "demos" / "stack" / "stage.json").read_text())
    assert stage["inputs"]["physics"] == pipeline.PHYSICS_VERSION
    fake.calls.clear()
    monkeypatch.setattr(pipeline, "PHYSICS_VERSION", pipeline.PHYSICS_VERSION + 1)
    run(fake, tmp_path, policies=("dp3",))
    # Demonstrations, the policy trained on them and every evaluation of it run again.
    assert fake.calls[0] == "demos/stack" and "policy/stack/dp3" in fake.calls
    assert sum(c.startswith("eval/") for c in fake.calls) == 4


def test_an_interrupted_stage_resumes_with_its_partial_outputs(tmp_path):
    fake = FakeStages()
    fake.fail_eval_once = True
    with pytest.raises(KeyboardInterrupt):
        run(fake, tmp_path, policies=("dp3",))
    cell = tmp_path / "eval" / "stack" / "dp3" / "seen_easy"
    assert json.loads((cell / "stage.json").read_text())["status"] == "running"
    fake.calls.clear()
    run(fake, tmp_path, policies=("dp3",))
    assert fake.calls[0] == "eval/policy/easy"  # demos and training reused
    assert (cell / "results.jsonl").read_text().count("\n") == 2  # kept, not cleared


def test_run_stage_refuses_a_foreign_folder(tmp_path):
    (tmp_path / "mine.txt").write_text("x")
    with pytest.raises(PipelineError, match="stage.json"):
        run_stage("x", tmp_path, {"a": 1}, lambda: {})


def test_bad_task_list(tmp_path):
    with pytest.raises(InvalidParameterError, match="tasks"):
        run(FakeStages(), tmp_path, tasks=("juggle",))


def test_a_resumed_stage_is_marked_in_its_record_and_the_table(tmp_path):
    fake = FakeStages()
    fake.fail_eval_once = True
    with pytest.raises(KeyboardInterrupt):
        run(fake, tmp_path, policies=("dp3",))
    report = run(fake, tmp_path, policies=("dp3",))
    resumed = [s["name"] for s in report["stages"] if s["resumed"]]
    assert resumed == ["eval/stack/dp3/seen_easy"]
    record = json.loads((tmp_path / "eval" / "stack" / "dp3" / "seen_easy" / "stage.json").read_text())
    assert record["resumed"] is True and record["status"] == "done"
    again = run(fake, tmp_path, policies=("dp3",))  # reused later, still marked
    assert [s["name"] for s in again["stages"] if s["resumed"] and s["reused"]] == resumed
    text = benchmark_markdown(again)
    assert "| eval/stack/dp3/seen_easy | yes (resumed) |" in text
    assert "| eval/stack/dp3/seen_hard | yes |" in text
    assert "the finishing invocation only." in text
