"""Spread of the procedural families: per category, the range of each main dimension."""

from __future__ import annotations

from keygen.objects.splits import SPLIT_SIZES, get_generator, split_params


def dimension_ranges(
    category: str, seed: int = 0, splits: tuple[str, ...] = ("train", "test", "policy")
) -> dict:
    """{dimension: {"min", "max", "ratio"}} over the instances of the given splits (metres)."""
    gen = get_generator(category)
    dims: dict[str, list[float]] = {}
    for split in splits:
        for params in split_params(category, split, seed, SPLIT_SIZES[split]):
            for name, value in gen.main_dimensions(params).items():
                dims.setdefault(name, []).append(float(value))
    return {
        name: {"min": min(v), "max": max(v), "ratio": max(v) / min(v) if min(v) > 0 else float("inf")}
        for name, v in dims.items()
    }


def ranges_markdown(ranges: dict[str, dict]) -> str:
    lines = ["| category | dimension | min (mm) | max (mm) | max/min |", "|---|---|---|---|---|"]
    for category, dims in ranges.items():
        for name, r in dims.items():
            lines.append(
                f"| {category} | {name} | {1000 * r['min']:.1f} | {1000 * r['max']:.1f} | {r['ratio']:.2f} |"
            )
    return "\n".join(lines)
