"""Cached scan sets with their symmetry labels, and the batches the keypoint networks train on.

A :class:`ScanSet` is a list of scans of one category split (``scans.npz``, written once by
:func:`build_scan_set`) plus, per scan, its view-dependent equivalence set over the 24 cube rotations
(``labels.npz``: a (S, 24) mask of group elements ``g`` such that pose ``R g`` explains the scan as
well as the true ``R``, see :mod:`keygen.keypoints.symmetry`) and, per instance, the shape's own
symmetry set. Both are stored in the object frame, so they survive re-posing the scan.

Augmentation (:meth:`ScanSet.sample`): a whole scan (points and pose) turned by a random rotation
about the world z axis is another valid table-pose scan (the cameras' azimuths are uniform anyway);
under ``pose_mode="any"`` any rotation is. So a few dozen rendered scans per instance give unlimited
poses, and the rotation labels are recomputed from the moved pose.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from keygen.atomic import atomic_write
from keygen.errors import InvalidParameterError
from keygen.geometry.clouds import farthest_point_sample
from keygen.geometry.rotations import octahedral_group, random_rotation, yaw_matrix
from keygen.keypoints.scans import Scan, ScanGenerator, load_scans, save_scans
from keygen.keypoints.symmetry import (
    SymmetryReference,
    instance_symmetry_set,
    is_axial,
    rotation_label,
    scan_equivalence_set,
    surface_sample,
)

__all__ = ["ScanBatch", "ScanSet", "build_scan_set", "resample"]

_GROUP = octahedral_group()


def resample(points: np.ndarray, n: int, rng: np.random.Generator | None = None) -> np.ndarray:
    """Exactly ``n`` points of a cloud (N, 3) -> (n, 3) float32 by farthest-point sampling.

    ``rng=None`` is deterministic (start at point 0, fpsample's fast bucketed FPS); with a generator
    the start point is random (training sees many subsets of one scan). Fewer than ``n`` points are
    repeated cyclically, so any N >= 1 works.
    """
    pts = np.asarray(points, dtype=np.float32)
    start = 0 if rng is None else int(rng.integers(len(pts)))
    if len(pts) == n:
        return pts.copy() if rng is None else pts[rng.permutation(n)]
    return farthest_point_sample(pts, n, start_index=start, method="fast").astype(np.float32)


@dataclass
class ScanBatch:
    """Scans re-posed for one training step. Shapes: points (B, n, 3), rotation (B, 3, 3), etc."""

    points: np.ndarray  # (B, n, 3) float32 world frame
    rotation: np.ndarray  # (B, 3, 3) true canonical -> world
    translation: np.ndarray  # (B, 3)
    target_mask: np.ndarray  # (B, 24) bool: classes a correct canonicaliser may output
    label: np.ndarray  # (B,) nearest-group-element class of the true rotation
    symmetries: np.ndarray  # (B, 4, 3, 3) shape symmetries of the instance, padded with the identity
    axial: np.ndarray  # (B,) bool: the shape is symmetric under every yaw
    instance: np.ndarray  # (B,) int index into ScanSet.instance_ids


class ScanSet:
    """Scans with per-scan equivalence sets and per-instance symmetry sets (see the module doc)."""

    def __init__(self, scans: list[Scan], equivalence: np.ndarray, instance_symmetry: dict[str, list[int]]):
        if len(scans) == 0:
            raise InvalidParameterError("a ScanSet needs at least one scan")
        if equivalence.shape != (len(scans), 24):
            raise InvalidParameterError(f"equivalence must be ({len(scans)}, 24), got {equivalence.shape}")
        self.scans, self.equivalence = scans, equivalence.astype(bool)
        self.instance_ids = sorted({s.instance_id for s in scans})
        missing = set(self.instance_ids) - set(instance_symmetry)
        if missing:
            raise InvalidParameterError(f"instance_symmetry lacks the instances {sorted(missing)}")
        self.instance_symmetry = {k: list(v) for k, v in instance_symmetry.items()}
        self.instance_of = np.array([self.instance_ids.index(s.instance_id) for s in scans])
        self.by_instance = [np.flatnonzero(self.instance_of == i) for i in range(len(self.instance_ids))]
        self._sym = np.tile(np.eye(3), (len(self.instance_ids), 4, 1, 1))  # (I, 4, 3, 3)
        self._axial = np.zeros(len(self.instance_ids), dtype=bool)
        for i, name in enumerate(self.instance_ids):
            sym = self.instance_symmetry[name][:4]
            self._sym[i, : len(sym)] = _GROUP[sym]
            self._axial[i] = is_axial(self.instance_symmetry[name])

    def __len__(self) -> int:
        return len(self.scans)

    # -- storage ------------------------------------------------------------------------------------
    def save(self, directory: str | Path) -> Path:
        directory = Path(directory)
        save_scans(directory / "scans.npz", self.scans)
        ids = sorted(self.instance_symmetry)
        sym = np.zeros((len(ids), 24), dtype=bool)
        for i, name in enumerate(ids):
            sym[i, self.instance_symmetry[name]] = True
        # Written last: its presence marks a complete set.
        atomic_write(
            directory / "labels.npz",
            lambda tmp: np.savez_compressed(
                tmp, equivalence=self.equivalence, symmetry=sym, symmetry_ids=np.array(ids)
            ),
        )
        return directory

    @classmethod
    def load(cls, directory: str | Path) -> ScanSet:
        directory = Path(directory)
        scans = load_scans(directory / "scans.npz")
        with np.load(directory / "labels.npz", allow_pickle=False) as f:
            sym = {
                str(n): np.flatnonzero(row).tolist()
                for n, row in zip(f["symmetry_ids"], f["symmetry"], strict=True)
            }
            return cls(scans, f["equivalence"], sym)

    @staticmethod
    def exists(directory: str | Path) -> bool:
        return (Path(directory) / "labels.npz").is_file() and (Path(directory) / "scans.npz").is_file()

    # -- sampling -----------------------------------------------------------------------------------
    def batch(
        self, indices: np.ndarray, num_points: int, rng: np.random.Generator, pose_mode: str | None = "table"
    ) -> ScanBatch:
        """Scans ``indices`` re-posed (``pose_mode`` "table": random yaw; "any": random rotation; None:
        as rendered) and resampled to ``num_points``."""
        pts, rots, trans, masks, labels = [], [], [], [], []
        for i in indices:
            scan = self.scans[int(i)]
            if pose_mode is None:
                turn = np.eye(3)
            elif pose_mode == "table":
                turn = yaw_matrix(rng.uniform(0.0, 2.0 * np.pi))
            else:
                turn = random_rotation(rng)
            R = turn @ scan.rotation
            # Points turn about the world origin with the pose: p' = turn p, t' = turn t.
            pts.append(resample(scan.points, num_points, rng) @ turn.T.astype(np.float32))
            rots.append(R)
            trans.append(turn @ scan.translation)
            eq = np.flatnonzero(self.equivalence[int(i)])
            mask = np.zeros(24, dtype=bool)
            mask[np.atleast_1d(rotation_label(R[None] @ _GROUP[eq]))] = True
            masks.append(mask)
            labels.append(int(rotation_label(R)))
        inst = self.instance_of[np.asarray(indices, dtype=np.int64)]
        return ScanBatch(
            points=np.stack(pts).astype(np.float32),
            rotation=np.stack(rots),
            translation=np.stack(trans),
            target_mask=np.stack(masks),
            label=np.array(labels),
            symmetries=self._sym[inst],
            axial=self._axial[inst],
            instance=inst,
        )

    def random_indices(self, count: int, rng: np.random.Generator) -> np.ndarray:
        return rng.integers(len(self.scans), size=count)

    def random_pairs(self, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Two different scans of the same (random) instance, ``count`` times: index arrays (count,)."""
        a, b = [], []
        for _ in range(count):
            members = self.by_instance[int(rng.integers(len(self.by_instance)))]
            i, j = rng.choice(members, size=2, replace=len(members) < 2)
            a.append(i)
            b.append(j)
        return np.array(a), np.array(b)


def build_scan_set(
    generator: ScanGenerator,
    instances: list[int] | range,
    scans_per_instance: int,
    seed: int,
    surface_points: int = 6000,
    progress: bool = True,
) -> ScanSet:
    """Render ``scans_per_instance`` scans of each instance and label their symmetries."""
    scans, equivalence, symmetry = [], [], {}
    bar = tqdm(
        total=len(instances) * scans_per_instance,
        desc=f"scans {generator.category}/{generator.split}",
        unit="scan",
        disable=not progress,
    )
    for index in instances:
        rng = np.random.default_rng([seed, int(index)])
        asset = generator.asset(int(index))
        first = generator.scan(int(index), rng)
        reference = SymmetryReference(
            surface_sample(asset.visual, surface_points, seed=int(index)), first.diameter
        )
        symmetry[first.instance_id] = instance_symmetry_set(reference.surface, first.diameter)
        for k in range(scans_per_instance):
            scan = first if k == 0 else generator.scan(int(index), rng)
            mask = np.zeros(24, dtype=bool)
            mask[scan_equivalence_set(scan.points, scan.rotation, scan.translation, reference)] = True
            scans.append(scan)
            equivalence.append(mask)
            bar.update(1)
    bar.close()
    return ScanSet(scans, np.stack(equivalence), symmetry)
