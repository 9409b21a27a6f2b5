"""Diffusion policies (KeyGen's DiT policy, its ablations, a DP3-style baseline) and their trainer."""

from keygen.policies.checkpoint import PolicyCheckpointError, load_policy
from keygen.policies.config import (
    POLICY_NAMES,
    TASK_KEYPOINT_OBJECTS,
    PolicyConfig,
    keypoint_categories,
    make_policy_config,
)
from keygen.policies.diffusion import EMA, DiffusionPolicy
from keygen.policies.features import KeypointSource
from keygen.policies.normalizer import Normalizer
from keygen.policies.runtime import PolicyRunner, load_runner
from keygen.policies.training import PRESETS, TrainConfig, train_policy

__all__ = [
    "EMA",
    "POLICY_NAMES",
    "PRESETS",
    "TASK_KEYPOINT_OBJECTS",
    "DiffusionPolicy",
    "KeypointSource",
    "Normalizer",
    "PolicyCheckpointError",
    "PolicyConfig",
    "PolicyRunner",
    "TrainConfig",
    "keypoint_categories",
    "load_policy",
    "load_runner",
    "make_policy_config",
    "train_policy",
]
