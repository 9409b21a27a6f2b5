"""benchmarks/unpaired_success_comparison.py: counts from K/N or episode files, Fisher's exact test
against hand-computed values, and clear errors on bad sources."""

from __future__ import annotations

import json
from math import comb
from pathlib import Path

import pytest


@pytest.fixture(scope="module")
def m(load_benchmark_script):
    return load_benchmark_script("unpaired_success_comparison")


def _episodes(path: Path, successes: list[bool]) -> Path:
    rows = [{"object_id": 0, "episode": i, "success": s} for i, s in enumerate(successes)]
    path.write_text("\n".join(json.dumps(r) for r in rows) + "\n\n")
    return path


def test_counts_from_text_and_from_an_episode_file(m, tmp_path: Path) -> None:
    assert m.read_counts("7/20") == (7, 20)
    assert m.read_counts(str(_episodes(tmp_path / "e.jsonl", [True, False, True, True]))) == (3, 4)


@pytest.mark.parametrize("bad", ["5/4", "0/0", "missing.jsonl"])
def test_bad_sources_are_refused(m, bad: str) -> None:
    with pytest.raises(SystemExit):
        m.read_counts(bad)


def test_a_file_that_is_not_an_evaluation_is_refused(m, tmp_path: Path) -> None:
    path = tmp_path / "x.jsonl"
    path.write_text('{"object_id": 0}\n')
    with pytest.raises(SystemExit, match="not a `keygen eval` episode record"):
        m.read_counts(str(path))


def test_fisher_p_matches_the_hypergeometric_sum(m) -> None:
    # 4/4 against 0/4: the only tables as extreme have all four successes on one side,
    # each with probability 1 / C(8, 4); two-sided p = 2 / 70.
    result = m.compare([("a", "4/4"), ("b", "0/4")])
    assert result["reference"] == "a"
    row = result["rows"][1]
    assert row["vs_first"]["difference_points"] == -100.0
    assert row["vs_first"]["fisher_p"] == pytest.approx(2 / comb(8, 4))
    # Equal rates are no evidence of a difference.
    same = m.compare([("a", "10/20"), ("b", "10/20")])
    assert same["rows"][1]["vs_first"]["fisher_p"] == pytest.approx(1.0)


def test_every_row_carries_a_wilson_interval_around_its_rate(m) -> None:
    for row in m.compare([("a", "145/240"), ("b", "126/240"), ("c", "0/10")])["rows"]:
        lo, hi = row["ci95"]
        assert 0.0 <= lo <= row["success_rate"] <= hi <= 1.0
