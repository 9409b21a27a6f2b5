"""Keypoint losses: values known by hand, gradients, reductions, argument checks, no mutation."""

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from keygen.errors import InvalidParameterError
from keygen.geometry.rotations import octahedral_group
from keygen.keypoints.losses import (
    KeypointLossWeights,
    aabb_volume,
    consistency_loss,
    coverage_loss,
    keypoint_loss,
    rms_spread,
    separation_loss,
    spread_loss,
    surface_loss,
    symmetric_rotation_loss,
)

GROUP = torch.tensor(octahedral_group().copy(), dtype=torch.float64)


def _t(x) -> torch.Tensor:
    return torch.tensor(x, dtype=torch.float64)


def _cube_cloud(side: float = 0.1) -> torch.Tensor:
    """(1, 8, 3) corners of a cube of the given side, one corner at the origin."""
    corners = np.array(np.meshgrid([0, side], [0, side], [0, side], indexing="ij")).reshape(3, -1).T
    return _t(corners)[None]


# -- separation -------------------------------------------------------------------------------
def test_separation_two_keypoints_closer_than_margin():
    d, margin = 0.01, 0.03
    kp = _t([[[0.0, 0.0, 0.0], [d, 0.0, 0.0]]])
    assert separation_loss(kp, margin).item() == pytest.approx((margin - d) ** 2)


def test_separation_is_zero_beyond_margin_and_averages_pairs():
    margin = 0.03
    far = _t([[[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]]])
    assert separation_loss(far, margin).item() == 0.0
    # Three keypoints, one close pair (d = 0.01) among 3 pairs -> (m - d)^2 / 3.
    one_close = _t([[[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.1, 0.0]]])
    assert separation_loss(one_close, margin).item() == pytest.approx((margin - 0.01) ** 2 / 3)


def test_separation_gradient_pushes_keypoints_apart():
    kp = _t([[[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]]]).requires_grad_()
    separation_loss(kp, 0.03).backward()
    grad = kp.grad[0]
    assert torch.isfinite(grad).all()
    # Descending the gradient moves the first point to -x and the second to +x.
    assert grad[0, 0] > 0 and grad[1, 0] < 0


def test_separation_coincident_keypoints_give_finite_value_and_gradient():
    kp = torch.zeros(1, 3, 3, dtype=torch.float64, requires_grad=True)
    loss = separation_loss(kp, 0.02)
    loss.backward()
    assert loss.item() == pytest.approx(0.02**2)
    assert torch.isfinite(kp.grad).all()


# -- surface ----------------------------------------------------------------------------------
def test_surface_zero_on_cloud_points_with_finite_gradient():
    cloud = _cube_cloud()
    kp = cloud[:, [0, 3, 7]].clone().requires_grad_()
    loss = surface_loss(kp, cloud)
    loss.backward()
    assert loss.item() == 0.0
    assert torch.isfinite(kp.grad).all()


