"""A tiny trained mug keypoint run, shared by the keypoint tests (training it takes a few seconds)."""

import pytest
import torch

from keygen.keypoints.training import KeypointTrainConfig, train_keypoints

# Small enough to train in seconds on one core; big enough to exercise every stage, checkpoints included.
TINY = dict(
    num_instances=2,
    scans_per_instance=3,
    canon_steps=12,
    detector_steps=12,
    canon_batch=8,
    pair_batch=4,
    num_points=64,
    width=32,
    hidden=16,
    num_keypoints=6,
    image_size=48,
    scan_points=256,
    checkpoint_every=5,
    log_every=4,
    train_ablation=True,
)


def _tiny_config(category="mug", **overrides):
    return KeypointTrainConfig.preset("quick", category, **(TINY | overrides))


@pytest.fixture(scope="session")
def tiny_config():
    """`tiny_config(category="mug", **overrides)`: the tiny run's training config."""
    return _tiny_config


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """A finished run. Tests that change files in it must work on a copy."""
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("kp") / "run"
    train_keypoints(_tiny_config(), out, progress=False)
    return out
