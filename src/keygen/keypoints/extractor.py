"""Inference: an object cloud in, K keypoints in the observation frame out (paper, "Keypoint inference").

``KeypointExtractor.load(run_dir)`` reads a run written by
:func:`keygen.keypoints.training.train_keypoints`; calling it on a cloud resamples it to the
networks' ``num_points`` by deterministic farthest-point sampling, predicts the rotation class
``R*`` (canonical -> observation), detects keypoints in ``P_can = R*^-1 P`` and maps them back with
``K_obs = R* K``. Keypoints are convex combinations of the (resampled) input points, so they lie in
its convex hull, in the input's frame and units.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from keygen.errors import InvalidParameterError
from keygen.keypoints.dataset import resample
from keygen.keypoints.models import Canonicalizer, CheckpointError, KeypointDetector, canonicalize, load_model

__all__ = ["KeypointExtractor", "KeypointPrediction"]

MIN_POINTS = 8


@dataclass(frozen=True)
class KeypointPrediction:
    """Keypoints, rotation and confidence of one cloud (unbatched shapes) or of a batch (leading B)."""

    keypoints: np.ndarray  # (K, 3) or (B, K, 3), observation frame, float32
    rotation: np.ndarray  # (3, 3) or (B, 3, 3): canonical -> observation (p_obs = R p_can)
    confidence: np.ndarray  # () or (B,) softmax probability of the chosen rotation class


class KeypointExtractor:
    """A trained canonicaliser + detector pair. ``canonicalizer=None`` runs the detector on raw clouds
    (the "without canonicaliser" ablation; rotation is then the identity and confidence 1)."""

    def __init__(
        self,
        category: str,
        canonicalizer: Canonicalizer | None,
        detector: KeypointDetector,
        num_points: int,
        device: str = "cpu",
    ) -> None:
        self.category = category
        self.num_keypoints = int(detector.num_keypoints)
        self.num_points = int(num_points)
        self.device = torch.device(device)
        self.canonicalizer = None if canonicalizer is None else canonicalizer.to(self.device).eval()
        self.detector = detector.to(self.device).eval()

    @classmethod
    def load(cls, run_dir: str | Path, device: str = "cpu", detector: str = "detector") -> KeypointExtractor:
        """The extractor of a training run directory (``detector="detector_nocanon"``: the ablation)."""
        run_dir = Path(run_dir)
        config_path = run_dir / "train_config.json"
        if not config_path.is_file():
            raise CheckpointError(
                f"{run_dir} is not a keypoint run (no train_config.json); train one with "
                "`keygen keypoints train --category mug --out DIR`"
            )
        config = json.loads(config_path.read_text())
        if not (run_dir / detector / "model.safetensors").is_file():
            raise CheckpointError(
                f"{run_dir} has no {detector}/ checkpoint; the run is unfinished (rerun the same train "
                "command to resume) or was trained without it"
            )
        det = load_model(run_dir / detector, KeypointDetector)
        canon = (
            None if detector == "detector_nocanon" else load_model(run_dir / "canonicalizer", Canonicalizer)
        )
        return cls(config["category"], canon, det, int(config["num_points"]), device)

    # -- inference -------------------------------------------------------------------------------
    def _prepare(self, cloud: np.ndarray) -> np.ndarray:
        arr = np.asarray(cloud, dtype=np.float32)
        if arr.ndim != 2 or arr.shape[1] != 3 or len(arr) < MIN_POINTS or not np.isfinite(arr).all():
            raise InvalidParameterError(
                f"a cloud must be a finite (N, 3) array with N >= {MIN_POINTS}, got shape {arr.shape}"
                + ("" if arr.ndim != 2 or np.isfinite(arr).all() else " with NaN/inf values")
                + "; pass the object's points in metres"
            )
        return resample(arr, self.num_points)

    @torch.no_grad()
    def _run(self, clouds: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = torch.from_numpy(clouds).to(self.device)  # (B, n, 3)
        if self.canonicalizer is None:
            R = torch.eye(3, device=self.device).expand(len(x), 3, 3)
            conf = torch.ones(len(x), device=self.device)
        else:
            R, _, conf = self.canonicalizer.predict(x)  # (B, 3, 3), (B,)
        _, weights = self.detector(canonicalize(x, R))  # (B, K, n)
        # R K_can = R (W P_can) = W P: the keypoints are the same convex combination of the input points.
        kp = weights @ x  # (B, K, 3)
        return kp.cpu().numpy(), R.cpu().numpy(), conf.cpu().numpy()

    def __call__(self, cloud: np.ndarray) -> KeypointPrediction:
        """One cloud (N, 3) or a batch (B, N, 3) in the observation frame, metres."""
        arr = np.asarray(cloud)
        if arr.ndim == 3:
            return self.batch(list(arr))
        kp, R, conf = self._run(self._prepare(arr)[None])
        return KeypointPrediction(kp[0].astype(np.float32), R[0].astype(np.float64), np.asarray(conf[0]))

    def batch(self, clouds: Sequence[np.ndarray]) -> KeypointPrediction:
        """A ragged list of (N_i, 3) clouds, one network call: (B, K, 3), (B, 3, 3), (B,)."""
        if len(clouds) == 0:
            raise InvalidParameterError("batch needs at least one cloud")
        kp, R, conf = self._run(np.stack([self._prepare(c) for c in clouds]))
        return KeypointPrediction(kp.astype(np.float32), R.astype(np.float64), conf)
