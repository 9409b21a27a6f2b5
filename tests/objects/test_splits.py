"""The splits: sizes, determinism, disjointness, and every instance of every split sound."""

import numpy as np
import pytest

from keygen.errors import InvalidParameterError
from keygen.objects.asset import CATEGORIES
from keygen.objects.splits import (
    SPLIT_SIZES,
    get_generator,
    instance_params,
    make_instance,
    param_key,
    split_params,
)
from keygen.objects.stats import dimension_ranges


@pytest.mark.parametrize("category", CATEGORIES)
def test_split_sizes_and_disjoint_parameters(category):
    assert SPLIT_SIZES["train"] >= 30 and SPLIT_SIZES["test"] >= 12 and SPLIT_SIZES["policy"] == 5
    keys = {split: [param_key(p) for p in split_params(category, split)] for split in SPLIT_SIZES}
    train = set(keys["train"])
    assert len(train) == SPLIT_SIZES["train"]
    assert not train & set(keys["test"]), "a test instance's parameters appear in train"
    assert not train & set(keys["policy"])
    assert not set(keys["test"]) & set(keys["policy"])


@pytest.mark.parametrize("category", CATEGORIES)
def test_splits_are_deterministic_and_seeded(category):
    assert instance_params(category, "test", 3) == instance_params(category, "test", 3)
    assert instance_params(category, "test", 3, seed=1) != instance_params(category, "test", 3, seed=0)
    # instance i does not depend on how many were drawn before it
    assert split_params(category, "train", count=5)[4] == instance_params(category, "train", 4)


@pytest.mark.parametrize("category", CATEGORIES)
def test_every_style_in_train_and_test(category):
    styles = set(get_generator(category).styles)
    for split in ("train", "test"):
        assert {p["style"] for p in split_params(category, split)} == styles


@pytest.mark.parametrize("category", CATEGORIES)
def test_main_dimensions_spread_at_least_1_5(category):
    for name, r in dimension_ranges(category).items():
        assert r["ratio"] >= 1.5, f"{category} {name}: {r}"


@pytest.mark.parametrize("category", CATEGORIES)
@pytest.mark.parametrize("split", list(SPLIT_SIZES))
def test_every_generated_instance_is_sound(category, split):
    """Watertight visual, convex collision parts, anchors where they belong: all instances."""
    gen = get_generator(category)
    for index in range(SPLIT_SIZES[split]):
        asset = make_instance(category, split, index)
        assert asset.split == split
        assert gen.validate(asset) == [], f"{asset.instance_id}: {gen.validate(asset)}"


def test_bad_split_arguments():
    with pytest.raises(InvalidParameterError):
        instance_params("cup", "train", 0)
    with pytest.raises(InvalidParameterError):
        instance_params("mug", "val", 0)
    with pytest.raises(InvalidParameterError):
        instance_params("mug", "train", -1)
    assert np.isfinite(
        list(get_generator("bowl").main_dimensions(instance_params("bowl", "test", 0)).values())
    ).all()
