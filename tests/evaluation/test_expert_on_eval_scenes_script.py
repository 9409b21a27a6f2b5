"""benchmarks/expert_on_eval_scenes.py: the expert faces exactly the scenes of ``keygen eval`` (same
seeds, same reset state whatever the rendering size), its records pair with an evaluation's, and a
rerun resumes."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from keygen.errors import InvalidParameterError
from keygen.evaluation.rollout import EnvSpec, episode_seed, make_env
from keygen.sim import PHYSICS_VERSION


@pytest.fixture(scope="module")
def m(load_benchmark_script):
    return load_benchmark_script("expert_on_eval_scenes")


def test_jobs_use_the_evaluations_episode_seeds(m) -> None:
    jobs = m.plan_jobs([3, 7], 2, 1000)
    assert [(o, k) for o, k, _ in jobs] == [(3, 0), (3, 1), (7, 0), (7, 1)]
    assert all(s == episode_seed(1000, o, k) for o, k, s in jobs)


def test_options_parse_as_json_where_they_can(m) -> None:
    assert m.parse_option("grasp=pinch") == ("grasp", "pinch")
    assert m.parse_option("lift=0.05") == ("lift", 0.05)
    assert m.parse_option("slow=true") == ("slow", True)
    with pytest.raises(InvalidParameterError, match="key=value"):
        m.parse_option("pinch")
    assert m.policy_label({}) == "expert"
    assert m.policy_label({"grasp": "pinch", "a": 1}) == "expert[a=1,grasp=pinch]"


def test_a_torn_last_line_is_ignored_on_resume(m, tmp_path) -> None:
    path = tmp_path / "e.jsonl"
    row = {"task": "pour", "policy": "expert", "split": "test", "setting": "hard", "scale": 1.0}
    row |= {"object_id": 2, "episode": 5, "seed": 7, "success": True, "physics": PHYSICS_VERSION}
    path.write_text(json.dumps(row) + "\n" + '{"object_id": 2, "epi')
    assert m.load_done(path) == {(2, 5): row}
    # An episode of another physics revision is not done: it runs again.
    path.write_text(json.dumps(row | {"physics": PHYSICS_VERSION - 1}) + "\n")
    assert m.load_done(path) == {}


def test_rendering_size_does_not_change_the_scene(m) -> None:
    # The script renders small images to save time; the physics state after reset must be the one
    # `keygen eval` (128 px, 1024 points) starts from.
    seed = episode_seed(1000, 1, 4)
    states = []
    for size, points in ((128, 1024), (32, 64)):
        env = make_env(EnvSpec("stack", "test", "hard", image_size=size, num_points=points), 1)
        env.reset(seed=seed)
        states.append(np.array(env.data.qpos))
        env.close()
    np.testing.assert_array_equal(states[0], states[1])


def test_one_episode_writes_an_eval_shaped_record_and_resumes(m, tmp_path, monkeypatch, capsys) -> None:
    out = tmp_path / "expert.jsonl"
    argv = ["x", "--task", "stack", "--split", "test", "--object-ids", "2", "--episodes-per-object", "1"]
    argv += ["--image-size", "32", "--num-points", "64", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", argv)
    m.main()
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(rows) == 1
    row = rows[0]
    assert row["policy"] == "expert" and row["object_id"] == 2 and row["episode"] == 0
    assert row["seed"] == episode_seed(1000, 2, 0) and isinstance(row["success"], bool)
    assert row["physics"] == PHYSICS_VERSION
    summary = json.loads(out.with_suffix(".json").read_text())
    assert summary["episodes"] == 1 and summary["by_object"]["2"]["episodes"] == 1
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["episodes"] == 1
    m.main()  # nothing left to run: the file keeps its one record
    assert len(out.read_text().splitlines()) == 1
    # Another expert's options into the same file are refused rather than mixed.
    monkeypatch.setattr(sys, "argv", argv + ["--expert-option", "x=1"])
    with pytest.raises(InvalidParameterError, match="another --out"):
        m.main()
