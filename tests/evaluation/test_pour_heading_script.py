"""benchmarks/pour_success_by_handle_yaw.py: sectors around the easy heading, headings rebuilt from
episode seeds (the easy setting's handle points along +x), and refusing non-pouring input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from keygen.evaluation.rollout import episode_seed


@pytest.fixture(scope="module")
def m(load_benchmark_script):
    return load_benchmark_script("pour_success_by_handle_yaw")


def test_sector_zero_is_centred_on_the_easy_heading(m) -> None:
    assert m.sector_of(0.0, 8) == 0
    assert m.sector_of(np.deg2rad(22.0), 8) == 0 and m.sector_of(np.deg2rad(-22.0), 8) == 0
    assert m.sector_of(np.deg2rad(23.0), 8) == 1
    assert m.sector_of(np.deg2rad(-23.0), 8) == 7
    assert m.sector_of(np.deg2rad(180.0), 8) == 4 and m.sector_of(np.deg2rad(-180.0), 8) == 4
    assert m.sector_of(np.deg2rad(90.0), 4) == 1


def test_easy_episodes_land_in_sector_zero_and_are_counted(m, tmp_path) -> None:
    records = [
        {"task": "pour", "split": "test", "setting": "easy", "scale": 1.0, "object_id": 0, "episode": k}
        | {"seed": episode_seed(1000, 0, k), "success": k == 0, "failure": None if k == 0 else "timeout"}
        for k in range(2)
    ]
    path = tmp_path / "easy.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in records))
    out = tmp_path / "summary.json"
    m.main([str(path), "--names", "p", "--sectors", "4", "--out", str(out)])
    summary = json.loads(out.read_text())
    first = summary["sectors"][0]["runs"]["p"]
    assert (first["episodes"], first["successes"], first["failures"]) == (2, 1, {"timeout": 1})
    assert all(row["runs"]["p"]["episodes"] == 0 for row in summary["sectors"][1:])
    assert all(abs(h) < 1.0 for h in summary["heading_deg_by_episode"].values())  # +x, within a degree


def test_refuses_other_tasks_and_bad_arguments(m, tmp_path) -> None:
    knife = tmp_path / "knife.jsonl"
    rec = {"task": "knife", "split": "test", "setting": "hard", "scale": 1.0, "object_id": 0, "seed": 1}
    knife.write_text(json.dumps(rec | {"success": False}) + "\n")
    with pytest.raises(SystemExit, match="only pouring"):
        m.main([str(knife)])
    with pytest.raises(SystemExit, match="sectors"):
        m.main([str(knife), "--sectors", "1"])
