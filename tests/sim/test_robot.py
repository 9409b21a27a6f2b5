"""The simulated arm: kinematics against the published DH table, limits, attachment, gripper layout."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from keygen.errors import InvalidParameterError
from keygen.sim import robot

PUBLISHED_LOWER = np.array([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973])
PUBLISHED_UPPER = np.array([2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973])
DOWN = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # tcp z down, x forward


def _rot_x(a: float) -> np.ndarray:
    T = np.eye(4)
    T[1:3, 1:3] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return T


def _rot_z(a: float) -> np.ndarray:
    T = np.eye(4)
    T[0:2, 0:2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return T


def _trans(x: float, y: float, z: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [x, y, z]
    return T


def dh_flange(q: np.ndarray) -> np.ndarray:
    """Flange pose (4, 4) in the base frame by Craig's modified DH, written from the table."""
    a = [0, 0, 0, 0.0825, -0.0825, 0, 0.088]
    d = [0.333, 0, 0.316, 0, 0.384, 0, 0]
    alpha = [0, -np.pi / 2, np.pi / 2, np.pi / 2, -np.pi / 2, np.pi / 2, np.pi / 2]
    T = np.eye(4)
    for i in range(7):
        T = T @ _rot_x(alpha[i]) @ _trans(a[i], 0, 0) @ _rot_z(q[i]) @ _trans(0, 0, d[i])
    return T @ _trans(0, 0, 0.107)


def dh_tcp(q: np.ndarray) -> np.ndarray:
    return dh_flange(q) @ _rot_z(-np.pi / 4) @ _trans(0, 0, robot.TCP_OFFSET)


def _site_pose(model: mujoco.MjModel, data: mujoco.MjData, name: str) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = data.site(name).xmat.reshape(3, 3)
    T[:3, 3] = data.site(name).xpos
    return T


def _set_arm(model: mujoco.MjModel, data: mujoco.MjData, handles: robot.RobotHandles, q: np.ndarray) -> None:
    for name, value in zip(handles.arm_joints, q, strict=True):
        data.qpos[model.joint(name).qposadr[0]] = value
    mujoco.mj_kinematics(model, data)


def _random_q(rng: np.random.Generator) -> np.ndarray:
    return rng.uniform(PUBLISHED_LOWER, PUBLISHED_UPPER)


def _scene_with_table_and_object(base_pos=(0.0, 0.0, 0.0), base_yaw: float = 0.0):
    spec = robot.recommended_options(mujoco.MjSpec())
    spec.worldbody.add_geom(
        name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.5, 0.6, 0.02], pos=[0.5, 0, -0.02]
    )
    body = spec.worldbody.add_body(name="object", pos=[0.5, 0.1, 0.03])
    body.add_freejoint(name="object_free")
    body.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.03, 0.03, 0.03], mass=0.2)
    handles = robot.add_robot(spec, base_pos=base_pos, base_yaw=base_yaw)
    model = spec.compile()
    return model, mujoco.MjData(model), handles


def test_standalone_spec_compiles_with_prefixed_names():
    model = robot.recommended_options(robot.build_robot_spec("arm/")).compile()
    assert (model.nq, model.nv, model.nu) == (9, 9, 8)
    handles = robot.robot_handles("arm/")
    for name in (*handles.arm_joints, *handles.finger_joints):
        model.joint(name)
    for name in (*handles.arm_actuators, handles.gripper_actuator):
        model.actuator(name)
    model.site(handles.tcp_site)
    assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    assert model.opt.timestep == pytest.approx(0.002)
    assert model.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC


def test_forward_kinematics_matches_modified_dh():
    model = robot.build_robot_spec().compile()
    data = mujoco.MjData(model)
    handles = robot.robot_handles()
    rng = np.random.default_rng(0)
    for _ in range(25):
        q = _random_q(rng)
        _set_arm(model, data, handles, q)
        for site, expected in ((handles.flange_site, dh_flange(q)), (handles.tcp_site, dh_tcp(q))):
            pose = _site_pose(model, data, site)
            assert np.linalg.norm(pose[:3, 3] - expected[:3, 3]) < 1e-3
            assert np.abs(pose[:3, :3] - expected[:3, :3]).max() < 1e-6


def test_attached_robot_kinematics_follow_the_base_pose():
    base_pos, yaw = np.array([0.1, -0.2, 0.05]), 0.7
    model, data, handles = _scene_with_table_and_object(base_pos, yaw)
    assert model.nq == 7 + 9  # the free object plus the robot
    base = _trans(*base_pos) @ _rot_z(yaw)
    rng = np.random.default_rng(1)
    for _ in range(10):
        q = _random_q(rng)
        _set_arm(model, data, handles, q)
        expected = base @ dh_tcp(q)
        pose = _site_pose(model, data, handles.tcp_site)
        assert np.linalg.norm(pose[:3, 3] - expected[:3, 3]) < 1e-3
        assert np.abs(pose[:3, :3] - expected[:3, :3]).max() < 1e-6