def test_surface_known_distances_and_gradient_towards_cloud():
    cloud = _t([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
    kp = _t([[[0.0, 0.0, 0.3], [1.0, 0.1, 0.0]]]).requires_grad_()
    loss = surface_loss(kp, cloud)
    assert loss.item() == pytest.approx((0.3 + 0.1) / 2)
    loss.backward()
    assert kp.grad[0, 0, 2] > 0 and kp.grad[0, 1, 1] > 0  # moving down the gradient approaches the cloud


# -- coverage ---------------------------------------------------------------------------------
def test_aabb_volume_of_a_box():
    pts = _t([[[0.0, 0.0, 0.0], [0.1, 0.2, 0.3], [0.05, 0.05, 0.05]]])
    assert aabb_volume(pts).item() == pytest.approx(0.1 * 0.2 * 0.3)


def test_coverage_zero_for_identical_boxes():
    cloud = _cube_cloud()
    kp = cloud[:, [0, 7]]  # opposite corners span the same box
    assert coverage_loss(kp, cloud, beta=1e-4).item() == 0.0


def test_coverage_matches_smooth_l1_in_both_regimes():
    cloud = _cube_cloud(0.1)  # volume 1e-3
    kp = _t([[[0.0, 0.0, 0.0], [0.05, 0.1, 0.1]]])  # volume 5e-4, gap -5e-4
    gap = 5e-4
    assert coverage_loss(kp, cloud, beta=1e-4).item() == pytest.approx(gap - 0.5 * 1e-4)  # linear part
    assert coverage_loss(kp, cloud, beta=1e-3).item() == pytest.approx(0.5 * gap**2 / 1e-3)  # quadratic part


def test_coverage_gradient_grows_the_keypoint_box():
    cloud = _cube_cloud(0.1)
    kp = _t([[[0.0, 0.0, 0.0], [0.05, 0.1, 0.1]]]).requires_grad_()
    coverage_loss(kp, cloud, beta=1e-4).backward()
    assert torch.isfinite(kp.grad).all()
    assert kp.grad[0, 1, 0] < 0  # descending moves the max-x keypoint outwards


# -- consistency ------------------------------------------------------------------------------
def test_consistency_zero_when_views_agree_in_observation_frame():
    gen = torch.Generator().manual_seed(0)
    kp_obs = torch.randn(2, 5, 3, generator=gen, dtype=torch.float64)
    R_a, R_b = GROUP[[3, 10]], GROUP[[17, 0]]
    # k_can = R^-1 k_obs, i.e. rows k_obs @ R.
    kp_a, kp_b = kp_obs @ R_a, kp_obs @ R_b
    assert consistency_loss(kp_a, R_a, kp_b, R_b).item() == pytest.approx(0.0, abs=1e-20)


def test_consistency_known_value():
    R = torch.eye(3, dtype=torch.float64)[None]
    kp_a = _t([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
    kp_b = _t([[[0.0, 0.0, 2.0], [1.0, 0.0, 0.0]]])
    assert consistency_loss(kp_a, R, kp_b, R).item() == pytest.approx(4.0 / 2)
    # A rotation applied to view b: R_b k_b for R_b = 90 deg about z maps (1, 0, 0) to (0, 1, 0).
    Rz = _t([[[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]])
    kp_b2 = _t([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
    assert consistency_loss(kp_a, R, kp_b2, Rz).item() == pytest.approx(2.0 / 2)  # |(1,0,0)-(0,1,0)|^2 = 2


def test_reduction_none_gives_per_sample_values():
    kp = _t([[[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]], [[0.0, 0.0, 0.0], [0.02, 0.0, 0.0]]])
    per = separation_loss(kp, 0.03, reduction="none")
    assert per.shape == (2,)
    np.testing.assert_allclose(per.numpy(), [0.02**2, 0.01**2])
    assert separation_loss(kp, 0.03).item() == pytest.approx(per.mean().item())
    with pytest.raises(InvalidParameterError, match="reduction"):
        separation_loss(kp, 0.03, reduction="sum")


# -- total ------------------------------------------------------------------------------------
def test_keypoint_loss_is_the_weighted_sum_and_gradients_flow():
    gen = torch.Generator().manual_seed(1)
    cloud_a = torch.rand(2, 64, 3, generator=gen, dtype=torch.float64) * 0.1
    cloud_b = torch.rand(2, 48, 3, generator=gen, dtype=torch.float64) * 0.1
    kp_a = cloud_a[:, :6].clone().requires_grad_()
    kp_b = (cloud_b[:, :6] + 0.003).requires_grad_()
    R_a, R_b = GROUP[[0, 5]], GROUP[[9, 0]]
    before = [t.clone() for t in (cloud_a, cloud_b, R_a, R_b)]
    w = KeypointLossWeights(lambda_sep=2.0, lambda_heur=0.5, lambda_cons=3.0, alpha_surf=4.0, alpha_cov=5.0)
    total, parts = keypoint_loss(kp_a, cloud_a, R_a, kp_b, cloud_b, R_b, w)
    expected_sep = 0.5 * (separation_loss(kp_a, w.margin) + separation_loss(kp_b, w.margin))
    assert parts["sep"].item() == pytest.approx(expected_sep.item())
    assert parts["heur"].item() == pytest.approx(4.0 * parts["surf"].item() + 5.0 * parts["cov"].item())
    assert parts["cons"].item() == pytest.approx(consistency_loss(kp_a, R_a, kp_b, R_b).item())
    expected = 2.0 * parts["sep"] + 0.5 * parts["heur"] + 3.0 * parts["cons"]
    assert total.item() == pytest.approx(expected.item())
    total.backward()
    for kp in (kp_a, kp_b):
        assert torch.isfinite(kp.grad).all() and kp.grad.abs().sum() > 0
    for b, t in zip(before, (cloud_a, cloud_b, R_a, R_b), strict=True):
        assert torch.equal(b, t)


def test_weights_are_validated():
    with pytest.raises(InvalidParameterError, match="margin"):
        KeypointLossWeights(margin=0.0)
    with pytest.raises(InvalidParameterError, match="lambda_sep"):
        KeypointLossWeights(lambda_sep=-1.0)
    with pytest.raises(InvalidParameterError, match="alpha_cov"):
        KeypointLossWeights(alpha_cov=math.nan)


def test_shape_errors_say_what_came():
    with pytest.raises(InvalidParameterError, match=r"\(B, count, 3\)"):
        surface_loss(torch.zeros(4, 3), torch.zeros(1, 4, 3))
    with pytest.raises(InvalidParameterError, match="batch size"):
        surface_loss(torch.zeros(2, 4, 3), torch.zeros(1, 4, 3))
    with pytest.raises(InvalidParameterError, match="at least 2"):
        separation_loss(torch.zeros(1, 1, 3), 0.1)
    with pytest.raises(InvalidParameterError, match="R_a"):
        consistency_loss(
            torch.zeros(2, 4, 3), torch.eye(3), torch.zeros(2, 4, 3), torch.eye(3).expand(2, 3, 3)
        )


# -- symmetric rotation loss ------------------------------------------------------------------
def test_symmetric_loss_equals_cross_entropy_for_single_targets():
    gen = torch.Generator().manual_seed(2)
    logits = torch.randn(5, 24, generator=gen, dtype=torch.float64)
    targets = torch.tensor([0, 3, 23, 7, 7])
    expected = F.cross_entropy(logits, targets)
    as_lists = symmetric_rotation_loss(logits, [[int(t)] for t in targets])
    as_mask = symmetric_rotation_loss(logits, F.one_hot(targets, 24).bool())
    assert as_lists.item() == pytest.approx(expected.item())
    assert as_mask.item() == pytest.approx(expected.item())


def test_symmetric_loss_decreases_as_the_set_grows_and_matches_summed_probability():
    gen = torch.Generator().manual_seed(3)
    logits = torch.randn(1, 24, generator=gen, dtype=torch.float64)
    probs = torch.softmax(logits, dim=-1)[0]
    values = [symmetric_rotation_loss(logits, [list(range(n))]).item() for n in (1, 2, 4, 8, 24)]
    assert all(b < a for a, b in zip(values, values[1:], strict=False))
    assert values[2] == pytest.approx(-math.log(probs[:4].sum().item()))
    assert values[-1] == pytest.approx(0.0, abs=1e-12)  # the whole group is always right


def test_symmetric_loss_gradient_and_stability():
    logits = torch.tensor([[1000.0, -1000.0, 0.0, 5.0]], requires_grad=True)
    loss = symmetric_rotation_loss(logits, [[1, 3]])
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(logits.grad).all()
    assert logits.grad[0, 3] < 0 and logits.grad[0, 0] > 0


def test_symmetric_loss_rejects_bad_sets():
    logits = torch.zeros(2, 24)
    with pytest.raises(InvalidParameterError, match="at least one index"):
        symmetric_rotation_loss(logits, [[0], []])
    with pytest.raises(InvalidParameterError, match="outside"):
        symmetric_rotation_loss(logits, [[0], [24]])
    with pytest.raises(InvalidParameterError, match="one index set per sample"):
        symmetric_rotation_loss(logits, [[0]])


# -- spread (anti-collapse) ---------------------------------------------------------------------
def test_rms_spread_known_value():
    # Two points 2 apart: each is 1 from the mean.
    assert rms_spread(_t([[[0.0, 0, 0], [2.0, 0, 0]]])).item() == pytest.approx(1.0)
    assert rms_spread(_t([[[0.3, 0.1, 0.2]] * 5])).item() == pytest.approx(0.0, abs=1e-9)


def test_spread_loss_known_values_and_zero_above_floor():
    cloud = _t([[[-1.0, 0, 0], [1.0, 0, 0]]])  # RMS spread 1
    collapsed = _t([[[0.2, 0, 0]] * 4])
    assert spread_loss(collapsed, cloud, 0.5).item() == pytest.approx(0.25)  # (0.5 - 0)^2
    half = _t([[[-0.25, 0, 0], [0.25, 0, 0]]])  # spread 0.25 < 0.5
    assert spread_loss(half, cloud, 0.5).item() == pytest.approx(0.0625)
    assert spread_loss(cloud.clone(), cloud, 0.5).item() == 0.0
    assert spread_loss(collapsed, cloud, 0.0).item() == 0.0


def test_spread_loss_gradient_spreads_collapsed_keypoints_and_flat_objects_count():
    # A flat cloud (z = 0): the coverage term is blind (box volume 0), the spread term is not.
    g = torch.Generator().manual_seed(0)
    cloud = torch.rand(2, 50, 3, generator=g, dtype=torch.float64) * _t([1.0, 0.1, 0.0])
    kp = cloud[:, :6].mean(1, keepdim=True) + 1e-3 * torch.randn(2, 6, 3, generator=g, dtype=torch.float64)
    kp.requires_grad_(True)
    assert aabb_volume(cloud).abs().max().item() == 0.0
    loss = spread_loss(kp, cloud, 0.5)
    loss.backward()
    with torch.no_grad():
        moved = kp - 0.1 * kp.grad
    assert torch.isfinite(kp.grad).all()
    assert spread_loss(moved, cloud, 0.5).item() < loss.item()
    per = spread_loss(kp.detach(), cloud, 0.5, reduction="none")
    assert per.shape == (2,)


def test_spread_loss_rejects_bad_floor_and_shapes():
    cloud = torch.zeros(1, 5, 3)
    for floor in (-0.1, 1.5, float("nan")):
        with pytest.raises(InvalidParameterError, match="floor"):
            spread_loss(torch.zeros(1, 3, 3), cloud, floor)
    with pytest.raises(InvalidParameterError):
        spread_loss(torch.zeros(2, 3, 3), cloud, 0.5)
