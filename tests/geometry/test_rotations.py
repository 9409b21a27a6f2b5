import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from keygen.errors import InvalidParameterError, KeyGenError
from keygen.geometry import (
    axis_angle_to_matrix,
    is_rotation,
    matrix_to_axis_angle,
    matrix_to_quat_wxyz,
    matrix_to_rot6d,
    nearest_octahedral,
    octahedral_group,
    octahedral_index,
    octahedral_inverse_indices,
    octahedral_multiplication_table,
    quat_wxyz_to_matrix,
    random_rotation,
    rot6d_to_matrix,
    rotation_angle_between,
    yaw_matrix,
)

SETTINGS = settings(max_examples=100, deadline=None)

# Quaternions from bounded floats: covers near-identity, half turns and axis-aligned cases
# that a Gaussian sampler rarely hits.
finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
quaternions = arrays(np.float64, 4, elements=finite).filter(lambda q: np.linalg.norm(q) > 1e-3)
seeds = st.integers(0, 2**32 - 1)


# -- octahedral group ---------------------------------------------------------------------
def test_group_has_24_distinct_proper_rotations():
    G = octahedral_group()
    assert G.shape == (24, 3, 3)
    assert len({g.tobytes() for g in G}) == 24
    assert np.all(is_rotation(G))
    np.testing.assert_allclose(np.linalg.det(G), 1.0)
    # Signed permutation matrices: one +-1 per row and column.
    assert np.all(np.abs(G).sum(axis=1) == 1) and np.all(np.abs(G).sum(axis=2) == 1)


def test_group_identity_first_and_read_only():
    G = octahedral_group()
    np.testing.assert_array_equal(G[0], np.eye(3))
    assert octahedral_group() is G  # cached
    with pytest.raises(ValueError):
        G[0, 0, 0] = 5.0


def test_group_order_is_the_documented_one():
    expected = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1, -1), repeat=3):
            g = np.zeros((3, 3))
            g[np.arange(3), perm] = signs
            if np.linalg.det(g) > 0:
                expected.append(g)
    np.testing.assert_array_equal(octahedral_group(), np.stack(expected))


def test_group_closed_and_table_consistent():
    G = octahedral_group()
    table = octahedral_multiplication_table()
    assert table.shape == (24, 24) and table.dtype.kind == "i"
    for i in range(24):
        for j in range(24):
            np.testing.assert_array_equal(G[i] @ G[j], G[table[i, j]])
    # Latin square: each row and column is a permutation of the group (cancellation law).
    assert all(sorted(row) == list(range(24)) for row in table)
    assert all(sorted(col) == list(range(24)) for col in table.T)
    np.testing.assert_array_equal(table[0], np.arange(24))


def test_group_inverses():
    G = octahedral_group()
    inv = octahedral_inverse_indices()
    table = octahedral_multiplication_table()
    for i in range(24):
        np.testing.assert_array_equal(G[i] @ G[inv[i]], np.eye(3))
        assert table[i, inv[i]] == 0 and table[inv[i], i] == 0
    np.testing.assert_array_equal(inv[inv], np.arange(24))


@SETTINGS
@given(i=st.integers(0, 23), j=st.integers(0, 23), k=st.integers(0, 23))
def test_group_associative(i, j, k):
    t = octahedral_multiplication_table()
    assert t[t[i, j], k] == t[i, t[j, k]]


def test_octahedral_index_round_trip_and_tolerance():
    G = octahedral_group()
    for k in range(24):
        assert octahedral_index(G[k]) == k
        assert octahedral_index(G[k] + 1e-8) == k
    with pytest.raises(InvalidParameterError, match="nearest_octahedral"):
        octahedral_index(yaw_matrix(0.3))
    with pytest.raises(InvalidParameterError):
        octahedral_index(np.eye(4))


@SETTINGS
@given(k=st.integers(0, 23), seed=seeds)
def test_nearest_octahedral_snaps_small_perturbations(k, seed):
    rng = np.random.default_rng(seed)
    # Cube rotations are at least 90 degrees apart, so a perturbation under 45 degrees snaps back.
    axis = rng.standard_normal(3)
    small = axis_angle_to_matrix(axis, rng.uniform(0, np.deg2rad(40)))
    assert nearest_octahedral(octahedral_group()[k] @ small) == k


@SETTINGS
@given(seed=seeds)
def test_nearest_octahedral_is_the_minimum_angle(seed):
    R = random_rotation(seed)
    best = nearest_octahedral(R)
    angles = rotation_angle_between(octahedral_group(), R)
    assert angles[best] <= angles.min() + 1e-9
    # Every rotation is within the covering radius of the group (about 62.8 degrees).
    assert angles.min() <= np.deg2rad(62.8 + 1e-6)


