"""The Table-I-shaped Markdown report and its JSON."""

import json

import pytest

from keygen.errors import InvalidParameterError
from keygen.evaluation.report import benchmark_markdown, format_cell, results_table, write_report
from keygen.evaluation.stats import wilson_interval


def row(task, policy, split, setting, wins, n):
    return {
        "task": task,
        "policy": policy,
        "split": split,
        "setting": setting,
        "success_rate": wins / n,
        "ci95": list(wilson_interval(wins, n)),
        "episodes": n,
        "failures": {} if wins == n else {"timeout": n - wins},
    }


RESULTS = [
    row(t, p, s, st, w, 20)
    for (t, w) in (("pour", 15), ("stack", 20))
    for p in ("dp3", "keygen")
    for s in ("unseen", "seen")
    for st in ("hard", "easy")
]


def test_cell_format_known_value():
    assert format_cell(row("pour", "keygen", "seen", "easy", 15, 20)) == "75% [53-89] n=20"
    assert format_cell(None) == "–"


def test_table_shape_rows_methods_columns_tasks_by_setting():
    lines = results_table(RESULTS).splitlines()
    assert lines[0] == "| Method | Pouring easy | Pouring hard | Stacking easy | Stacking hard |"
    # Seen block first, methods in a fixed order (KeyGen before DP3), whatever the input order.
    assert (
        lines[2].startswith("| **Seen") and lines[3].startswith("| KeyGen |") and lines[4].startswith("| DP3")
    )
    assert lines[5].startswith("| **Unseen") and len(lines) == 8
    assert all(line.count("|") == 6 for line in lines)
    assert "100% [84-100] n=20" in lines[3]


def test_missing_cells_are_dashes_and_bad_rows_are_refused():
    table = results_table(
        [row("knife", "keygen", "unseen", "hard", 1, 2), row("knife", "dp3", "unseen", "easy", 0, 2)]
    )
    assert "–" in table and "Collect Knife easy" in table
    with pytest.raises(InvalidParameterError, match="ci95"):
        results_table(
            [{"task": "pour", "policy": "keygen", "split": "seen", "setting": "easy", "success_rate": 1}]
        )


def test_report_files(tmp_path):
    report = {"preset": {"name": "quick", "demos": 10}, "results": RESULTS, "stages": [], "seconds": 1.5}
    md, js = write_report(report, tmp_path / "out")
    assert "Smoke test, not a result" in md.read_text() and "## Failures" in md.read_text()
    assert json.loads(js.read_text())["results"] == RESULTS
    assert "Smoke test" not in benchmark_markdown(report | {"preset": {"name": "paper"}})
