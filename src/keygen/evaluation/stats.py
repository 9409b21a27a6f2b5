"""Success-rate statistics."""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable
from typing import Any

from keygen.errors import InvalidParameterError


def wilson_interval(successes: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """The Wilson score interval of a binomial proportion (95% by default); (0, 1) when n is 0."""
    if n < 0 or successes < 0 or successes > n:
        raise InvalidParameterError(f"need 0 <= successes <= n, got {successes} of {n}")
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def summarize(results: Iterable[dict[str, Any]], group_key: str = "object_id") -> dict[str, Any]:
    """Overall success rate with a 95% Wilson interval, per-group breakdown and failure counts."""
    results = list(results)
    n = len(results)
    wins = sum(bool(r["success"]) for r in results)
    groups: dict[str, list[dict]] = {}
    for r in results:
        groups.setdefault(str(r[group_key]), []).append(r)
    by_group = {}
    for key in sorted(groups, key=lambda k: (len(k), k)):
        rs = groups[key]
        g_wins = sum(bool(r["success"]) for r in rs)
        by_group[key] = {
            "episodes": len(rs),
            "successes": g_wins,
            "success_rate": g_wins / len(rs),
            "failures": dict(Counter(r["failure"] for r in rs if not r["success"])),
        }
    return {
        "episodes": n,
        "successes": wins,
        "success_rate": wins / n if n else 0.0,
        "ci95": list(wilson_interval(wins, n)),
        f"by_{group_key.removesuffix('_id')}": by_group,
        "failures": dict(Counter(r["failure"] for r in results if not r["success"])),
    }
