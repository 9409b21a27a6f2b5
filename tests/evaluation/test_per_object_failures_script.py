"""benchmarks/per_object_failures.py: per-object counts and failure reasons, the instances' shape
parameters, Spearman's rho on constructed cases, and refusing mixed or malformed inputs."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from keygen.objects.splits import instance_params


@pytest.fixture(scope="module")
def m(load_benchmark_script):
    return load_benchmark_script("per_object_failures")


def _write(path: Path, outcomes: dict[int, list[str | None]], task: str = "pour") -> Path:
    """One record per entry: None is a success, a string the failure reason (test split)."""
    records = [
        {"task": task, "split": "test", "object_id": o, "episode": e, "success": not f, "failure": f}
        for o, fails in outcomes.items()
        for e, f in enumerate(fails)
    ]
    lines = [json.dumps(r) for r in records]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_spearman_on_constructed_cases(m) -> None:
    assert m.spearman([1, 2, 3, 4], [10, 20, 30, 40]) == pytest.approx(1.0)
    assert m.spearman([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)
    assert m.spearman([1, 2, 3], [5, 5, 5]) is None  # constant: undefined
    assert m.spearman([1, 2], [1, 2]) is None  # too few objects
    # ties share their mean rank: ranks (0.5, 0.5, 2) against (0, 1, 2)
    assert m.spearman([1, 1, 2], [1, 2, 3]) == pytest.approx(0.8660254, abs=1e-6)


def test_counts_failures_and_parameters_per_object(m, tmp_path, capsys) -> None:
    a = _write(tmp_path / "a.jsonl", {0: [None, "held_by_body", "held_by_body"], 2: ["timeout", None, None]})
    b = _write(tmp_path / "b.jsonl", {0: ["dropped"] * 3, 2: [None] * 3})
    out = tmp_path / "summary.json"
    m.main([str(a), str(b), "--names", "world,yaw", "--params", "style,radius_bottom", "--out", str(out)])
    summary = json.loads(out.read_text())
    assert (summary["task"], summary["category"], summary["split"]) == ("pour", "mug", "test")
    first, second = summary["objects"]
    assert first["object_id"] == 0 and second["object_id"] == 2
    assert first["runs"]["world"] == {"episodes": 3, "successes": 1, "failures": {"held_by_body": 2}}
    assert first["runs"]["yaw"] == {"episodes": 3, "successes": 0, "failures": {"dropped": 3}}
    assert second["runs"]["world"]["successes"] == 2 and second["runs"]["yaw"]["successes"] == 3
    assert first["params"]["radius_bottom"] == instance_params("mug", "test", 0)["radius_bottom"]
    assert summary["reference"]["params"]["style"] == instance_params("mug", "policy", 0)["style"]
    assert set(summary["spearman_success_vs_param"]["world"]) == {"radius_bottom"}  # style is not numeric
    printed = capsys.readouterr().out
    assert "| 0 | " in printed and "held_by_body 2" in printed and "(reference)" in printed


def test_refuses_mixed_cells_unknown_parameters_and_bad_names(m, tmp_path) -> None:
    pour = _write(tmp_path / "pour.jsonl", {0: [None]})
    knife = _write(tmp_path / "knife.jsonl", {0: [None]}, task="knife")
    with pytest.raises(SystemExit, match="mix tasks"):
        m.main([str(pour), str(knife), "--names", "p,k"])
    with pytest.raises(SystemExit, match="no parameters"):
        m.main([str(pour), "--params", "blade_length"])
    with pytest.raises(SystemExit, match="distinct names"):
        m.main([str(pour), str(pour), "--names", "same,same"])
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"object_id": 0}\n')
    with pytest.raises(SystemExit, match="not a `keygen eval` episode record"):
        m.main([str(bad)])
