"""Inference: an object cloud in, K keypoints in the observation frame out (paper, "Keypoint inference").

``KeypointExtractor.load(run_dir)`` reads a run written by
:func:`keygen.keypoints.training.train_keypoints`; calling it on a cloud resamples it to the
networks' ``num_points`` by deterministic farthest-point sampling, predicts the rotation class
``R*`` (canonical -> observation), detects keypoints in ``P_can = R*^-1 P`` and maps them back with
``K_obs = R* K``. Keypoints are convex combinations of the (resampled) input points, so they lie in
its convex hull, in the input's frame and units.

A run's ``inference.json`` (:mod:`keygen.keypoints.refine`) adds test-time refinements beyond the
paper: a resampling ensemble, a yaw fix of ``R*`` and, for upright surfaces of revolution, completion
of the cloud about its axis (:mod:`keygen.keypoints.completion`); ``load(run, ensemble=1,
refine_iters=0, axial_copies=0)`` gives the paper's single pass. Runs without the file infer with the
single pass.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from keygen.errors import InvalidParameterError
from keygen.keypoints.completion import complete_about_axis
from keygen.keypoints.dataset import resample
from keygen.keypoints.models import Canonicalizer, CheckpointError, KeypointDetector, canonicalize, load_model
from keygen.keypoints.refine import ENSEMBLE_SEED, InferenceSettings, refine_rotation

__all__ = ["KeypointExtractor", "KeypointPrediction"]

MIN_POINTS = 8
REFINE_SUBSETS = 1  # ensemble subsets the yaw refinement fits on (more gained nothing, measured)


@dataclass(frozen=True)
class KeypointPrediction:
    """Keypoints, rotation and confidence of one cloud (unbatched shapes) or of a batch (leading B)."""

    keypoints: np.ndarray  # (K, 3) or (B, K, 3), observation frame, float32
    rotation: np.ndarray  # (3, 3) or (B, 3, 3): canonical -> observation (p_obs = R p_can)
    confidence: np.ndarray  # () or (B,) softmax probability of the chosen rotation class
    label: np.ndarray | None = None  # () or (B,) the classifier's rotation class (-1: no canonicaliser)


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
        settings: InferenceSettings | None = None,
    ) -> None:
        self.category = category
        self.num_keypoints = int(detector.num_keypoints)
        self.num_points = int(num_points)
        self.device = torch.device(device)
        self.settings = InferenceSettings() if settings is None else settings
        if self.settings.refine_iters and canonicalizer is None:
            raise InvalidParameterError("yaw refinement corrects a canonicaliser's rotation; this has none")
        template = self.settings.template
        if template is not None and len(template) != self.num_keypoints:
            raise InvalidParameterError(
                f"the template has {len(template)} keypoints, the detector {self.num_keypoints}"
            )
        self.canonicalizer = None if canonicalizer is None else canonicalizer.to(self.device).eval()
        self.detector = detector.to(self.device).eval()

    @classmethod
    def load(
        cls,
        run_dir: str | Path,
        device: str = "cpu",
        detector: str = "detector",
        ensemble: int | None = None,
        refine_iters: int | None = None,
        axial_copies: int | None = None,
    ) -> KeypointExtractor:
        """The extractor of a training run directory (``detector="detector_nocanon"``: the ablation).

        ``ensemble``, ``refine_iters`` and ``axial_copies`` override the run's ``inference.json`` (None
        keeps it); ``ensemble=1, refine_iters=0, axial_copies=0`` is the paper's single pass. The
        ablation never refines.
        """
        run_dir = Path(run_dir)
        config_path = run_dir / "train_config.json"
        if not config_path.is_file():
            if (run_dir / "config.json").is_file():  # the layout of a policy run
                raise CheckpointError(
                    f"{run_dir} is a policy run, not a keypoint run; evaluate it with "
                    f"`keygen eval {run_dir} --split test`"
                )
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
        settings = InferenceSettings.load(run_dir) or InferenceSettings()
        if canon is None:
            settings = settings.replace(refine_iters=0)
        settings = settings.replace(ensemble, refine_iters, axial_copies)
        return cls(config["category"], canon, det, int(config["num_points"]), device, settings)

    # -- inference -------------------------------------------------------------------------------
    def _prepare(self, cloud: np.ndarray) -> np.ndarray:
        """(N, 3) -> (M, n, 3): the ensemble's subsets (the first deterministic, the others seeded)."""
        arr = np.asarray(cloud, dtype=np.float32)
        if arr.ndim != 2 or arr.shape[1] != 3 or len(arr) < MIN_POINTS or not np.isfinite(arr).all():
            raise InvalidParameterError(
                f"a cloud must be a finite (N, 3) array with N >= {MIN_POINTS}, got shape {arr.shape}"
                + ("" if arr.ndim != 2 or np.isfinite(arr).all() else " with NaN/inf values")
                + "; pass the object's points in metres"
            )
        if self.settings.axial_copies > 1:
            arr = complete_about_axis(arr, self.settings.up, self.settings.axial_copies)
        rng = np.random.default_rng(ENSEMBLE_SEED)
        subsets = [resample(arr, self.num_points)]
        subsets += [resample(arr, self.num_points, rng) for _ in range(self.settings.ensemble - 1)]
        return np.stack(subsets)

    def _detect(self, x: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
        """Keypoints (B, M, K, 3) of subsets x (B, M, n, 3) canonicalised by R (B, 3, 3)."""
        B, M, n, _ = x.shape
        flat = x.reshape(B * M, n, 3)
        _, weights = self.detector(canonicalize(flat, R.repeat_interleave(M, dim=0)))  # (B*M, K, n)
        # R K_can = R (W P_can) = W P: the keypoints are the same convex combination of the input points.
        return (weights @ flat).reshape(B, M, -1, 3)

    @torch.no_grad()
    def _run(self, clouds: np.ndarray) -> tuple[np.ndarray, ...]:
        x = torch.from_numpy(clouds).to(self.device)  # (B, M, n, 3)
        B, M = x.shape[:2]
        if self.canonicalizer is None:
            R = torch.eye(3, device=self.device).expand(B, 3, 3)
            conf = torch.ones(B, device=self.device)
            label = torch.full((B,), -1, dtype=torch.long)
        else:
            logp = torch.log_softmax(self.canonicalizer(x.flatten(0, 1)), dim=-1).reshape(B, M, -1)
            label = logp.mean(dim=1).argmax(dim=-1)  # (B,) the subsets' vote
            conf = logp.exp().mean(dim=1).gather(1, label[:, None])[:, 0]  # (B,)
            R = self.canonicalizer.rotations.to(x)[label]  # (B, 3, 3)
        if self.settings.refine_iters:
            # The yaw fixes look at the first subset only (fitting on more gained nothing), so only it
            # is detected in the classifier's frame; the whole ensemble detects once, in the refined one.
            few = x[:, :REFINE_SUBSETS]  # (B, m, n, 3)
            R = refine_rotation(
                self._detect, few, R, self._detect(few, R), self.settings, self.settings.refine_iters
            )
        kp = self._detect(x, R)  # (B, M, K, 3)
        return (kp.mean(dim=1).cpu().numpy(), R.cpu().numpy(), conf.cpu().numpy(), label.cpu().numpy())

    def __call__(self, cloud: np.ndarray) -> KeypointPrediction:
        """One cloud (N, 3) or a batch (B, N, 3) in the observation frame, metres."""
        arr = np.asarray(cloud)
        if arr.ndim == 3:
            return self.batch(list(arr))
        kp, R, conf, label = self._run(self._prepare(arr)[None])
        return KeypointPrediction(
            kp[0].astype(np.float32), R[0].astype(np.float64), np.asarray(conf[0]), np.asarray(label[0])
        )

    def batch(self, clouds: Sequence[np.ndarray]) -> KeypointPrediction:
        """A ragged list of (N_i, 3) clouds, one network call: (B, K, 3), (B, 3, 3), (B,)."""
        if len(clouds) == 0:
            raise InvalidParameterError("batch needs at least one cloud")
        kp, R, conf, label = self._run(np.stack([self._prepare(c) for c in clouds]))
        return KeypointPrediction(kp.astype(np.float32), R.astype(np.float64), conf, label)
