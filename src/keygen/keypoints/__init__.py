"""Self-supervised 3D keypoints: the data the detector trains and is evaluated on.

``scans``: partial, fused depth scans of single objects at random poses, with their ground-truth
pose and anchors (:class:`ScanGenerator`, :class:`Scan`, :func:`save_scans`, :func:`load_scans`).

The PyTorch parts are imported from their modules so that this package does not load torch:
``keygen.keypoints.losses`` (separation, surface, coverage, cross-view consistency, the weighted
total, and a cross-entropy over sets of symmetric rotations) and ``keygen.keypoints.models``
(PointNet encoder, the 24-way canonicaliser, the convex-combination keypoint detector,
canonicalise / reproject, safetensors checkpoints).
"""

from keygen.keypoints.scans import POSE_MODES, Scan, ScanError, ScanGenerator, load_scans, save_scans

__all__ = ["POSE_MODES", "Scan", "ScanError", "ScanGenerator", "load_scans", "save_scans"]
