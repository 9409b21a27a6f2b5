import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from keygen.errors import InvalidParameterError
from keygen.geometry import (
    RigidTransform,
    apply_transform,
    compose,
    invert_transform,
    make_transform,
    matrix_to_quat_wxyz,
    pose_to_transform,
    random_rotation,
    transform_directions,
    transform_to_pose,
    yaw_matrix,
)

SETTINGS = settings(max_examples=100, deadline=None)
seeds = st.integers(0, 2**32 - 1)
translations = arrays(np.float64, 3, elements=st.floats(-100.0, 100.0))


def random_transform(rng: np.random.Generator, size: int | None = None) -> np.ndarray:
    shape = () if size is None else (size,)
    return make_transform(random_rotation(rng, size), rng.uniform(-2, 2, (*shape, 3)))


def test_make_transform_layout_and_defaults():
    R, t = yaw_matrix(0.4), np.array([1.0, 2.0, 3.0])
    T = make_transform(R, t)
    np.testing.assert_array_equal(T[:3, :3], R)
    np.testing.assert_array_equal(T[:3, 3], t)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    np.testing.assert_array_equal(make_transform(), np.eye(4))
    np.testing.assert_array_equal(make_transform(t=t)[:3, :3], np.eye(3))
    # Batched rotations with one shared translation broadcast.
    assert make_transform(random_rotation(0, 5), t).shape == (5, 4, 4)


@SETTINGS
@given(seed=seeds, t=translations)
def test_inverse_round_trip(seed, t):
    T = make_transform(random_rotation(seed), t)
    T_inv = invert_transform(T)
    np.testing.assert_allclose(T @ T_inv, np.eye(4), atol=1e-12 * (1 + np.abs(t).max()))
    np.testing.assert_allclose(T_inv @ T, np.eye(4), atol=1e-12 * (1 + np.abs(t).max()))
    np.testing.assert_allclose(invert_transform(T_inv), T, atol=1e-12 * (1 + np.abs(t).max()))
    np.testing.assert_allclose(T_inv, np.linalg.inv(T), atol=1e-9 * (1 + np.abs(t).max()))


@SETTINGS
@given(seed=seeds)
def test_apply_inverse_recovers_points(seed):
    rng = np.random.default_rng(seed)
    T = random_transform(rng)
    pts = rng.uniform(-1, 1, (20, 3))
    moved = apply_transform(T, pts)
    np.testing.assert_allclose(apply_transform(invert_transform(T), moved), pts, atol=1e-12)
    # Rigid: pairwise distances are preserved.
    np.testing.assert_allclose(
        np.linalg.norm(moved[:, None] - moved[None], axis=-1),
        np.linalg.norm(pts[:, None] - pts[None], axis=-1),
        atol=1e-12,
    )


@SETTINGS
@given(seed=seeds)
def test_compose_matches_sequential_application(seed):
    rng = np.random.default_rng(seed)
    A, B, C = (random_transform(rng) for _ in range(3))
    pts = rng.uniform(-1, 1, (7, 3))
    expected = apply_transform(A, apply_transform(B, apply_transform(C, pts)))
    np.testing.assert_allclose(apply_transform(compose(A, B, C), pts), expected, atol=1e-12)
    np.testing.assert_allclose(compose(A), A)
    np.testing.assert_allclose(compose(A, invert_transform(A)), np.eye(4), atol=1e-12)


def test_batched_transforms_apply_per_entry():
    rng = np.random.default_rng(0)
    Ts = random_transform(rng, size=4)
    pts = rng.uniform(-1, 1, (4, 10, 3))
    out = apply_transform(Ts, pts)
    for i in range(4):
        np.testing.assert_allclose(out[i], apply_transform(Ts[i], pts[i]), atol=1e-14)
    inv = invert_transform(Ts)
    np.testing.assert_allclose(apply_transform(inv, out), pts, atol=1e-12)
    dirs = transform_directions(Ts, pts)
    np.testing.assert_allclose(dirs[2], pts[2] @ Ts[2, :3, :3].T)
    with pytest.raises(InvalidParameterError, match=r"\(\.\.\., N, 3\)"):
        apply_transform(Ts, np.zeros(3))


