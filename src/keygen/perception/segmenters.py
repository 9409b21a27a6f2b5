"""Segmentation as an interface: per-view label images of the task-relevant objects.

A segmenter turns rendered views into (V, H, W) integer labels: 0 for everything that is not a
task object, k >= 1 for task object k. The default, :class:`SimulatorSegmenter`, reads the
simulator's exact per-pixel geom ids; a model-based segmenter (e.g. a detector plus a mask model
run on ``rgb``) implements the same call and plugs in unchanged.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np


class Segmenter(Protocol):
    def __call__(self, rgb: np.ndarray | None, depth: np.ndarray, geom_ids: np.ndarray) -> np.ndarray:
        """(V, H, W) int labels, 0 = not a task object."""


class SimulatorSegmenter:
    """Exact masks from the simulator: a lookup from geom id to object label."""

    def __init__(self, geom_labels: np.ndarray) -> None:
        # geom_labels[g] is the label of geom g; one extra slot at the end catches id -1 (no geom).
        self._lookup = np.concatenate([np.asarray(geom_labels, dtype=np.int32), [0]])

    def __call__(self, rgb: np.ndarray | None, depth: np.ndarray, geom_ids: np.ndarray) -> np.ndarray:
        return self._lookup[geom_ids]
