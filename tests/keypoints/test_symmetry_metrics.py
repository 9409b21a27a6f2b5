"""Symmetry sets, rotation labels and the keypoint metrics on inputs whose answer is known."""

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from keygen.errors import InvalidParameterError
from keygen.geometry.rotations import octahedral_group, yaw_matrix
from keygen.keypoints import metrics as M
from keygen.keypoints.symmetry import (
    SymmetryReference,
    equivalent_labels,
    instance_symmetry_set,
    is_axial,
    rotation_label,
    scan_equivalence_set,
    surface_sample,
    yaw_indices,
)

G = octahedral_group()


def test_yaw_indices_are_the_rotations_about_z():
    idx = yaw_indices()
    assert idx[0] == 0 and len(set(idx)) == 4
    for k, i in enumerate(idx):
        np.testing.assert_allclose(G[i], yaw_matrix(k * np.pi / 2), atol=1e-12)


def test_cylinder_is_axial_and_a_box_has_the_three_half_turns():
    cyl = surface_sample(trimesh.creation.cylinder(radius=0.05, height=0.08), 4000)
    sym = instance_symmetry_set(cyl, 0.13)
    assert set(yaw_indices()) <= set(sym) and is_axial(sym)
    box = surface_sample(trimesh.creation.box([0.2, 0.1, 0.05]), 4000)
    sym_box = instance_symmetry_set(box, 0.23)
    # identity and the 180-degree turns about x, y and z: the diagonal sign matrices
    expected = [i for i, g in enumerate(G) if np.allclose(np.abs(g), np.eye(3))]
    assert sorted(sym_box) == expected and not is_axial(sym_box)


def test_scan_equivalence_sees_hidden_asymmetry():
    # A box with a bump on +x; a "scan" that sees only the -x half fits the half-turn about z too.
    body = trimesh.creation.box([0.1, 0.1, 0.1])
    bump = trimesh.creation.box([0.04, 0.02, 0.02])
    bump.apply_translation([0.07, 0.0, 0.0])
    shape = surface_sample(trimesh.util.concatenate([body, bump]), 6000)
    ref = SymmetryReference(shape, 0.2)
    R, t = yaw_matrix(0.3), np.array([0.5, 0.2, 0.0])
    half_turn = yaw_indices()[2]
    visible = shape[shape[:, 0] < -0.02]
    assert half_turn in scan_equivalence_set(visible @ R.T + t, R, t, ref)
    assert half_turn not in scan_equivalence_set(shape @ R.T + t, R, t, ref)


def test_rotation_labels_snap_to_the_nearest_element_and_expand_over_sets():
    assert rotation_label(yaw_matrix(np.radians(30))) == 0
    assert rotation_label(yaw_matrix(np.radians(80))) == yaw_indices()[1]
    labels = equivalent_labels(yaw_matrix(np.radians(10)), yaw_indices())
    assert labels == sorted(yaw_indices())


def test_pair_errors_known_values_and_symmetry():
    xa = np.array([[0.1, 0.0, 0.0], [0.0, 0.1, 0.05], [0.0, 0.0, 0.1]])
    np.testing.assert_allclose(M.pair_errors(xa, xa + [0.0, 0.0, 0.01]), [0.01] * 3)
    turned = xa @ yaw_matrix(0.7).T
    assert M.pair_errors(xa, turned).max() > 0.05
    np.testing.assert_allclose(M.pair_errors(xa, turned, axial=True), 0.0, atol=1e-12)
    flipped = xa @ G[1].T  # half-turn about x
    np.testing.assert_allclose(M.pair_errors(xa, flipped, symmetry=[0, 1]), 0.0, atol=1e-12)
    with pytest.raises(InvalidParameterError):
        M.pair_errors(xa, xa[:2])


def test_canonicalizer_accuracy_counts_top1_set_and_sym():
    R = np.stack([yaw_matrix(np.radians(a)) for a in (10.0, 44.0, 100.0)])
    eq = np.zeros((3, 24), bool)
    eq[:, 0] = True
    eq[2, list(yaw_indices())] = True  # the third scan is symmetric under yaw
    y = yaw_indices()
    acc = M.canonicalizer_accuracy(np.array([0, y[1], y[3]]), R, eq)
    # top-1: only the first; set: first and third; sym: the second is 46 deg away from its label -> ok
    assert acc["canon_acc_top1"] == pytest.approx(1 / 3)
    assert acc["canon_acc_set"] == pytest.approx(2 / 3)
    assert acc["canon_acc_sym"] == pytest.approx(1.0)


def test_dual_alignment_score_perfect_and_shuffled():
    anchors = {"a": np.array([0.0, 0.0, 0.0]), "b": np.array([0.1, 0.0, 0.0]), "c": np.array([0.0, 0.1, 0.0])}
    kp = np.stack([anchors["a"], anchors["b"], anchors["c"]]) + 0.001
    scans = [kp.copy() for _ in range(6)]
    ref = np.array([True] * 3 + [False] * 3)
    assert M.dual_alignment_score(scans, [anchors] * 6, ref)["das"] == 1.0
    shuffled = scans[:3] + [kp[[1, 2, 0]]] * 3  # every index moved to another anchor
    assert M.dual_alignment_score(shuffled, [anchors] * 6, ref)["das"] == 0.0
    with pytest.raises(InvalidParameterError):
        M.dual_alignment_score(scans, [anchors] * 6, np.ones(6, bool))


def test_anchor_points_drop_what_symmetry_moves():
    anchors = {"axis": np.array([0.0, 0.0, 0.05]), "rim": np.array([0.06, 0.0, 0.05])}
    assert set(M.anchor_points(anchors, [0], False, 0.15)) == {"axis", "rim"}
    assert set(M.anchor_points(anchors, list(yaw_indices()), True, 0.15)) == {"axis"}


def test_coverage_inclusivity_volume_ratio():
    anchors = {"a": np.zeros(3), "b": np.array([1.0, 0.0, 0.0])}
    kp = np.array([[0.0, 0.0, 0.05], [0.5, 0.0, 0.0]])
    assert M.coverage(kp, anchors, diameter=1.0, radius=0.1) == 0.5
    tree = cKDTree(np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]))
    assert M.inclusivity(kp, tree, diameter=1.0, radius=0.03) == 0.5
    cloud = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    assert M.volume_ratio(np.array([[0.0, 0.0, 0.0], [0.5, 0.5, 0.5]]), cloud) == pytest.approx(0.125)