def test_single_transform_accepts_any_leading_shape():
    T = make_transform(yaw_matrix(np.pi / 2), [1.0, 0.0, 0.0])
    np.testing.assert_allclose(apply_transform(T, [1.0, 0.0, 0.0]), [1.0, 1.0, 0.0], atol=1e-15)
    assert apply_transform(T, np.zeros((2, 5, 3))).shape == (2, 5, 3)
    # Directions ignore the translation.
    np.testing.assert_allclose(transform_directions(T, [1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-15)


@SETTINGS
@given(seed=seeds, t=translations)
def test_pose_round_trip(seed, t):
    R = random_rotation(seed)
    T = make_transform(R, t)
    pos, quat = transform_to_pose(T)
    assert quat[0] >= 0 and np.isclose(np.linalg.norm(quat), 1.0)
    np.testing.assert_allclose(pose_to_transform(pos, quat), T, atol=1e-12)
    np.testing.assert_allclose(quat, matrix_to_quat_wxyz(R))


def test_pose_to_transform_normalises_quaternion_and_batches():
    T = pose_to_transform([0.0, 0.0, 1.0], [2.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(T, make_transform(np.eye(3), [0, 0, 1.0]))
    q = np.tile([1.0, 0, 0, 0], (3, 1))
    assert pose_to_transform(np.zeros((3, 3)), q).shape == (3, 4, 4)


@pytest.mark.parametrize(
    "bad, message",
    [
        (np.eye(3), r"\(4, 4\)"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), "proper rotation"),
        (np.diag([2.0, 2.0, 2.0, 1.0]), "proper rotation"),
        (np.vstack([np.eye(4)[:3], [0, 0, 1, 1]]), "last row"),
        (np.full((4, 4), np.nan), "NaN"),
    ],
)
def test_bad_transforms_rejected(bad, message):
    with pytest.raises(InvalidParameterError, match=message):
        invert_transform(bad)
    with pytest.raises(InvalidParameterError):
        apply_transform(bad, np.zeros((1, 3)))


def test_make_transform_validation():
    with pytest.raises(InvalidParameterError, match="proper rotation"):
        make_transform(np.ones((3, 3)), np.zeros(3))
    with pytest.raises(InvalidParameterError, match="translation"):
        make_transform(np.eye(3), np.zeros(4))
    with pytest.raises(InvalidParameterError, match="at least one"):
        compose()
    with pytest.raises(InvalidParameterError, match="points"):
        apply_transform(np.eye(4), np.zeros((5, 2)))


# -- RigidTransform -----------------------------------------------------------------------
@SETTINGS
@given(seed=seeds)
def test_rigid_transform_matches_matrix_functions(seed):
    rng = np.random.default_rng(seed)
    A, B = random_transform(rng), random_transform(rng)
    a, b = RigidTransform.from_matrix(A), RigidTransform.from_matrix(B)
    np.testing.assert_allclose((a @ b).as_matrix(), A @ B, atol=1e-12)
    np.testing.assert_allclose(a.inverse().as_matrix(), invert_transform(A), atol=1e-12)
    assert (a @ a.inverse()).allclose(RigidTransform.identity(), atol=1e-12)
    pts = rng.uniform(-1, 1, (5, 3))
    np.testing.assert_allclose(a.apply(pts), apply_transform(A, pts), atol=1e-12)
    np.testing.assert_allclose(a.apply_directions(pts), transform_directions(A, pts), atol=1e-12)
    pos, quat = a.as_pose()
    assert RigidTransform.from_pose(pos, quat).allclose(a, atol=1e-12)


def test_rigid_transform_is_immutable_and_copies_inputs():
    R = yaw_matrix(0.2)
    t = np.array([1.0, 2.0, 3.0])
    tf = RigidTransform(R, t)
    t[0] = 100.0  # the caller's array is not shared
    assert tf.translation[0] == 1.0
    with pytest.raises(ValueError):
        tf.translation[0] = 5.0
    with pytest.raises(AttributeError):
        tf.rotation = np.eye(3)
    assert "RigidTransform(" in repr(tf)


def test_rigid_transform_validation():
    with pytest.raises(InvalidParameterError, match="proper rotation"):
        RigidTransform(np.diag([1.0, -1.0, 1.0]), np.zeros(3))
    with pytest.raises(InvalidParameterError, match="one transform"):
        RigidTransform(random_rotation(0, 2), np.zeros(3))
    with pytest.raises(InvalidParameterError, match="one \\(4, 4\\)"):
        RigidTransform.from_matrix(np.stack([np.eye(4)] * 2))
    with pytest.raises(TypeError):
        RigidTransform.identity() @ np.eye(4)
