"""Compare success counts of evaluations that cannot be paired episode by episode.

Run: ``.venv/bin/python benchmarks/unpaired_success_comparison.py NAME=SOURCE [NAME=SOURCE ...]
[--out benchmarks/results/NAME.json]``, where each SOURCE is either a ``keygen eval`` episode file
(``RUN/eval/<split>_<setting>_scale<s>_seed<S>.jsonl``) or a count ``SUCCESSES/EPISODES`` taken from
a stored summary (for a run whose episode file no longer exists).

``benchmarks/paired_eval_comparison.py`` is the stronger test when both episode files exist and share
seeds: it looks only at the episodes the two policies disagree on. When one side survives only as a
count, the two evaluations are treated as independent samples: each gets its 95% Wilson interval, and
every later entry is compared with the first by a two-sided Fisher exact test on the 2x2 table
(successes, failures). The unpaired test ignores that the scenes were the same, so it is conservative:
a difference it calls significant would be at least as clear paired. An analysis of stored results,
not a benchmark of speed.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from scipy.stats import fisher_exact

from keygen.evaluation.stats import wilson_interval


def read_counts(source: str) -> tuple[int, int]:
    """``(successes, episodes)`` from ``K/N`` or from a ``keygen eval`` episode file."""
    k, sep, n = source.partition("/")
    if sep and k.strip().isdigit() and n.strip().isdigit():
        successes, episodes = int(k), int(n)
        if episodes < 1 or not 0 <= successes <= episodes:
            raise SystemExit(f"{source!r}: need 0 <= successes <= episodes and episodes >= 1")
        return successes, episodes
    path = Path(source)
    if not path.is_file():
        raise SystemExit(f"{source!r} is neither SUCCESSES/EPISODES nor an existing episode file")
    successes = episodes = 0
    for line_no, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            successes += bool(json.loads(line)["success"])
        except (ValueError, KeyError) as err:
            raise SystemExit(f"{path}:{line_no}: not a `keygen eval` episode record ({err})") from err
        episodes += 1
    if not episodes:
        raise SystemExit(f"{path} holds no episodes")
    return successes, episodes


def _entry(text: str) -> tuple[str, str]:
    name, sep, source = text.partition("=")
    if not sep or not name or not source:
        raise argparse.ArgumentTypeError(f"expected NAME=SOURCE, got {text!r}")
    return name, source


def compare(entries: list[tuple[str, str]]) -> dict:
    rows = []
    for name, source in entries:
        k, n = read_counts(source)
        rows.append(
            {
                "name": name,
                "source": source,
                "successes": k,
                "episodes": n,
                "success_rate": k / n,
                "ci95": list(wilson_interval(k, n)),
            }
        )
    ref = rows[0]
    for row in rows[1:]:
        table = [
            [row["successes"], row["episodes"] - row["successes"]],
            [ref["successes"], ref["episodes"] - ref["successes"]],
        ]
        row["vs_first"] = {
            "difference_points": round(100 * (row["success_rate"] - ref["success_rate"]), 2),
            "fisher_p": float(fisher_exact(table, alternative="two-sided").pvalue),
        }
    return {"reference": ref["name"], "rows": rows}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("entries", type=_entry, nargs="+", help="NAME=SOURCE; the first is the reference")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args()
    if len(args.entries) < 2:
        raise SystemExit("give at least two NAME=SOURCE entries")
    result = compare(args.entries)
    print(f"| evaluation | successes | rate | 95% CI | vs {result['reference']} | Fisher p |")
    print("|---|---|---|---|---|---|")
    for row in result["rows"]:
        lo, hi = row["ci95"]
        vs = row.get("vs_first")
        diff = f"{vs['difference_points']:+.1f} points" if vs else "reference"
        pval = f"{vs['fisher_p']:.3g}" if vs else ""
        print(
            f"| {row['name']} | {row['successes']}/{row['episodes']} | {100 * row['success_rate']:.1f}% "
            f"| {100 * lo:.1f}-{100 * hi:.1f} | {diff} | {pval} |"
        )
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1) + "\n")
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