def test_joint_limits_are_the_published_ones():
    model = robot.build_robot_spec().compile()
    handles = robot.robot_handles()
    ranges = np.array([model.joint(n).range for n in handles.arm_joints])
    np.testing.assert_allclose(ranges[:, 0], PUBLISHED_LOWER)
    np.testing.assert_allclose(ranges[:, 1], PUBLISHED_UPPER)
    assert all(model.jnt_limited[model.joint(n).id] for n in handles.arm_joints)
    np.testing.assert_allclose(robot.JOINT_VELOCITY_LIMITS, [2.175] * 4 + [2.61] * 3)
    for name, limit in zip(handles.arm_actuators, robot.JOINT_TORQUE_LIMITS, strict=True):
        np.testing.assert_allclose(model.actuator(name).forcerange, [-limit, limit])
    for name in handles.finger_joints:
        np.testing.assert_allclose(model.joint(name).range, [0.0, 0.04])


def test_masses_are_plausible():
    model = robot.build_robot_spec().compile()
    handles = robot.robot_handles()
    arm_mass = sum(model.body(f"{handles.prefix}link{i}").mass[0] for i in range(1, 8))
    assert 10.0 < arm_mass < 25.0
    assert all(0.3 < model.body(f"{handles.prefix}link{i}").mass[0] < 6.0 for i in range(1, 8))
    assert np.all(model.body_inertia[1:] > 0)


def test_home_pose_points_down_in_front_of_the_base_and_holds_still():
    model, data, handles = _scene_with_table_and_object()
    assert np.all(np.array(robot.HOME_QPOS) > PUBLISHED_LOWER)
    assert np.all(np.array(robot.HOME_QPOS) < PUBLISHED_UPPER)
    robot.set_home(model, data, handles)
    pose = _site_pose(model, data, handles.tcp_site)
    assert 0.4 <= pose[0, 3] <= 0.5 and abs(pose[1, 3]) < 1e-6
    np.testing.assert_allclose(pose[:3, 3], robot.HOME_TCP_POS, atol=1e-3)
    np.testing.assert_allclose(pose[:3, :3], DOWN, atol=1e-3)
    # The servos with gravity compensation hold the pose: half a second of physics, no drift.
    for _ in range(250):
        mujoco.mj_step(model, data)
    mujoco.mj_kinematics(model, data)
    assert np.linalg.norm(data.site(handles.tcp_site).xpos - pose[:3, 3]) < 1e-3
    robot_geoms = {model.geom(n).id for n in handles.collision_geoms}
    touching = [c for c in data.contact if c.geom1 in robot_geoms or c.geom2 in robot_geoms]
    assert touching == []


def test_gripper_layout_pads_and_tcp():
    model = robot.build_robot_spec().compile()
    data = mujoco.MjData(model)
    handles = robot.robot_handles()
    for name in handles.finger_joints:
        data.qpos[model.joint(name).qposadr[0]] = 0.02
    mujoco.mj_kinematics(model, data)
    tcp = _site_pose(model, data, handles.tcp_site)
    left, right = (model.geom(n) for n in handles.pad_geoms)
    for pad in (left, right):
        np.testing.assert_allclose(2 * pad.size, robot.PAD_SIZE)  # 18 mm wide, 8 mm thick
        assert pad.condim[0] in (4, 6)
        np.testing.assert_allclose(pad.friction, [1.5, 0.02, 0.002])
    # The tcp is midway between the pads, on the closing axis (its y axis), within the pad length.
    p_left = tcp[:3, :3].T @ (data.geom(left.id).xpos - tcp[:3, 3])
    p_right = tcp[:3, :3].T @ (data.geom(right.id).xpos - tcp[:3, 3])
    np.testing.assert_allclose((p_left + p_right)[:2], 0.0, atol=1e-9)
    assert p_left[1] > 0.02 > 0 > -0.02 > p_right[1]
    assert abs(p_left[2]) < robot.PAD_SIZE[2] / 2
    # At 20 mm per finger the inner pad faces are 40 mm apart (80 mm when fully open).
    thickness = robot.PAD_SIZE[1]
    assert (p_left[1] - p_right[1]) - thickness == pytest.approx(0.04)
    # Finger length from where the fingers leave the hand to their tips.
    assert robot.FINGER_BASE_Z + robot.FINGER_LENGTH - robot.TCP_OFFSET == pytest.approx(0.005)
    assert 0.045 <= robot.FINGER_LENGTH <= 0.1


def test_robot_geoms_do_not_collide_with_each_other_but_with_the_world():
    names = robot.robot_collision_geom_names()
    assert set(robot.robot_handles().pad_geoms) <= set(names)
    model = robot.build_robot_spec().compile()
    for name in names:
        geom = model.geom(name)
        assert geom.contype[0] & geom.conaffinity[0] == 0  # robot vs robot: never
        assert geom.conaffinity[0] & 1  # robot vs default-contype world geoms: always


def test_two_robots_and_bad_arguments():
    spec = mujoco.MjSpec()
    first = robot.add_robot(spec, base_pos=(0, -0.5, 0))
    second = robot.add_robot(spec, base_pos=(0, 0.5, 0), base_yaw=np.pi, name_prefix="other/")
    model = spec.compile()
    assert model.nu == 16
    assert first.tcp_site != second.tcp_site
    with pytest.raises(InvalidParameterError, match="name_prefix"):
        robot.add_robot(spec, name_prefix="other/")
    with pytest.raises(InvalidParameterError, match="base_pos"):
        robot.add_robot(mujoco.MjSpec(), base_pos=(0, 0))
    with pytest.raises(InvalidParameterError):
        robot.add_robot(mujoco.MjSpec(), base_pos=(0, np.nan, 0))
