"""The end-effector controller: tracking, proprioception, grasp holding, bad targets."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from keygen.errors import InvalidParameterError
from keygen.geometry.rotations import matrix_to_rot6d, rot6d_to_matrix
from keygen.sim import robot
from keygen.sim.controller import ACTION_DIM, EndEffectorController, proprioception, validate_target

DOWN = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # tcp z down, x forward
WORKSPACE_LOW = np.array([0.3, -0.25, 0.1])
WORKSPACE_HIGH = np.array([0.6, 0.25, 0.45])


def _yaw(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _target(position, rotation, gripper: float) -> np.ndarray:
    return np.concatenate([position, matrix_to_rot6d(rotation), [gripper]])


def _angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    cos = (np.trace(R_a.T @ R_b) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def _scene(with_box: bool = False):
    spec = robot.recommended_options(mujoco.MjSpec())
    spec.worldbody.add_geom(
        name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.5, 0.6, 0.02], pos=[0.5, 0, -0.02]
    )
    if with_box:
        body = spec.worldbody.add_body(name="box", pos=[0.5, 0.05, 0.02])
        body.add_freejoint()
        body.add_geom(name="box", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.02, 0.02, 0.02], mass=0.3)
    handles = robot.add_robot(spec)
    model = spec.compile()
    data = mujoco.MjData(model)
    robot.set_home(model, data, handles)
    return model, data, handles


@pytest.fixture(scope="module")
def arm():
    model, data, handles = _scene()
    return model, data, handles, EndEffectorController(model, handles)


def _measured(model, data, handles) -> np.ndarray:
    mujoco.mj_kinematics(model, data)  # site poses for the latest qpos
    return proprioception(model, data, handles)


def test_tracks_random_reachable_targets_from_nearby_starts(arm):
    model, data, handles, controller = arm
    rng = np.random.default_rng(0)
    for _ in range(10):
        robot.set_home(model, data, handles)
        controller.reset(model, data)
        goal = rng.uniform(WORKSPACE_LOW, WORKSPACE_HIGH)
        rotation = _yaw(rng.uniform(-np.pi / 2, np.pi / 2)) @ DOWN
        # Settle at a start up to 5 cm away from the goal, then give the goal for two periods.
        start = goal + rng.uniform(-0.05, 0.05, size=3)
        for _ in range(15):
            controller.step(model, data, _target(start, rotation, 1.0))
        for _ in range(2):
            controller.step(model, data, _target(goal, rotation, 1.0))
        state = _measured(model, data, handles)
        assert np.linalg.norm(state[:3] - goal) < 5e-3
        assert _angle_deg(rot6d_to_matrix(state[3:9]), rotation) < 2.0
        q = data.qpos[[model.joint(n).qposadr[0] for n in handles.arm_joints]]
        assert np.all(q >= np.array(robot.JOINT_LOWER) - 1e-3)
        assert np.all(q <= np.array(robot.JOINT_UPPER) + 1e-3)


def test_proprioception_of_the_reached_state_matches_the_target(arm):
    model, data, handles, controller = arm
    robot.set_home(model, data, handles)
    controller.reset(model, data)
    target = _target([0.5, 0.1, 0.25], _yaw(0.3) @ DOWN, 0.5)
    for _ in range(10):
        controller.step(model, data, target)
    state = _measured(model, data, handles)
    assert state.shape == (ACTION_DIM,)
    np.testing.assert_allclose(state[:3], target[:3], atol=1e-3)
    np.testing.assert_allclose(state[3:9], target[3:9], atol=5e-3)
    assert state[9] == pytest.approx(0.5, abs=0.02)
    # The 6D part is two orthonormal columns.
    x, y = state[3:6], state[6:9]
    assert np.linalg.norm(x) == pytest.approx(1.0) and np.linalg.norm(y) == pytest.approx(1.0)
    assert abs(x @ y) < 1e-9
    np.testing.assert_allclose(controller.proprioception(model, data), state)


def test_unreachable_target_keeps_joints_within_limits(arm):
    model, data, handles, controller = arm
    robot.set_home(model, data, handles)
    controller.reset(model, data)
    far = _target([1.5, 0.0, 0.2], DOWN, 1.0)
    for _ in range(10):
        controller.step(model, data, far)
    q_ref = controller.q_ref
    assert np.all(np.isfinite(q_ref))
    assert np.all(q_ref >= np.array(robot.JOINT_LOWER) - 1e-9)
    assert np.all(q_ref <= np.array(robot.JOINT_UPPER) + 1e-9)
    assert np.all(np.isfinite(data.qpos))


def test_grasps_lifts_and_holds_a_box():
    model, data, handles = _scene(with_box=True)
    controller = EndEffectorController(model, handles)
    controller.reset(model, data)
    box = model.body("box").id
    tcp = model.site(handles.tcp_site).id
    start = data.xpos[box].copy()

    def run(position, gripper, periods):
        for _ in range(periods):
            controller.step(model, data, _target(position, DOWN, gripper))

    def box_in_tcp_frame():
        mujoco.mj_kinematics(model, data)
        return data.site_xmat[tcp].reshape(3, 3).T @ (data.xpos[box] - data.site_xpos[tcp])

    run(start + [0, 0, 0.10], 1.0, 10)  # above the box, open
    run(start, 1.0, 10)  # down around it
    run(start, 0.0, 5)  # close
    grasped = box_in_tcp_frame()
    opening = 2 * robot.FINGER_MAX * _measured(model, data, handles)[9]
    assert opening == pytest.approx(0.04, abs=2.5e-3)  # the pads rest on the 4 cm faces
    run(start + [0, 0, 0.10], 0.0, 10)  # lift 10 cm in one step target
    lifted = box_in_tcp_frame()
    run(start + [0, 0, 0.10], 0.0, 10)  # hold for 1 s
    held = box_in_tcp_frame()
    assert data.xpos[box][2] - start[2] > 0.095
    assert np.linalg.norm(held - grasped) < 5e-3  # lift and hold together slip less than 5 mm
    assert np.linalg.norm(held - lifted) < 1e-3
    # Opening lets it go.
    run(start + [0, 0, 0.10], 1.0, 5)
    assert data.xpos[box][2] < start[2] + 0.09


@pytest.mark.parametrize(
    "bad",
    [
        np.full(10, np.nan),
        np.r_[0.5, 0.0, np.inf, 1, 0, 0, 0, 1, 0, 1],
        np.zeros(9),
        np.zeros((2, 10)),
        np.r_[0.5, 0.0, 0.2, 0, 0, 0, 0, 1, 0, 1],  # zero first column: no rotation
    ],
)
def test_bad_targets_raise(arm, bad):
    model, data, handles, controller = arm
    with pytest.raises(InvalidParameterError):
        controller.step(model, data, bad)


def test_validate_target_and_constructor_errors(arm):
    model, _, handles, _ = arm
    good = _target([0.5, 0, 0.2], DOWN, 1.0)
    np.testing.assert_array_equal(validate_target(good.tolist()), good)
    with pytest.raises(InvalidParameterError, match="shape"):
        validate_target([1.0, 2.0])
    with pytest.raises(InvalidParameterError, match="ik_every"):
        EndEffectorController(model, handles, ik_every=0)
    with pytest.raises(InvalidParameterError, match="prefix"):
        EndEffectorController(model, robot.robot_handles("missing/"))
    with pytest.raises(InvalidParameterError, match="not installed"):
        EndEffectorController(model, handles, solver="no-such-solver")


def test_controller_works_for_a_moved_and_turned_base():
    spec = robot.recommended_options(mujoco.MjSpec())
    handles = robot.add_robot(spec, base_pos=(0.2, -0.3, 0.1), base_yaw=np.pi / 2, name_prefix="r2/")
    model = spec.compile()
    data = mujoco.MjData(model)
    robot.set_home(model, data, handles)
    controller = EndEffectorController(model, handles)
    controller.reset(model, data)
    # 0.45 m in front of the turned base is +y in the world.
    goal = np.array([0.2, -0.3 + 0.45, 0.1 + 0.25])
    rotation = _yaw(np.pi / 2) @ DOWN
    for _ in range(10):
        controller.step(model, data, _target(goal, rotation, 1.0))
    state = _measured(model, data, handles)
    assert np.linalg.norm(state[:3] - goal) < 2e-3
    assert _angle_deg(rot6d_to_matrix(state[3:9]), rotation) < 1.0