def test_nearest_octahedral_batched():
    R = random_rotation(3, size=(2, 5))
    out = nearest_octahedral(R)
    assert out.shape == (2, 5)
    assert out[1, 2] == nearest_octahedral(R[1, 2])


# -- 6D -----------------------------------------------------------------------------------
def test_rot6d_is_first_two_columns():
    R = random_rotation(0)
    x = matrix_to_rot6d(R)
    np.testing.assert_array_equal(x, np.concatenate([R[:, 0], R[:, 1]]))


@SETTINGS
@given(seed=seeds)
def test_rot6d_round_trip(seed):
    R = random_rotation(seed, size=8)
    np.testing.assert_allclose(rot6d_to_matrix(matrix_to_rot6d(R)), R, atol=1e-12)


@SETTINGS
@given(x=arrays(np.float64, 6, elements=st.floats(-10, 10)))
def test_rot6d_any_non_degenerate_vector_gives_rotation(x):
    a1, a2 = x[:3], x[3:]
    if np.linalg.norm(a1) < 1e-3 or np.linalg.norm(np.cross(a1, a2)) < 1e-3 * np.linalg.norm(a1):
        return
    R = rot6d_to_matrix(x)
    assert is_rotation(R, atol=1e-9)
    # Gram-Schmidt keeps the first column's direction and the plane of the first two.
    np.testing.assert_allclose(R[:, 0], a1 / np.linalg.norm(a1), atol=1e-9)
    assert np.dot(np.cross(R[:, 0], R[:, 1]), np.cross(a1, a2)) > 0


def test_rot6d_degenerate_and_bad_shape():
    with pytest.raises(InvalidParameterError, match="zero first column"):
        rot6d_to_matrix(np.array([0, 0, 0, 1, 0, 0.0]))
    with pytest.raises(InvalidParameterError, match="parallel"):
        rot6d_to_matrix(np.array([1, 0, 0, 2, 0, 0.0]))
    with pytest.raises(InvalidParameterError, match=r"\(\.\.\., 6\)"):
        rot6d_to_matrix(np.zeros(5))
    with pytest.raises(KeyGenError):
        matrix_to_rot6d(np.zeros((3, 4)))


# -- quaternions --------------------------------------------------------------------------
def test_quat_wxyz_known_values():
    np.testing.assert_allclose(quat_wxyz_to_matrix([1, 0, 0, 0]), np.eye(3))
    half = np.sqrt(0.5)
    # 90 degrees about z: (w, x, y, z) = (cos 45, 0, 0, sin 45)
    np.testing.assert_allclose(quat_wxyz_to_matrix([half, 0, 0, half]), yaw_matrix(np.pi / 2), atol=1e-15)
    np.testing.assert_allclose(matrix_to_quat_wxyz(yaw_matrix(np.pi / 2)), [half, 0, 0, half], atol=1e-15)
    # Half turn about x: w = 0, the sign is fixed by the largest component.
    q = matrix_to_quat_wxyz(np.diag([1.0, -1.0, -1.0]))
    np.testing.assert_allclose(np.abs(q), [0, 1, 0, 0], atol=1e-15)


@SETTINGS
@given(q=quaternions)
def test_quaternion_round_trip_up_to_sign(q):
    unit = q / np.linalg.norm(q)
    R = quat_wxyz_to_matrix(q)
    assert is_rotation(R, atol=1e-9)
    back = matrix_to_quat_wxyz(R)
    assert np.isclose(np.linalg.norm(back), 1.0)
    assert back[0] >= 0
    assert min(np.abs(back - unit).max(), np.abs(back + unit).max()) < 1e-9


@SETTINGS
@given(seed=seeds)
def test_matrix_quaternion_round_trip_batched(seed):
    R = random_rotation(seed, size=(3, 4))
    q = matrix_to_quat_wxyz(R)
    assert q.shape == (3, 4, 4)
    np.testing.assert_allclose(quat_wxyz_to_matrix(q), R, atol=1e-12)


def test_quaternion_composition_matches_matrix_product():
    # Hamilton product in (w, x, y, z) order corresponds to R(q1) @ R(q2).
    def hamilton(a, b):
        w1, x1, y1, z1 = a
        w2, x2, y2, z2 = b
        return np.array(
            [
                w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
                w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
            ]
        )

    R1, R2 = random_rotation(1), random_rotation(2)
    q = hamilton(matrix_to_quat_wxyz(R1), matrix_to_quat_wxyz(R2))
    np.testing.assert_allclose(quat_wxyz_to_matrix(q), R1 @ R2, atol=1e-12)


def test_quaternion_errors():
    with pytest.raises(InvalidParameterError, match="zero norm"):
        quat_wxyz_to_matrix(np.zeros(4))
    with pytest.raises(InvalidParameterError, match="NaN"):
        quat_wxyz_to_matrix([np.nan, 0, 0, 1])


