"""Self-supervised 3D keypoints: the data the detector trains and is evaluated on.

``scans``: partial, fused depth scans of single objects at random poses, with their ground-truth
pose and anchors (:class:`ScanGenerator`, :class:`Scan`, :func:`save_scans`, :func:`load_scans`).
"""

from keygen.keypoints.scans import POSE_MODES, Scan, ScanError, ScanGenerator, load_scans, save_scans

__all__ = ["POSE_MODES", "Scan", "ScanError", "ScanGenerator", "load_scans", "save_scans"]
