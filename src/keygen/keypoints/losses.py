"""Training losses of the keypoint stage, as written in the paper (section "3D Keypoint Detection").

Shapes: keypoints ``kp`` (B, K, 3), clouds (B, N, 3), rotations ``R`` (B, 3, 3), all in metres.
Points are ROW vectors; a rotation acting on column vectors (``x_obs = R @ x_can``, the package's
convention) therefore acts on a row batch as ``points @ R^T``.

Every loss returns the mean over the batch (a scalar) with ``reduction="mean"`` or one value per
sample (B,) with ``reduction="none"``. Inputs are never modified in place.

- :func:`separation_loss`: mean over the K(K-1)/2 pairs of ``[margin - ||k_i - k_j||]_+^2``.
- :func:`surface_loss`: mean over keypoints of the distance to the nearest cloud point.
- :func:`coverage_loss`: ``SmoothL1_beta(Vol_AABB(kp) - Vol_AABB(cloud))``.
- :func:`spread_loss`: ``[floor * rms(cloud) - rms(kp)]_+^2``, a guard against collapsed keypoints.
- :func:`consistency_loss`: mean over keypoints of ``||R_a k_a - R_b k_b||^2``.
- :func:`keypoint_loss`: the weighted total of the two views (paper's L_total) and its parts.
- :func:`symmetric_rotation_loss`: cross-entropy against a SET of equivalent rotation classes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F

from keygen.errors import InvalidParameterError

__all__ = [
    "KeypointLossWeights",
    "aabb_volume",
    "consistency_loss",
    "coverage_loss",
    "keypoint_loss",
    "separation_loss",
    "spread_loss",
    "surface_loss",
    "symmetric_rotation_loss",
]

REDUCTIONS = ("mean", "none")


# -- validation ---------------------------------------------------------------------------
def _check_points(x: torch.Tensor, name: str) -> None:
    if not isinstance(x, torch.Tensor) or x.ndim != 3 or x.shape[-1] != 3:
        shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
        raise InvalidParameterError(
            f"{name} must be a torch tensor of shape (B, count, 3), got {shape}; "
            "add a batch axis with x[None] for a single sample"
        )


def _check_rotations(R: torch.Tensor, name: str, batch: int) -> None:
    if not isinstance(R, torch.Tensor) or R.shape != (batch, 3, 3):
        shape = tuple(R.shape) if isinstance(R, torch.Tensor) else type(R).__name__
        raise InvalidParameterError(
            f"{name} must be a torch tensor of shape ({batch}, 3, 3) (one rotation per sample), got {shape}"
        )


def _check_same_batch(a: torch.Tensor, b: torch.Tensor, names: str) -> None:
    if a.shape[0] != b.shape[0]:
        raise InvalidParameterError(
            f"{names} must have the same batch size, got {a.shape[0]} and {b.shape[0]}"
        )


def _reduce(per_sample: torch.Tensor, reduction: str) -> torch.Tensor:
    if reduction == "mean":
        return per_sample.mean()
    if reduction == "none":
        return per_sample
    raise InvalidParameterError(f"reduction must be one of {REDUCTIONS}, got {reduction!r}")


def _safe_sqrt(sq: torch.Tensor) -> torch.Tensor:
    """sqrt with a zero (not infinite / NaN) gradient at 0, and exact values elsewhere.

    A plain ``sqrt`` has an infinite derivative at 0, which turns a keypoint sitting exactly on a
    cloud point (the optimum of the surface term) into NaN gradients.
    """
    positive = sq > 0
    return torch.where(
        positive, torch.sqrt(torch.where(positive, sq, torch.ones_like(sq))), torch.zeros_like(sq)
    )


# -- the paper's terms ----------------------------------------------------------------------
def separation_loss(kp: torch.Tensor, margin: float, reduction: str = "mean") -> torch.Tensor:
    """Mean over the K(K-1)/2 keypoint pairs of ``[margin - ||k_i - k_j||]_+^2`` (paper's l_sep).

    ``kp`` (B, K, 3) with K >= 2; ``margin`` > 0 in metres.
    """
    _check_points(kp, "kp")
    if not margin > 0:
        raise InvalidParameterError(f"margin must be > 0 metres, got {margin}")
    K = kp.shape[1]
    if K < 2:
        raise InvalidParameterError(f"separation needs at least 2 keypoints per sample, got K={K}")
    diff = kp[:, :, None, :] - kp[:, None, :, :]  # (B, K, K, 3)
    dist = _safe_sqrt((diff * diff).sum(-1))  # (B, K, K)
    i, j = torch.triu_indices(K, K, offset=1, device=kp.device)  # the K(K-1)/2 pairs i < j
    hinge = torch.clamp(margin - dist[:, i, j], min=0.0) ** 2  # (B, K(K-1)/2)
    return _reduce(hinge.mean(-1), reduction)


def surface_loss(kp: torch.Tensor, cloud: torch.Tensor, reduction: str = "mean") -> torch.Tensor:
    """Mean over keypoints of the distance to the nearest cloud point (paper's l_surf).

    ``kp`` (B, K, 3), ``cloud`` (B, N, 3).
    """
    _check_points(kp, "kp")
    _check_points(cloud, "cloud")
    _check_same_batch(kp, cloud, "kp and cloud")
    diff = kp[:, :, None, :] - cloud[:, None, :, :]  # (B, K, N, 3)
    nearest_sq = (diff * diff).sum(-1).min(dim=-1).values  # (B, K)
    return _reduce(_safe_sqrt(nearest_sq).mean(-1), reduction)


def aabb_volume(points: torch.Tensor) -> torch.Tensor:
    """Volume (m^3) of the axis-aligned bounding box of each sample: (B, n, 3) -> (B,)."""
    _check_points(points, "points")
    extent = points.max(dim=1).values - points.min(dim=1).values  # (B, 3)
    return extent.prod(dim=-1)


def coverage_loss(
    kp: torch.Tensor, cloud: torch.Tensor, beta: float, reduction: str = "mean"
) -> torch.Tensor:
    """``SmoothL1_beta(Vol_AABB(kp) - Vol_AABB(cloud))`` (paper's l_cov), volumes in m^3.

    ``beta`` (m^3) is where SmoothL1 turns from quadratic to linear; pick it near the volume
    differences you expect (an object 0.1 m across has an AABB of about 1e-3 m^3).
    Keypoints are convex combinations of the cloud, so their box is never larger: the term pulls
    them outwards until their box spans the cloud's.
    """
    _check_points(kp, "kp")
    _check_points(cloud, "cloud")
    _check_same_batch(kp, cloud, "kp and cloud")
    if not beta > 0:
        raise InvalidParameterError(f"beta must be > 0 (m^3), got {beta}")
    gap = aabb_volume(kp) - aabb_volume(cloud)  # (B,)
    per_sample = F.smooth_l1_loss(gap, torch.zeros_like(gap), beta=beta, reduction="none")  # (B,)
    return _reduce(per_sample, reduction)


def rms_spread(points: torch.Tensor) -> torch.Tensor:
    """Root-mean-square distance of each sample's points to their mean: (B, n, 3) -> (B,)."""
    _check_points(points, "points")
    centred = points - points.mean(dim=1, keepdim=True)  # (B, n, 3)
    return _safe_sqrt(centred.pow(2).sum(-1).mean(-1))


def spread_loss(kp: torch.Tensor, cloud: torch.Tensor, floor: float, reduction: str = "mean") -> torch.Tensor:
    """``[floor * rms(cloud) - rms(kp)]_+^2``: zero once the keypoints spread at least ``floor`` times
    as widely (RMS about their mean) as the cloud; a guard against collapse.

    Why not the coverage term: the AABB volume of a flat object (a knife) is ~0 for any keypoints, so
    it cannot tell spread-out keypoints from collapsed ones; the RMS spread can, in any dimension.
    The separation hinge saturates (its gradient vanishes) once all keypoints sit on one spot, while
    this term's gradient does not. ``kp`` (B, K, 3), ``cloud`` (B, N, 3), ``floor`` in [0, 1]
    (keypoints are convex combinations of the cloud, so 1 is about the most they can reach).
    """
    _check_points(kp, "kp")
    _check_points(cloud, "cloud")
    _check_same_batch(kp, cloud, "kp and cloud")
    if not 0.0 <= floor <= 1.0:
        raise InvalidParameterError(f"floor must be in [0, 1], a fraction of the cloud's spread; got {floor}")
    gap = torch.clamp(floor * rms_spread(cloud).detach() - rms_spread(kp), min=0.0)  # (B,)
    return _reduce(gap**2, reduction)


def consistency_loss(
    kp_a: torch.Tensor, R_a: torch.Tensor, kp_b: torch.Tensor, R_b: torch.Tensor, reduction: str = "mean"
) -> torch.Tensor:
    """Mean over keypoints of ``||R_a k_a - R_b k_b||^2`` (paper's L_cons).

    ``kp_a``, ``kp_b`` (B, K, 3) canonical keypoints of two views, index-matched; ``R_a``, ``R_b``
    (B, 3, 3) each view's canonical -> observation rotation.
    """
    _check_points(kp_a, "kp_a")
    _check_points(kp_b, "kp_b")
    if kp_a.shape != kp_b.shape:
        raise InvalidParameterError(
            f"kp_a and kp_b must have the same shape (index-matched keypoints), got "
            f"{tuple(kp_a.shape)} and {tuple(kp_b.shape)}"
        )
    _check_rotations(R_a, "R_a", kp_a.shape[0])
    _check_rotations(R_b, "R_b", kp_b.shape[0])
    # Row vectors: R k (column) is k @ R^T (row).
    obs_a = kp_a @ R_a.transpose(-1, -2)  # (B, K, 3)
    obs_b = kp_b @ R_b.transpose(-1, -2)  # (B, K, 3)
    per_sample = ((obs_a - obs_b) ** 2).sum(-1).mean(-1)  # (B,)
    return _reduce(per_sample, reduction)


@dataclass(frozen=True)
class KeypointLossWeights:
    """Weights of L_total = l_sep * L_sep + l_heur * L_heur + l_cons * L_cons, validated on creation.

    ``margin`` (m) is the separation margin, ``coverage_beta`` (m^3) the SmoothL1 knee of the
    coverage term. The paper gives no values; these defaults are plausible for objects about
    0.1 m across with 10 keypoints and are not tuned.
    """

    lambda_sep: float = 1.0
    lambda_heur: float = 1.0
    lambda_cons: float = 1.0
    alpha_surf: float = 1.0
    alpha_cov: float = 1.0
    margin: float = 0.03
    coverage_beta: float = 1e-4

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise InvalidParameterError(f"{name} must be a finite number >= 0, got {value!r}")
        for name in ("margin", "coverage_beta"):
            if getattr(self, name) <= 0:
                raise InvalidParameterError(f"{name} must be > 0, got {getattr(self, name)}")


def keypoint_loss(
    kp_a: torch.Tensor,
    cloud_a: torch.Tensor,
    R_a: torch.Tensor,
    kp_b: torch.Tensor,
    cloud_b: torch.Tensor,
    R_b: torch.Tensor,
    weights: KeypointLossWeights | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The paper's L_total for two views of the same object, and its parts.

    ``kp_a``/``kp_b`` (B, K, 3) keypoints in the canonical frame, ``cloud_a``/``cloud_b`` (B, N, 3)
    the canonicalised clouds P_can they were detected in (N may differ between views),
    ``R_a``/``R_b`` (B, 3, 3) the canonical -> observation rotations. Returns ``(total, parts)``
    with scalar tensors (still attached to the graph) under the keys ``sep``, ``surf``, ``cov``,
    ``heur``, ``cons``; ``sep``/``surf``/``cov`` are already averaged over the two views.
    """
    w = KeypointLossWeights() if weights is None else weights
    sep = 0.5 * (separation_loss(kp_a, w.margin) + separation_loss(kp_b, w.margin))
    surf = 0.5 * (surface_loss(kp_a, cloud_a) + surface_loss(kp_b, cloud_b))
    cov = 0.5 * (
        coverage_loss(kp_a, cloud_a, w.coverage_beta) + coverage_loss(kp_b, cloud_b, w.coverage_beta)
    )
    heur = w.alpha_surf * surf + w.alpha_cov * cov
    cons = consistency_loss(kp_a, R_a, kp_b, R_b)
    total = w.lambda_sep * sep + w.lambda_heur * heur + w.lambda_cons * cons
    return total, {"sep": sep, "surf": surf, "cov": cov, "heur": heur, "cons": cons}


# -- canonical orientation ------------------------------------------------------------------
def _target_mask(
    target_sets: torch.Tensor | Sequence[Sequence[int]], batch: int, classes: int
) -> torch.Tensor:
    """(B, C) boolean mask of the allowed classes, from a mask or from lists of indices."""
    if isinstance(target_sets, torch.Tensor):
        if target_sets.shape != (batch, classes):
            raise InvalidParameterError(
                f"target_sets as a tensor must be a ({batch}, {classes}) mask, got {tuple(target_sets.shape)}"
            )
        mask = target_sets.bool()
    else:
        if len(target_sets) != batch:
            raise InvalidParameterError(
                f"target_sets must hold one index set per sample ({batch}), got {len(target_sets)}"
            )
        mask = torch.zeros(batch, classes, dtype=torch.bool)
        for row, indices in enumerate(target_sets):
            for index in indices:
                if not 0 <= int(index) < classes:
                    raise InvalidParameterError(
                        f"target index {index} of sample {row} is outside [0, {classes}); "
                        "indices refer to rows of octahedral_group()"
                    )
                mask[row, int(index)] = True
    empty = ~mask.any(dim=1)
    if bool(empty.any()):
        raise InvalidParameterError(
            "every target set needs at least one index; samples "
            f"{empty.nonzero().flatten().tolist()} have none"
        )
    return mask


def symmetric_rotation_loss(
    logits: torch.Tensor, target_sets: torch.Tensor | Sequence[Sequence[int]], reduction: str = "mean"
) -> torch.Tensor:
    """Cross-entropy against a SET of equivalent rotation classes: ``-log sum_{c in set} p(c)``.

    For a symmetric object (a bowl about z, a knife turned over) several rotations give the same
    canonical cloud; any of them is right, so the classifier is rewarded for the probability mass
    on the whole set. With one index per set this is the ordinary cross-entropy.

    ``logits`` (B, C); ``target_sets`` a (B, C) boolean/0-1 mask or B sequences of class indices.
    """
    if not isinstance(logits, torch.Tensor) or logits.ndim != 2:
        shape = tuple(logits.shape) if isinstance(logits, torch.Tensor) else type(logits).__name__
        raise InvalidParameterError(f"logits must be a (B, C) tensor, got {shape}")
    batch, classes = logits.shape
    mask = _target_mask(target_sets, batch, classes).to(logits.device)  # (B, C)
    # log sum_set p = logsumexp over the set - logsumexp over all (stable for large logits).
    in_set = torch.logsumexp(logits.masked_fill(~mask, float("-inf")), dim=1)  # (B,)
    everything = torch.logsumexp(logits, dim=1)  # (B,)
    return _reduce(everything - in_set, reduction)
