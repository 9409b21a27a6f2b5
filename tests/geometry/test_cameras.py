import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from keygen.errors import InvalidParameterError
from keygen.geometry import (
    apply_transform,
    backproject_depth,
    camera_points_to_world,
    fov_from_intrinsics,
    intrinsics_from_fov,
    invert_transform,
    is_rotation,
    look_at,
    make_transform,
    opencv_to_opengl,
    opengl_to_opencv,
    project_points,
    random_rotation,
)

SETTINGS = settings(max_examples=50, deadline=None)
W, H, FOVY = 64, 48, 45.0


def plane_depth(K: np.ndarray, normal_cam: np.ndarray, offset: float, h: int, w: int) -> np.ndarray:
    """z-depth image of the plane {p : n . p = offset} seen by a camera at the origin."""
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.stack([(cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1], np.ones_like(rows)], axis=-1)
    # Each ray has z = 1, so the hit's z-depth is the ray parameter.
    return offset / (rays @ normal_cam)


def test_intrinsics_from_fov_matches_mujoco_convention():
    K = intrinsics_from_fov(W, H, FOVY)
    f = (H / 2) / np.tan(np.deg2rad(FOVY) / 2)
    np.testing.assert_allclose(K, [[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]])
    fovx, fovy = fov_from_intrinsics(K, W, H)
    assert np.isclose(fovy, FOVY)
    # Square pixels: the horizontal fov follows from the aspect ratio.
    assert np.isclose(np.tan(np.deg2rad(fovx) / 2), np.tan(np.deg2rad(FOVY) / 2) * W / H)


@SETTINGS
@given(w=st.integers(1, 4000), h=st.integers(1, 4000), fovy=st.floats(1.0, 170.0))
def test_fov_round_trip(w, h, fovy):
    assert np.isclose(fov_from_intrinsics(intrinsics_from_fov(w, h, fovy), w, h)[1], fovy)


def test_intrinsics_validation():
    with pytest.raises(InvalidParameterError, match="fovy_deg"):
        intrinsics_from_fov(W, H, 180.0)
    with pytest.raises(InvalidParameterError, match="image size"):
        intrinsics_from_fov(0, H, 45.0)
    with pytest.raises(InvalidParameterError, match="fx, fy > 0"):
        fov_from_intrinsics(np.zeros((3, 3)), W, H)


