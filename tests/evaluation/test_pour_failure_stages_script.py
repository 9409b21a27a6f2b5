"""benchmarks/pour_failure_stages.py: every pouring episode lands in exactly one stage, decided by
the task's own metrics, and bad files are refused with a clear message."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


@pytest.fixture(scope="module")
def m(load_benchmark_script):
    return load_benchmark_script("pour_failure_stages")


def _rec(obj: int, success: bool, failure: str | None, held: float = 1.0, left: float = 0.0) -> dict:
    metrics = {"held_by_handle": held, "left_mug_fraction": left, "poured_fraction": 0.0}
    return {"task": "pour", "object_id": obj, "success": success, "failure": failure, "metrics": metrics}


# One constructed episode per stage, in the order of STAGES.
CASES = [
    _rec(0, True, None, left=1.0),
    _rec(0, False, "held_by_body", held=0.0),
    _rec(1, False, "dropped", left=0.3),
    _rec(1, False, "timeout", held=0.0),
    _rec(1, False, "timeout", held=1.0, left=0.0),
    _rec(2, False, "timeout", held=1.0, left=0.75),
    _rec(2, False, "knife_off_table"),
]


def _write(path: Path, rows: list[dict]) -> Path:
    path.write_text("\n".join(json.dumps(r) for r in rows) + "\n\n")
    return path


def test_each_constructed_episode_gets_its_stage(m) -> None:
    assert [m.stage(r) for r in CASES] == list(m.STAGES)


def test_summary_counts_every_episode_once_overall_and_per_object(m, tmp_path: Path) -> None:
    rows = m.read_pour_records(_write(tmp_path / "a.jsonl", CASES))
    run = m.summarise({"a": rows})["runs"]["a"]
    assert run["episodes"] == len(CASES) == sum(run["stages"].values())
    assert all(v == 1 for v in run["stages"].values())
    assert run["by_object"]["1"] == {
        s: int(s in ("dropped", "timeout_not_gripped", "timeout_not_poured")) for s in m.STAGES
    }
    assert sum(sum(c.values()) for c in run["by_object"].values()) == len(CASES)


def test_files_that_are_not_pouring_evaluations_are_refused(m, tmp_path: Path) -> None:
    knife = dict(CASES[0], task="knife")
    with pytest.raises(SystemExit, match="pouring evaluations only"):
        m.read_pour_records(_write(tmp_path / "k.jsonl", [knife]))
    no_metric = dict(CASES[3], metrics={"held_by_handle": 1.0})  # a timeout is split by its metrics
    with pytest.raises(SystemExit, match="lack"):
        m.read_pour_records(_write(tmp_path / "n.jsonl", [no_metric]))
    (tmp_path / "bad.jsonl").write_text("{not json\n")
    with pytest.raises(SystemExit, match="not a `keygen eval` episode record"):
        m.read_pour_records(tmp_path / "bad.jsonl")
    with pytest.raises(SystemExit, match="holds no episodes"):
        m.read_pour_records(_write(tmp_path / "empty.jsonl", []))


def test_a_diverged_simulation_without_metrics_is_other(m, tmp_path: Path) -> None:
    unstable = dict(_rec(3, False, "physics_unstable"), metrics={})
    rows = m.read_pour_records(_write(tmp_path / "u.jsonl", [CASES[0], unstable]))
    assert [m.stage(r) for r in rows] == ["success", "other"]
