"""Benchmark reports: a Markdown table shaped like the paper's Table I, and the JSON beside it.

Rows are methods, in two blocks (seen instances, then unseen instances); columns are tasks x
{easy, hard}. Each cell is the success rate with its 95% Wilson interval and the episode count, e.g.
``75% [53-89] n=20``. Unseen cells pool every unseen object's episodes; with equal episodes per
object this equals the mean of the per-object rates, the paper's "averaged over the 12".
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from keygen.atomic import atomic_write_text
from keygen.errors import InvalidParameterError

TASK_TITLES = {"pour": "Pouring", "knife": "Collect Knife", "stack": "Stacking"}
POLICY_TITLES = {
    "keygen": "KeyGen",
    "keygen_no_kp": "KeyGen w/o keypoints",
    "keygen_scene": "KeyGen w/o object-centric",
    "keygen_yaw": "KeyGen, keypoint yaw frame (beyond the paper)",
    "dp3": "DP3",
}
SPLIT_TITLES = {
    "seen": "Seen instances (in-distribution)",
    "unseen": "Unseen instances (out-of-distribution)",
}
REQUIRED = ("task", "policy", "split", "setting", "success_rate", "ci95")


def _reuse_label(stage: dict[str, Any]) -> str:
    label = "yes" if stage.get("reused") else "no"
    return f"{label} (resumed)" if stage.get("resumed") else label


def format_cell(row: dict[str, Any] | None) -> str:
    """``75% [53-89] n=20``; an en dash where nothing was measured."""
    if row is None:
        return "–"
    lo, hi = row["ci95"]
    n = f" n={row['episodes']}" if "episodes" in row else ""
    return f"{100 * row['success_rate']:.0f}% [{100 * lo:.0f}-{100 * hi:.0f}]{n}"


def _check(results: list[dict[str, Any]]) -> None:
    for i, row in enumerate(results):
        missing = [k for k in REQUIRED if k not in row]
        if missing:
            raise InvalidParameterError(f"result {i} lacks {missing}; each result needs {list(REQUIRED)}")


def _ordered(values, preferred) -> list[str]:
    present = list(dict.fromkeys(values))
    return [v for v in preferred if v in present] + [v for v in present if v not in preferred]


def results_table(results: list[dict[str, Any]]) -> str:
    """The Table-I-shaped Markdown table of a list of result rows."""
    _check(results)
    tasks = _ordered([r["task"] for r in results], list(TASK_TITLES))
    policies = _ordered([r["policy"] for r in results], list(POLICY_TITLES))
    settings = _ordered([r["setting"] for r in results], ["easy", "hard"])
    splits = _ordered([r["split"] for r in results], list(SPLIT_TITLES))
    cells = {(r["task"], r["policy"], r["split"], r["setting"]): r for r in results}
    columns = [(t, s) for t in tasks for s in settings]
    head = "| Method | " + " | ".join(f"{TASK_TITLES.get(t, t)} {s}" for t, s in columns) + " |"
    lines = [head, "|---|" + "---|" * len(columns)]
    for split in splits:
        lines.append(f"| **{SPLIT_TITLES.get(split, split)}** |" + " |" * len(columns))
        for policy in policies:
            row = [format_cell(cells.get((t, policy, split, s))) for t, s in columns]
            lines.append(f"| {POLICY_TITLES.get(policy, policy)} | " + " | ".join(row) + " |")
    return "\n".join(lines)


def failures_table(results: list[dict[str, Any]]) -> str:
    """Failure reasons per cell (task, method, split, setting), for the cells that had failures."""
    lines = ["| task | method | split | setting | failures |", "|---|---|---|---|---|"]
    for r in results:
        if r.get("failures"):
            reasons = ", ".join(f"{k} x{v}" for k, v in sorted(r["failures"].items()))
            lines.append(
                f"| {r['task']} | {POLICY_TITLES.get(r['policy'], r['policy'])} | {r['split']} | "
                f"{r['setting']} | {reasons} |"
            )
    return "\n".join(lines) if len(lines) > 2 else "No failures."


def benchmark_markdown(report: dict[str, Any]) -> str:
    """The whole Markdown report: protocol line, the table, failures, stage wall times."""
    preset = report.get("preset", {})
    name = preset.get("name", "?")
    parts = [f"# KeyGen benchmark ({name} preset)", ""]
    if name == "quick":
        parts += [
            "> **Smoke test, not a result.** The quick preset trains on a handful of demonstrations for a "
            "few minutes and evaluates 1-2 rollouts per object; it checks that the pipeline runs end to "
            "end. Use `--preset paper` for numbers.",
            "",
        ]
    if preset:
        parts += [
            f"Training: {preset.get('demos')} demonstrations ({preset.get('demo_setting')} setting) on "
            f"{preset.get('demo_split')} instance(s) {preset.get('demo_object_ids')}; keypoints preset "
            f"`{preset.get('keypoint_preset')}`, policy preset `{preset.get('policy_preset')}`; "
            f"{preset.get('image_size')} px views, {preset.get('num_points')} points. Evaluation: seen = the "
            f"training instance(s), unseen = test instances {preset.get('unseen_ids')}, "
            f"{preset.get('episodes_per_object')} rollout(s) per object, evaluation seed "
            f"{preset.get('eval_seed')}. Cells: success rate [95% Wilson interval] n=episodes.",
            "",
        ]
    parts += [results_table(report["results"]), "", "## Failures", "", failures_table(report["results"])]
    stages = report.get("stages") or []
    if stages:
        parts += ["", "## Stages", "", "| stage | reused | seconds |", "|---|---|---|"]
        parts += [f"| {s['name']} | {_reuse_label(s)} | {s.get('seconds', '')} |" for s in stages]
        if any(s.get("resumed") for s in stages):
            note = "(resumed): finished by a later invocation than the one that started it; its seconds count"
            parts += ["", note, "the finishing invocation only."]
    if "seconds" in report:
        parts += ["", f"Total wall time of this invocation: {report['seconds']} s."]
    return "\n".join(parts) + "\n"


def write_report(report: dict[str, Any], out_dir: str | Path) -> tuple[Path, Path]:
    """``benchmark.md`` and ``benchmark.json`` in ``out_dir`` (written atomically); returns both paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    md, js = out_dir / "benchmark.md", out_dir / "benchmark.json"
    for path, text in ((md, benchmark_markdown(report)), (js, json.dumps(report, indent=1, default=str))):
        atomic_write_text(path, text)
    return md, js