# -- axis-angle ---------------------------------------------------------------------------
@SETTINGS
@given(seed=seeds)
def test_axis_angle_round_trip(seed):
    R = random_rotation(seed, size=6)
    rotvec = matrix_to_axis_angle(R)
    assert np.all(np.linalg.norm(rotvec, axis=-1) <= np.pi + 1e-12)
    np.testing.assert_allclose(axis_angle_to_matrix(rotvec), R, atol=1e-12)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-6, 0.5, np.pi - 1e-7, np.pi])
def test_axis_angle_edge_angles(angle):
    axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    R = axis_angle_to_matrix(axis, angle)
    assert is_rotation(R, atol=1e-12)
    rotvec = matrix_to_axis_angle(R)
    np.testing.assert_allclose(np.linalg.norm(rotvec), angle, atol=1e-9)
    if angle > 1e-3:
        # At pi the axis is only defined up to sign.
        assert abs(abs(np.dot(rotvec / np.linalg.norm(rotvec), axis)) - 1) < 1e-9
    np.testing.assert_allclose(axis_angle_to_matrix(rotvec), R, atol=1e-9)


def test_axis_angle_two_forms_agree_and_batch():
    axes = np.array([[0, 0, 2.0], [1.0, 1.0, 0]])
    angles = np.array([0.3, -1.2])
    R = axis_angle_to_matrix(axes, angles)
    unit = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    np.testing.assert_allclose(R, axis_angle_to_matrix(unit * angles[:, None]), atol=1e-15)
    np.testing.assert_allclose(R[0], yaw_matrix(0.3), atol=1e-15)
    np.testing.assert_array_equal(axis_angle_to_matrix(np.zeros(3)), np.eye(3))
    with pytest.raises(InvalidParameterError, match="zero vector"):
        axis_angle_to_matrix(np.zeros(3), 1.0)


# -- angles, sampling, yaw, checks --------------------------------------------------------
@SETTINGS
@given(seed=seeds, angle=st.floats(0.0, np.pi))
def test_rotation_angle_between_recovers_angle(seed, angle):
    rng = np.random.default_rng(seed)
    R1 = random_rotation(rng)
    R2 = R1 @ axis_angle_to_matrix(rng.standard_normal(3) + 1e-3, angle)
    assert abs(rotation_angle_between(R1, R2) - angle) < 1e-9
    assert abs(rotation_angle_between(R2, R1) - angle) < 1e-9


def test_rotation_angle_between_small_angles_accurate():
    # arccos of the trace would give ~1e-8 here; the atan2 form keeps full precision.
    assert abs(rotation_angle_between(np.eye(3), yaw_matrix(1e-10)) - 1e-10) < 1e-20


def test_random_rotation_shapes_seeding_and_uniformity():
    assert random_rotation(0).shape == (3, 3)
    assert random_rotation(0, size=5).shape == (5, 3, 3)
    assert random_rotation(0, size=(2, 3)).shape == (2, 3, 3, 3)
    np.testing.assert_array_equal(random_rotation(7, 4), random_rotation(np.random.default_rng(7), 4))
    R = random_rotation(11, size=20000)
    assert np.all(is_rotation(R, atol=1e-9))
    # Haar measure: E[R] = 0, and the angle density is (1 - cos t) / pi, so E[angle] = pi/2 + 2/pi.
    assert np.abs(R.mean(axis=0)).max() < 0.02
    angles = rotation_angle_between(np.eye(3), R)
    assert abs(angles.mean() - (np.pi / 2 + 2 / np.pi)) < 0.02


def test_yaw_matrix():
    R = yaw_matrix(np.pi / 2)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(R @ [0, 0, 1], [0, 0, 1])
    batch = yaw_matrix(np.array([[0.0, 1.0], [2.0, 3.0]]))
    assert batch.shape == (2, 2, 3, 3)
    np.testing.assert_allclose(batch[1, 0], yaw_matrix(2.0))


def test_is_rotation():
    assert is_rotation(np.eye(3))
    assert not is_rotation(np.diag([1.0, 1.0, -1.0]))  # a reflection
    assert not is_rotation(2 * np.eye(3))
    assert not is_rotation(np.eye(4))
    assert not is_rotation(np.full((3, 3), np.nan))
    assert is_rotation(np.eye(3) + 1e-8, atol=1e-6)
    assert not is_rotation(np.eye(3) + 1e-4, atol=1e-6)
    batch = np.stack([np.eye(3), -np.eye(3)])
    np.testing.assert_array_equal(is_rotation(batch), [True, False])


def test_non_finite_rotation_rejected():
    with pytest.raises(InvalidParameterError, match="NaN"):
        matrix_to_quat_wxyz(np.full((3, 3), np.nan))
