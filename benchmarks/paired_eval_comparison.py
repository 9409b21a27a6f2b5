"""Compare two policies' evaluations episode by episode (same objects, same episode seeds).

Run: ``.venv/bin/python benchmarks/paired_eval_comparison.py A.jsonl B.jsonl [A2.jsonl B2.jsonl ...]
[--names a,b] [--group wide=0,5,8,10] [--out benchmarks/results/NAME.json]``, where each file is the
``RUN/eval/<split>_<setting>_scale<s>_seed<S>.jsonl`` that ``keygen eval`` writes. More than one pair
(say the two policies trained with a second seed, or scored on a second set of objects) pools the
pairs into one comparison: an episode is paired only with its own pair's counterpart, and the test
sums the disagreements over the pairs (a stratified McNemar test). Per-object rows and groups add
up an object id over the pairs: read them only when the pairs score the same objects.

``keygen eval`` draws episode k of object o from the same seed for every policy, so two runs of the
same split, setting and ``--seed`` face identical scenes and can be paired. Two independent 95%
intervals overlap long before a difference stops being real; the paired test looks only at the
episodes where the policies disagree (exact two-sided McNemar: under "no difference" each
disagreement is a fair coin). Prints, overall, per object and for each ``--group`` of object ids:
successes of each policy, the disagreements and the p-value; and each policy's failure reasons.
Writes the same as JSON. An analysis of stored results, not a benchmark of speed.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from math import comb
from pathlib import Path

from keygen.evaluation.stats import wilson_interval


def read_episodes(path: Path) -> dict[tuple[int, int], dict]:
    """``(object_id, episode) -> record`` of one evaluation file."""
    out = {}
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if line.strip():
            try:
                rec = json.loads(line)
                out[(int(rec["object_id"]), int(rec["episode"]))] = rec
            except (ValueError, KeyError) as err:
                raise SystemExit(f"{path}:{n}: not a `keygen eval` episode record ({err})") from err
    if not out:
        raise SystemExit(f"{path} holds no episodes")
    return out


def mcnemar_exact(only_a: int, only_b: int) -> float:
    """Two-sided exact McNemar p-value from the two disagreement counts."""
    n = only_a + only_b
    if n == 0:
        return 1.0
    tail = sum(comb(n, i) for i in range(min(only_a, only_b) + 1)) / 2**n
    return min(1.0, 2.0 * tail)


def paired(a: dict, b: dict, keys: list[tuple[int, int]]) -> dict:
    sa = sum(bool(a[k]["success"]) for k in keys)
    sb = sum(bool(b[k]["success"]) for k in keys)
    only_a = sum(bool(a[k]["success"]) and not b[k]["success"] for k in keys)
    only_b = sum(bool(b[k]["success"]) and not a[k]["success"] for k in keys)
    return {
        "episodes": len(keys),
        "successes": [sa, sb],
        "ci95": [list(wilson_interval(sa, len(keys))), list(wilson_interval(sb, len(keys)))],
        "only_first": only_a,
        "only_second": only_b,
        "mcnemar_p": mcnemar_exact(only_a, only_b),
    }


def pool(pairs: list[tuple[dict, dict]]) -> tuple[dict, dict]:
    """Several paired evaluations as one: each key gains its pair's index, so episodes pair only
    within their own pair; ``compare`` then sees one evaluation per side (object ids stay first)."""
    if len(pairs) == 1:
        return pairs[0]
    first, second = {}, {}
    for i, (a, b) in enumerate(pairs):
        first.update({(*k, i): rec for k, rec in a.items()})
        second.update({(*k, i): rec for k, rec in b.items()})
    return first, second


def compare(a: dict, b: dict, groups: dict[str, list[int]]) -> dict:
    """Paired comparison of two evaluations on the episodes both hold (same seeds required)."""
    keys = sorted(set(a) & set(b))
    if not keys:
        raise SystemExit("the two evaluations share no (object, episode)")
    for k in keys:
        if a[k].get("seed") != b[k].get("seed"):
            raise SystemExit(f"object {k[0]} episode {k[1]} has different seeds: not the same scenes")
    objects = sorted({k[0] for k in keys})
    result = {
        "overall": paired(a, b, keys),
        "by_object": {str(o): paired(a, b, [k for k in keys if k[0] == o]) for o in objects},
        "groups": {},
        "failures": [
            dict(Counter(d[k]["failure"] for k in keys if not d[k]["success"]).most_common()) for d in (a, b)
        ],
    }
    for name, ids in groups.items():
        sel = [k for k in keys if k[0] in ids]
        result["groups"][name] = {
            "object_ids": ids,
            **paired(a, b, sel),
            "failures": [
                dict(Counter(d[k]["failure"] for k in sel if not d[k]["success"]).most_common())
                for d in (a, b)
            ],
        }
    return result


def _group(text: str) -> tuple[str, list[int]]:
    name, sep, ids = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"--group takes NAME=ID,ID,..., got {text!r}")
    return name, [int(i) for i in ids.split(",") if i]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("files", type=Path, nargs="+", help="A.jsonl B.jsonl, then more pairs to pool")
    p.add_argument("--names", default="first,second", help="two labels, comma-separated")
    p.add_argument("--group", type=_group, action="append", default=[], help="NAME=ID,ID,... (repeatable)")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args()
    names = args.names.split(",")
    if len(names) != 2:
        raise SystemExit("--names takes exactly two labels")
    if len(args.files) % 2:
        raise SystemExit(f"give the evaluation files in pairs (first, second, ...), got {len(args.files)}")
    pairs = [
        (read_episodes(args.files[i]), read_episodes(args.files[i + 1])) for i in range(0, len(args.files), 2)
    ]
    result = compare(*pool(pairs), dict(args.group))
    result = {"files": [str(f) for f in args.files], "names": names, "pairs": len(pairs), **result}

    rows = [("all", result["overall"])]
    rows += [(f"object {o}", r) for o, r in result["by_object"].items()]
    rows += [(f"{n} {g['object_ids']}", g) for n, g in result["groups"].items()]
    print(f"| episodes | n | {names[0]} | {names[1]} | only {names[0]} | only {names[1]} | McNemar p |")
    print("|---|---|---|---|---|---|---|")
    for label, r in rows:
        sa, sb = r["successes"]
        print(
            f"| {label} | {r['episodes']} | {sa} | {sb} | {r['only_first']} | {r['only_second']} "
            f"| {r['mcnemar_p']:.3g} |"
        )
    for name, fails in zip(names, result["failures"], strict=True):
        print(f"failures, {name}: {fails}")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1) + "\n")
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
