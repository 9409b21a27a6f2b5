"""Alternatives to the learned detector, scored on the same scans by :mod:`keygen.keypoints.evaluate`.

- :class:`FPSCanonicalBaseline` ("fps_canonical"): no learned detector. The cloud is canonicalised by the
  trained canonicaliser, then K points are chosen by farthest-point sampling started at a canonically
  defined point (the point of largest canonical x, ties broken by z then y), and they are indexed in
  that FPS order. A fixed rule, so its indices carry meaning only as far as the FPS order is stable.
- the detector trained without the canonicaliser ("no_canonicalizer"):
  ``KeypointExtractor.load(run, detector="detector_nocanon")``.

Each method maps a list of (N, 3) clouds to ``(keypoints (B, K, 3), rotation class (B,) or None)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from keygen.geometry.clouds import farthest_point_sample
from keygen.geometry.rotations import octahedral_group
from keygen.keypoints.dataset import resample
from keygen.keypoints.extractor import KeypointExtractor
from keygen.keypoints.models import Canonicalizer

__all__ = ["FPSCanonicalBaseline", "extractor_method"]


class FPSCanonicalBaseline:
    """Farthest-point-sampled points in the predicted canonical frame, ordered canonically."""

    def __init__(self, canonicalizer: Canonicalizer, num_keypoints: int, num_points: int) -> None:
        self.canonicalizer = canonicalizer.eval()
        self.num_keypoints, self.num_points = int(num_keypoints), int(num_points)

    @torch.no_grad()
    def __call__(self, clouds: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        x = np.stack([resample(c, self.num_points) for c in clouds])  # (B, n, 3)
        _, index, _ = self.canonicalizer.predict(torch.from_numpy(x))
        index = index.numpy()
        out = []
        for cloud, c in zip(x, index, strict=True):
            can = cloud.astype(np.float64) @ octahedral_group()[c]  # (n, 3): R^T p per row
            start = int(np.lexsort((can[:, 1], can[:, 2], can[:, 0]))[-1])  # largest x, then z, then y
            _, chosen = farthest_point_sample(can, self.num_keypoints, start_index=start, return_index=True)
            out.append(cloud[chosen])
        return np.stack(out).astype(np.float32), index


def extractor_method(extractor: KeypointExtractor):
    """An extractor as a method: keypoints and, when it canonicalises, the classifier's class (the
    rotation itself may be yaw-refined, see :mod:`keygen.keypoints.refine`)."""

    def run(clouds: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray | None]:
        pred = extractor.batch(list(clouds))
        if extractor.canonicalizer is None:
            return pred.keypoints, None
        return pred.keypoints, np.asarray(pred.label, dtype=np.int64)

    return run
