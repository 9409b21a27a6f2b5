"""How far each pouring episode got: the stage a failure stopped at, from the stored episode records.

Run: ``.venv/bin/python benchmarks/pour_failure_stages.py A.jsonl [B.jsonl ...] [--names a,b]
[--out benchmarks/results/NAME.json]``, where each file is a pouring ``keygen eval`` episode file
(``RUN/eval/<split>_<setting>_scale<s>_seed<S>.jsonl``).

The task names three failures: ``held_by_body``, ``dropped`` and ``timeout``. A timeout hides very
different episodes (a hand that never closed on the handle, a mug lifted but never tipped, a pour that
went beside the box), and which of them dominate decides what to improve. The pour task's episode
metrics are enough to tell them apart without rolling anything out again (``keygen.sim.tasks.pour``:
``held_by_handle`` is 1 once both jaws held handle parts and no finger touched the body,
``left_mug_fraction`` the share of spheres that ever left the cavity, ``poured_fraction`` the share in
the box at the end). Every episode gets one stage:

- ``success``;
- ``held_by_body``, ``dropped``: the task's own failures;
- ``timeout_not_gripped``: the time ran out before both jaws held the handle;
- ``timeout_not_poured``: gripped by the handle, and no sphere ever left the mug (never lifted, or
  never tipped far enough);
- ``timeout_poured_outside``: spheres left the mug, but too few ended in the box (the pour missed the
  opening, or stopped short);
- ``other``: any other failure reason (``physics_unstable``, a simulation that diverged, whose
  record holds no metrics).

Prints one row per run and per object and writes JSON. An analysis of stored results, not a
benchmark of speed.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

STAGES = (
    "success",
    "held_by_body",
    "dropped",
    "timeout_not_gripped",
    "timeout_not_poured",
    "timeout_poured_outside",
    "other",
)
_METRICS = ("held_by_handle", "left_mug_fraction")


def read_pour_records(path: Path) -> list[dict]:
    """The episode records of a pouring evaluation; stops at the first line that is not one."""
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
            task, metrics = rec["task"], rec["metrics"]
            rec["object_id"], rec["success"] = int(rec["object_id"]), bool(rec["success"])
            # Only a timeout is split by its metrics; a diverged simulation (physics_unstable) has none.
            needs = not rec["success"] and rec.get("failure") == "timeout"
            missing = [k for k in _METRICS if k not in metrics] if needs else []
        except (ValueError, KeyError, TypeError) as err:
            raise SystemExit(f"{path}:{n}: not a `keygen eval` episode record ({err})") from err
        if task != "pour":
            raise SystemExit(f"{path}:{n}: a {task!r} episode; this analysis reads pouring evaluations only")
        if missing:
            raise SystemExit(f"{path}:{n}: the episode's metrics lack {missing}")
        rows.append(rec)
    if not rows:
        raise SystemExit(f"{path} holds no episodes")
    return rows


def stage(rec: dict) -> str:
    """One episode's stage (see the module docstring)."""
    if rec["success"]:
        return "success"
    failure = rec.get("failure")
    if failure in ("held_by_body", "dropped"):
        return failure
    if failure != "timeout":
        return "other"
    metrics = rec["metrics"]
    if metrics["held_by_handle"] < 0.5:
        return "timeout_not_gripped"
    if metrics["left_mug_fraction"] <= 0.0:
        return "timeout_not_poured"
    return "timeout_poured_outside"


def summarise(runs: dict[str, list[dict]]) -> dict:
    out = {"stages": list(STAGES), "runs": {}}
    for name, rows in runs.items():
        by_object: dict[int, Counter] = {}
        for r in rows:
            by_object.setdefault(r["object_id"], Counter())[stage(r)] += 1
        total = sum(by_object.values(), Counter())  # each episode staged once
        out["runs"][name] = {
            "episodes": len(rows),
            "stages": {s: total.get(s, 0) for s in STAGES},
            "by_object": {str(obj): {s: c.get(s, 0) for s in STAGES} for obj, c in sorted(by_object.items())},
        }
    return out


def print_table(summary: dict) -> None:
    short = {s: s.replace("timeout_", "t/") for s in STAGES}
    print(f"{'run':<24} {'episodes':>8} " + " ".join(f"{short[s]:>16}" for s in STAGES))
    for name, run in summary["runs"].items():
        print(f"{name:<24} {run['episodes']:>8} " + " ".join(f"{run['stages'][s]:>16}" for s in STAGES))
    for name, run in summary["runs"].items():
        print(f"\n{name}, per object:")
        for obj, counts in run["by_object"].items():
            cells = ", ".join(f"{short[s]} {v}" for s, v in counts.items() if v)
            print(f"  object {obj:>3}: {cells}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("files", nargs="+", type=Path, help="pouring `keygen eval` episode files")
    parser.add_argument("--names", default=None, help="comma-separated run names (default: file stems)")
    parser.add_argument("--out", type=Path, default=None, help="write the summary as JSON here")
    args = parser.parse_args()
    names = args.names.split(",") if args.names else [p.stem for p in args.files]
    if len(names) != len(args.files) or len(set(names)) != len(names):
        raise SystemExit("--names needs one distinct name per file")
    for path in args.files:
        if not path.is_file():
            raise SystemExit(f"{path} is not a file")
    summary = summarise({n: read_pour_records(p) for n, p in zip(names, args.files, strict=True)})
    summary["files"] = {n: str(p) for n, p in zip(names, args.files, strict=True)}
    print_table(summary)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(summary, indent=2) + "\n")
        print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
