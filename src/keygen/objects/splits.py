"""Deterministic train / test / policy splits of the procedural categories.

Every instance's parameters come from its own seed stream, ``SeedSequence([seed, category,
split, index])``, so instance ``i`` of a split never depends on how many others were drawn.
Styles (handle shapes, blade profiles, wall profiles) are dealt out in turn so every split
covers every style. The ``policy`` split holds the instances policies are trained on: index 0
is the single training instance of the paper's protocol, indices 1-4 join it for the
data-efficiency study. Policy instances are drawn from their own stream, so they are distinct
from ``train`` (keypoint training) and from ``test`` (never seen by keypoints or policies).
"""

from __future__ import annotations

import importlib
from typing import Any

import numpy as np

from keygen.errors import InvalidParameterError
from keygen.objects.asset import CATEGORIES, Asset
from keygen.objects.generators.base import CategoryGenerator

SPLITS = ("train", "test", "policy")
SPLIT_SIZES = {"train": 30, "test": 12, "policy": 5}
DEFAULT_SEED = 0

_GENERATORS = {
    "mug": "keygen.objects.generators.mug:MugGenerator",
    "knife": "keygen.objects.generators.knife:KnifeGenerator",
    "bowl": "keygen.objects.generators.bowl:BowlGenerator",
}
_SPLIT_CODES = {"train": 1, "test": 2, "policy": 3}
_CATEGORY_CODES = {"mug": 11, "knife": 12, "bowl": 13}


def get_generator(category: str) -> CategoryGenerator:
    if category not in _GENERATORS:
        raise InvalidParameterError(f"category must be one of {CATEGORIES}, got {category!r}")
    module, name = _GENERATORS[category].split(":")
    return getattr(importlib.import_module(module), name)()


def _check(category: str, split: str, index: int) -> None:
    if category not in _GENERATORS:
        raise InvalidParameterError(f"category must be one of {CATEGORIES}, got {category!r}")
    if split not in SPLITS:
        raise InvalidParameterError(f"split must be one of {SPLITS}, got {split!r}")
    if index < 0:
        raise InvalidParameterError(f"instance index must be >= 0, got {index}")


def instance_params(category: str, split: str, index: int, seed: int = DEFAULT_SEED) -> dict[str, Any]:
    """The parameter dict of instance ``index`` of ``split`` (any index, not only the default count)."""
    _check(category, split, index)
    gen = get_generator(category)
    rng = np.random.default_rng(
        np.random.SeedSequence([int(seed), _CATEGORY_CODES[category], _SPLIT_CODES[split], int(index)])
    )
    # Offset the style rotation per split so small splits do not all start on the same style.
    style = gen.styles[(index + _SPLIT_CODES[split]) % len(gen.styles)]
    return gen.sample_params(rng, style=style)


def instance_id(category: str, split: str, index: int) -> str:
    return f"{category}-{split}-{index:03d}"


def make_instance(category: str, split: str, index: int, seed: int = DEFAULT_SEED) -> Asset:
    """Build instance ``index`` of a split at scale 1."""
    params = instance_params(category, split, index, seed)
    asset = get_generator(category).build(params, instance_id(category, split, index))
    asset.split = split
    return asset


def split_params(category: str, split: str, seed: int = DEFAULT_SEED, count: int | None = None) -> list[dict]:
    count = SPLIT_SIZES[split] if count is None else count
    return [instance_params(category, split, i, seed) for i in range(count)]


def param_key(params: dict[str, Any]) -> tuple:
    """A hashable, rounding-free key of a parameter dict (for disjointness checks)."""
    return tuple(sorted((k, tuple(v) if isinstance(v, list) else v) for k, v in params.items()))