def test_backproject_fronto_parallel_plane():
    K = intrinsics_from_fov(W, H, FOVY)
    depth = np.full((H, W), 1.5)
    pts, pix = backproject_depth(depth, K, return_pixels=True)
    assert pts.shape == (H * W, 3) and pix.shape == (H * W, 2)
    np.testing.assert_allclose(pts[:, 2], 1.5)
    # Row-major order, and image right / down are camera +x / +y.
    np.testing.assert_array_equal(pix[:3], [[0, 0], [0, 1], [0, 2]])
    assert pts[1, 0] > pts[0, 0] and pts[W, 1] > pts[0, 1]
    # The image centre lies on the optical axis; the top edge is at half the vertical fov.
    centre = pts[(pix[:, 0] == H // 2) & (pix[:, 1] == W // 2)][0]
    assert abs(centre[0]) < 1.5 / K[0, 0] and abs(centre[1]) < 1.5 / K[1, 1]
    top = pts[pix[:, 0] == 0, 1].mean() - 0.5 * 1.5 / K[1, 1]  # outer edge of the top row
    assert np.isclose(np.degrees(np.arctan2(-top, 1.5)), FOVY / 2)


@SETTINGS
@given(
    normal=arrays(np.float64, 3, elements=st.floats(-0.5, 0.5)),
    offset=st.floats(0.2, 5.0),
)
def test_backproject_recovers_tilted_plane(normal, offset):
    n = normal + np.array([0.0, 0.0, 1.0])  # facing the camera, at most ~40 degrees tilted
    n /= np.linalg.norm(n)
    K = intrinsics_from_fov(W, H, FOVY)
    depth = plane_depth(K, n, offset, H, W)
    pts = backproject_depth(depth, K)
    np.testing.assert_allclose(pts @ n, offset, rtol=1e-9)
    # A plane fit (SVD) recovers the same normal.
    centred = pts - pts.mean(axis=0)
    fitted = np.linalg.svd(centred, full_matrices=False)[2][-1]
    assert abs(abs(fitted @ n) - 1.0) < 1e-9


@SETTINGS
@given(seed=st.integers(0, 2**32 - 1))
def test_project_backproject_recovers_pixels(seed):
    rng = np.random.default_rng(seed)
    K = intrinsics_from_fov(W, H, rng.uniform(20, 100))
    depth = rng.uniform(0.1, 4.0, (H, W))
    pts, pix = backproject_depth(depth, K, return_pixels=True)
    uv, z = project_points(pts, K)
    np.testing.assert_allclose(uv, pix[:, ::-1], atol=1e-9)  # (u, v) = (col, row)
    np.testing.assert_allclose(z, depth[pix[:, 0], pix[:, 1]])


def test_backproject_skips_invalid_depth_and_masks():
    K = intrinsics_from_fov(4, 3, 60.0)
    depth = np.array([[0.0, 1.0, np.inf, np.nan], [2.0, 3.0, -1.0, 0.5], [1.0, 1.0, 1.0, 10.0]])
    pts, pix = backproject_depth(depth, K, return_pixels=True)
    np.testing.assert_array_equal(pix, [[0, 1], [1, 0], [1, 1], [1, 3], [2, 0], [2, 1], [2, 2], [2, 3]])
    assert np.all(np.isfinite(pts))
    _, pix = backproject_depth(depth, K, min_depth=0.9, max_depth=2.5, return_pixels=True)
    np.testing.assert_array_equal(pix, [[0, 1], [1, 0], [2, 0], [2, 1], [2, 2]])
    mask = np.zeros_like(depth, dtype=bool)
    mask[2] = True
    _, pix = backproject_depth(depth, K, mask=mask, return_pixels=True)
    np.testing.assert_array_equal(pix[:, 0], [2, 2, 2, 2])
    assert backproject_depth(np.zeros((3, 4)), K).shape == (0, 3)


def test_backproject_validation():
    K = intrinsics_from_fov(4, 3, 60.0)
    with pytest.raises(InvalidParameterError, match=r"\(H, W\)"):
        backproject_depth(np.zeros(12), K)
    with pytest.raises(InvalidParameterError, match="mask"):
        backproject_depth(np.ones((3, 4)), K, mask=np.ones((4, 3), dtype=bool))
    with pytest.raises(InvalidParameterError, match="min_depth <= max_depth"):
        backproject_depth(np.ones((3, 4)), K, min_depth=2.0, max_depth=1.0)


def test_project_points_behind_camera_is_nan():
    K = intrinsics_from_fov(W, H, FOVY)
    uv, z = project_points(np.array([[0.0, 0.0, 2.0], [0.1, 0.0, -1.0], [0.0, 0.0, 0.0]]), K)
    np.testing.assert_allclose(uv[0], [(W - 1) / 2, (H - 1) / 2])
    assert np.all(np.isnan(uv[1:])) and np.array_equal(z, [2.0, -1.0, 0.0])
    with pytest.raises(InvalidParameterError, match=r"\(\.\.\., 3\)"):
        project_points(np.zeros((3, 2)), K)


@SETTINGS
@given(
    eye=arrays(np.float64, 3, elements=st.floats(-3, 3)),
    target=arrays(np.float64, 3, elements=st.floats(-3, 3)),
)
def test_look_at_puts_target_on_optical_axis(eye, target):
    forward = target - eye
    # Degenerate views (eye at the target, looking straight up or down) are tested separately.
    assume(np.linalg.norm(np.cross(forward, [0, 0, 1])) > 1e-3)
    T = look_at(eye, target)
    assert is_rotation(T[:3, :3], atol=1e-9)
    np.testing.assert_allclose(T[:3, 3], eye)
    target_cam = apply_transform(invert_transform(T), target)
    np.testing.assert_allclose(target_cam[:2], 0.0, atol=1e-9)
    assert np.isclose(target_cam[2], np.linalg.norm(forward))
    # Image "down" (+y) points against world up; image x is horizontal.
    assert T[:3, 1] @ [0, 0, 1] < 0 and abs(T[2, 0]) < 1e-12
    K = intrinsics_from_fov(W, H, FOVY)
    uv, _ = project_points(target_cam, K)
    np.testing.assert_allclose(uv, [(W - 1) / 2, (H - 1) / 2], atol=1e-6)


def test_look_at_known_pose():
    # Looking along +x with z up: image right is world -y, image down is world -z.
    T = look_at([0.0, 0.0, 0.0], [2.0, 0.0, 0.0])
    np.testing.assert_allclose(T[:3, :3], [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-15)
    with pytest.raises(InvalidParameterError, match="parallel"):
        look_at([0, 0, 1.0], [0, 0, 0.0])
    with pytest.raises(InvalidParameterError, match="coincide"):
        look_at([1, 1, 1.0], [1, 1, 1.0])
    # A different up vector resolves the straight-down view.
    T = look_at([0, 0, 1.0], [0, 0, 0.0], up=[0, 1.0, 0])
    np.testing.assert_allclose(T[:3, 2], [0, 0, -1.0])


def test_opengl_opencv_conversion():
    T_cv = look_at([1.0, -2.0, 1.5], [0.0, 0.0, 0.3])
    T_gl = opencv_to_opengl(T_cv)
    # OpenGL cameras look along -z and have y up: the same optical axis and image axes, flipped.
    np.testing.assert_allclose(T_gl[:3, 2], -T_cv[:3, 2])
    np.testing.assert_allclose(T_gl[:3, 1], -T_cv[:3, 1])
    np.testing.assert_allclose(T_gl[:3, 0], T_cv[:3, 0])
    np.testing.assert_allclose(T_gl[:3, 3], T_cv[:3, 3])
    np.testing.assert_allclose(opengl_to_opencv(T_gl), T_cv)
    batch = np.stack([T_cv, T_gl])
    np.testing.assert_allclose(opengl_to_opencv(opencv_to_opengl(batch)), batch)
    # A point in front of the camera: z > 0 in OpenCV coordinates, z < 0 in OpenGL coordinates.
    p_world = np.array([0.0, 0.0, 0.3])
    p_cv = apply_transform(invert_transform(T_cv), p_world)
    p_gl = apply_transform(invert_transform(T_gl), p_world)
    np.testing.assert_allclose(p_gl, p_cv * [1, -1, -1], atol=1e-12)


def test_camera_points_to_world_round_trip():
    rng = np.random.default_rng(0)
    T = make_transform(random_rotation(rng), rng.uniform(-1, 1, 3))
    K = intrinsics_from_fov(W, H, FOVY)
    pts_cam = backproject_depth(np.full((H, W), 2.0), K)
    world = camera_points_to_world(pts_cam, T)
    np.testing.assert_allclose(apply_transform(invert_transform(T), world), pts_cam, atol=1e-12)
    # Plane z_cam = 2 maps to the plane at distance 2 from the camera along its optical axis.
    np.testing.assert_allclose((world - T[:3, 3]) @ T[:3, 2], 2.0)


def test_conventions_match_a_mujoco_render():
    """End to end: MuJoCo depth -> back-projection -> world recovers the rendered scene."""
    mujoco = pytest.importorskip("mujoco")
    xml = """<mujoco><worldbody>
      <geom type="plane" size="2 2 0.1"/>
      <geom type="box" size="0.05 0.05 0.05" pos="0.1 -0.05 0.05"/>
      <camera name="cam" pos="0.6 -0.5 0.7" xyaxes="0.64 0.77 0 -0.5 0.4 0.77" fovy="50"/>
    </worldbody></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    # Offscreen rendering must work (MUJOCO_GL=egl, set in tests/conftest.py): a failure here is real.
    renderer = mujoco.Renderer(model, 72, 96)
    with renderer:
        renderer.enable_depth_rendering()
        renderer.update_scene(data, camera="cam")
        depth = renderer.render()
    K = intrinsics_from_fov(96, 72, float(model.cam_fovy[0]))
    T_gl = make_transform(data.cam_xmat[0].reshape(3, 3), data.cam_xpos[0])
    T_cv = opengl_to_opencv(T_gl)
    # Beyond the 4 m plane the renderer returns the far clip distance; drop it.
    world = camera_points_to_world(backproject_depth(depth, K, max_depth=5.0), T_cv)
    on_floor = np.abs(world[:, 2]) < 1e-3
    assert on_floor.mean() > 0.8
    box = world[~on_floor]
    assert len(box) > 20
    # Every other point lies on the box surface (float32 depth: sub-millimetre error).
    lo, hi = np.array([0.05, -0.1, 0.0]), np.array([0.15, 0.0, 0.1])
    assert np.all(box > lo - 1e-3) and np.all(box < hi + 1e-3)
    # Projecting the box top centre lands on a box pixel at the rendered depth.
    top_cam = apply_transform(invert_transform(T_cv), [0.1, -0.05, 0.1])
    (u, v), z = project_points(top_cam, K)
    assert abs(depth[int(round(v)), int(round(u))] - z) < 5e-3
