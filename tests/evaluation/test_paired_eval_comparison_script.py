"""benchmarks/paired_eval_comparison.py: pairing by (object, episode), the exact McNemar p-value,
groups, and refusing evaluations whose scenes differ."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


@pytest.fixture(scope="module")
def m(load_benchmark_script):
    return load_benchmark_script("paired_eval_comparison")


def _write(path: Path, successes: dict[tuple[int, int], bool], seed_offset: int = 0) -> Path:
    lines = [
        json.dumps(
            {
                "object_id": o,
                "episode": e,
                "seed": 100 * o + e + seed_offset,
                "success": s,
                "failure": None if s else "timeout",
            }
        )  # fmt: skip
        for (o, e), s in successes.items()
    ]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_mcnemar_matches_hand_computed_values(m) -> None:
    assert m.mcnemar_exact(0, 0) == 1.0
    assert m.mcnemar_exact(3, 3) == 1.0
    assert m.mcnemar_exact(0, 5) == pytest.approx(2 / 32)  # 2 * (1/2)^5
    assert m.mcnemar_exact(1, 4) == pytest.approx(2 * 6 / 32)  # 2 * (C(5,0) + C(5,1)) / 2^5
    assert m.mcnemar_exact(4, 16) == m.mcnemar_exact(16, 4)


def test_pairs_by_object_and_episode_with_groups(m, tmp_path: Path) -> None:
    a = {(o, e): e < 2 for o in range(3) for e in range(4)}  # 2 of 4 per object
    b = {(o, e): (e < 3 if o == 2 else e < 2) for o in range(3) for e in range(4)}  # object 2: one more
    b[(0, 0)] = False  # and one fewer on object 0
    b[(0, 3)] = True
    first = m.read_episodes(_write(tmp_path / "a.jsonl", a))
    res = m.compare(first, m.read_episodes(_write(tmp_path / "b.jsonl", b)), {"last": [2]})
    assert res["overall"]["successes"] == [6, 7]
    assert (res["overall"]["only_first"], res["overall"]["only_second"]) == (1, 2)
    assert res["by_object"]["0"]["successes"] == [2, 2] and res["by_object"]["0"]["only_first"] == 1
    assert res["groups"]["last"]["successes"] == [2, 3] and res["groups"]["last"]["episodes"] == 4
    assert res["failures"] == [{"timeout": 6}, {"timeout": 5}]


def test_refuses_evaluations_of_different_scenes(m, tmp_path: Path) -> None:
    a = m.read_episodes(_write(tmp_path / "a.jsonl", {(0, 0): True}))
    b = m.read_episodes(_write(tmp_path / "b.jsonl", {(0, 0): True}, seed_offset=1))
    with pytest.raises(SystemExit, match="different seeds"):
        m.compare(a, b, {})
    c = m.read_episodes(_write(tmp_path / "c.jsonl", {(1, 0): True}))
    with pytest.raises(SystemExit, match="share no"):
        m.compare(a, c, {})
    (tmp_path / "bad.jsonl").write_text("{}\n")
    with pytest.raises(SystemExit, match="not a `keygen eval` episode record"):
        m.read_episodes(tmp_path / "bad.jsonl")
