"""Motion utilities: IK, collision checking, retiming, RRT-Connect, actions, plan_to_pose."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from keygen.errors import InvalidParameterError, KeyGenError
from keygen.expert import motion
from keygen.geometry.rotations import rot6d_to_matrix, rotation_angle_between
from keygen.sim import robot
from keygen.sim.controller import ACTION_DIM

DOWN = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # tcp z down, x forward
HOME = np.array(robot.HOME_QPOS)
WALL_HALF = (0.15, 0.02, 0.15)  # a wall across the workspace, splitting it into y < 0 and y > 0
WALL_POS = (0.5, 0.0, 0.15)


def _yaw(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _scene(wall: bool):
    spec = robot.recommended_options(mujoco.MjSpec())
    spec.worldbody.add_geom(
        name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.6, 0.65, 0.02], pos=[0.45, 0, -0.02]
    )
    if wall:
        spec.worldbody.add_geom(
            name="wall", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(WALL_HALF), pos=list(WALL_POS)
        )
    handles = robot.add_robot(spec)
    model = spec.compile()
    data = mujoco.MjData(model)
    robot.set_home(model, data, handles)
    return model, data, handles


@pytest.fixture(scope="module")
def open_scene():
    return _scene(wall=False)


@pytest.fixture(scope="module")
def wall_scene():
    model, data, handles = _scene(wall=True)
    either_side = [motion.solve_ik(model, handles, [0.5, side, 0.1], DOWN, HOME).q for side in (-0.2, 0.2)]
    return model, data, handles, either_side


def _arm_qadr(model, handles) -> np.ndarray:
    return np.array([model.joint(n).qposadr[0] for n in handles.arm_joints])


def _set_arm(model, data, handles, q) -> None:
    data.qpos[_arm_qadr(model, handles)] = q
    data.qvel[:] = 0.0
    mujoco.mj_forward(model, data)


# -- IK -----------------------------------------------------------------------------------------


def test_ik_reaches_random_reachable_poses_within_limits(open_scene):
    model, _, handles = open_scene
    rng = np.random.default_rng(0)
    for _ in range(12):
        position = rng.uniform([0.3, -0.3, 0.05], [0.65, 0.3, 0.45])
        rotation = _yaw(rng.uniform(-np.pi / 2, np.pi / 2)) @ DOWN
        result = motion.solve_ik(model, handles, position, rotation, HOME, seed=1)
        assert result.ok
        pos, rot = motion.forward_kinematics(handles, result.q)
        assert np.linalg.norm(pos - position) < 2e-3
        assert np.degrees(rotation_angle_between(rot, rotation)) < 1.0
        assert np.all(result.q >= motion.Q_LOWER) and np.all(result.q <= motion.Q_UPPER)
        assert result.error.position < 2e-3


def test_ik_reaches_fk_poses_of_random_configurations_from_home(open_scene):
    model, _, handles = open_scene
    rng = np.random.default_rng(3)
    for _ in range(6):
        q_true = rng.uniform(motion.Q_LOWER + 0.3, motion.Q_UPPER - 0.3)
        position, rotation = motion.forward_kinematics(handles, q_true)
        result = motion.solve_ik(model, handles, position, rotation, HOME, seed=2)
        assert result.ok, result.error
        pos, rot = motion.forward_kinematics(handles, result.q)
        assert np.linalg.norm(pos - position) < 2e-3
        assert np.degrees(rotation_angle_between(rot, rotation)) < 1.0


def test_ik_reports_an_unreachable_pose(open_scene):
    model, _, handles = open_scene
    result = motion.solve_ik(model, handles, [1.5, 0.0, 0.3], DOWN, HOME, n_random_seeds=2)
    assert not result.ok
    assert result.error.position > 0.3
    assert np.all(result.q >= motion.Q_LOWER) and np.all(result.q <= motion.Q_UPPER)


def test_ik_accept_rejects_solutions(open_scene):
    model, _, handles = open_scene
    result = motion.solve_ik(
        model, handles, [0.45, 0.0, 0.2], DOWN, HOME, n_random_seeds=1, accept=lambda q: False
    )
    assert not result.ok
    assert result.error.position < 1e-3  # the pose itself was reached


def test_ik_is_deterministic(open_scene):
    model, _, handles = open_scene
    a = motion.solve_ik(model, handles, [0.35, 0.25, 0.3], _yaw(0.7) @ DOWN, HOME, seed=5)
    b = motion.solve_ik(model, handles, [0.35, 0.25, 0.3], _yaw(0.7) @ DOWN, HOME, seed=5)
    assert np.array_equal(a.q, b.q)


# -- collision checking ---------------------------------------------------------------------------


def test_checker_passes_home_and_flags_the_hand_inside_the_table(open_scene):
    model, data, handles = open_scene
    checker = motion.CollisionChecker(model, handles, data=data)
    assert checker.is_free(HOME)
    inside = motion.solve_ik(model, handles, [0.5, -0.1, -0.03], DOWN, HOME).q
    assert not checker.is_free(inside)
    contacts = checker.contacts(inside)
    assert contacts and all(c.other_geom == "table" and c.distance < 0 for c in contacts)
    assert {c.robot_geom for c in contacts} <= set(handles.collision_geoms)
    # Ignoring the table (as if it were a held object) clears the configuration.
    assert motion.CollisionChecker(model, handles, data=data, ignore_geoms=["table"]).is_free(inside)


def test_checker_leaves_the_live_simulation_untouched(open_scene):
    model, data, handles = open_scene
    qpos, ncon = data.qpos.copy(), data.ncon
    contype = model.geom_contype.copy()
    checker = motion.CollisionChecker(model, handles, data=data)
    checker.is_free(motion.solve_ik(model, handles, [0.5, 0.0, -0.05], DOWN, HOME).q)
    assert np.array_equal(data.qpos, qpos) and data.ncon == ncon
    assert np.array_equal(model.geom_contype, contype)


def test_checker_clearance_keeps_a_distance(open_scene):
    model, data, handles = open_scene
    # Fingertips 2.5 cm above the table (tcp 5 mm short of them): free when touching is all that
    # counts, flagged with a 5 cm clearance; HOME keeps more than 5 cm everywhere.
    low = motion.solve_ik(model, handles, [0.5, 0.0, 0.03], DOWN, HOME).q
    strict = motion.CollisionChecker(model, handles, data=data, clearance=0.05)
    assert motion.CollisionChecker(model, handles, data=data).is_free(low)
    assert not strict.is_free(low) and strict.is_free(HOME)
    assert all(0.0 < c.distance < 0.05 for c in strict.contacts(low))


def test_checker_rejects_unknown_ignored_geom(open_scene):
    model, data, handles = open_scene
    with pytest.raises(InvalidParameterError, match="no_such_geom"):
        motion.CollisionChecker(model, handles, data=data, ignore_geoms=["no_such_geom"])


# -- retiming ---------------------------------------------------------------------------------------


def test_retime_respects_limits_and_hits_every_waypoint():
    rng = np.random.default_rng(0)
    vel = rng.uniform(0.3, 1.5, 7)
    acc = rng.uniform(0.5, 3.0, 7)
    dt = 0.1
    for _ in range(5):
        waypoints = rng.uniform(motion.Q_LOWER + 0.5, motion.Q_UPPER - 0.5, size=(4, 7))
        waypoints[2] = waypoints[1] + rng.normal(0, 0.01, 7)  # a tiny segment too
        traj = motion.retime(waypoints, vel, acc, dt)
        assert np.allclose(np.diff(traj.t), dt)
        velocity = np.diff(traj.q, axis=0) / dt
        acceleration = np.diff(traj.q, n=2, axis=0) / dt**2
        assert np.all(np.abs(velocity) <= vel * (1 + 1e-9) + 1e-12)
        assert np.all(np.abs(acceleration) <= acc * (1 + 1e-9) + 1e-12)
        assert np.all(np.abs(traj.qd) <= vel * (1 + 1e-9))
        np.testing.assert_allclose(traj.q[traj.waypoint_index], waypoints, atol=1e-12)
        assert np.all(traj.qd[traj.waypoint_index] == 0.0)  # rest at every waypoint
        # Samples stay on the piecewise-linear path between consecutive waypoints.
        for k, (i, j) in enumerate(zip(traj.waypoint_index[:-1], traj.waypoint_index[1:], strict=True)):
            d = waypoints[k + 1] - waypoints[k]
            s = (traj.q[i : j + 1] - waypoints[k]) @ d / (d @ d)
            np.testing.assert_allclose(traj.q[i : j + 1], waypoints[k] + s[:, None] * d, atol=1e-12)
            assert np.all(np.diff(s) >= -1e-12)


def test_retime_is_near_time_optimal_for_a_single_joint():
    # 1 rad on one joint, v = 1, a = 2: 0.5 s accelerating, 0.5 s cruising, 0.5 s braking.
    traj = motion.retime(np.stack([np.zeros(7), np.eye(7)[0]]), np.ones(7), np.full(7, 2.0), dt=0.1)
    assert traj.duration == pytest.approx(1.5)


def test_retime_rejects_bad_limits():
    with pytest.raises(InvalidParameterError):
        motion.retime(np.zeros((2, 7)), vel_limits=np.zeros(7))
    with pytest.raises(InvalidParameterError):
        motion.retime(np.zeros((2, 6)))


# -- RRT-Connect ------------------------------------------------------------------------------------


def test_rrt_connect_goes_around_an_obstacle(wall_scene):
    model, data, handles, (q_a, q_b) = wall_scene
    checker = motion.CollisionChecker(model, handles, data=data)
    assert checker.is_free(q_a) and checker.is_free(q_b)
    assert not checker.path_is_free(np.stack([q_a, q_b]))  # the straight path hits the wall
    path = motion.plan_rrt_connect(checker, q_a, q_b, seed=0)
    assert len(path) >= 3
    np.testing.assert_array_equal(path[0], q_a)
    np.testing.assert_array_equal(path[-1], q_b)
    assert checker.path_is_free(path, step=0.004)  # five times denser than the planner checked
    assert np.all(path >= motion.Q_LOWER) and np.all(path <= motion.Q_UPPER)


def test_rrt_connect_is_deterministic_for_a_seed(wall_scene):
    model, data, handles, (q_a, q_b) = wall_scene
    checker = motion.CollisionChecker(model, handles, data=data)
    first = motion.plan_rrt_connect(checker, q_a, q_b, seed=7)
    again = motion.plan_rrt_connect(motion.CollisionChecker(model, handles, data=data), q_a, q_b, seed=7)
    np.testing.assert_array_equal(first, again)


def test_rrt_connect_refuses_a_goal_in_collision(wall_scene):
    model, data, handles, (q_a, _) = wall_scene
    checker = motion.CollisionChecker(model, handles, data=data)
    inside = motion.solve_ik(model, handles, list(WALL_POS), DOWN, HOME).q
    with pytest.raises(motion.PlanningError) as info:
        motion.plan_rrt_connect(checker, q_a, inside, seed=0)
    assert info.value.reason == "goal_in_collision"


# -- actions and plan_to_pose -----------------------------------------------------------------------


def test_actions_reproduce_forward_kinematics_of_the_scene(open_scene):
    model, _, handles = open_scene
    rng = np.random.default_rng(1)
    q_traj = rng.uniform(motion.Q_LOWER, motion.Q_UPPER, size=(5, 7))
    grip = np.linspace(0.0, 1.0, 5)
    actions = motion.joint_path_to_actions(model, handles, q_traj, grip)
    assert actions.shape == (5, ACTION_DIM)
    scratch = mujoco.MjData(model)  # FK in the scene model itself, independent of the helper
    site = model.site(handles.tcp_site).id
    for q, action in zip(q_traj, actions, strict=True):
        scratch.qpos[_arm_qadr(model, handles)] = q
        mujoco.mj_kinematics(model, scratch)
        np.testing.assert_allclose(action[:3], scratch.site_xpos[site], atol=1e-9)
        np.testing.assert_allclose(
            rot6d_to_matrix(action[3:9]), scratch.site_xmat[site].reshape(3, 3), atol=1e-9
        )
    np.testing.assert_array_equal(actions[:, 9], grip)


def test_plan_to_pose_goes_over_the_wall(wall_scene):
    model, data, handles, (q_a, _) = wall_scene
    _set_arm(model, data, handles, q_a)
    goal = np.array([0.5, 0.2, 0.1])
    rotation = _yaw(0.3) @ DOWN
    plan = motion.plan_to_pose(model, data, handles, goal, rotation, gripper=1.0, seed=0)
    assert plan.used_rrt
    assert plan.actions.shape == (len(plan.trajectory.q) - 1, ACTION_DIM)
    assert np.linalg.norm(plan.actions[-1, :3] - goal) < 2e-3
    assert np.degrees(rotation_angle_between(rot6d_to_matrix(plan.actions[-1, 3:9]), rotation)) < 1.0
    assert np.all(plan.actions[:, 9] == 1.0)
    checker = motion.CollisionChecker(model, handles, data=data)
    assert checker.path_is_free(plan.trajectory.q, step=0.01)
    again = motion.plan_to_pose(model, data, handles, goal, rotation, gripper=1.0, seed=0)
    np.testing.assert_array_equal(plan.actions, again.actions)


def test_plan_to_pose_uses_a_straight_path_when_free(open_scene):
    model, data, handles = open_scene
    robot.set_home(model, data, handles)
    plan = motion.plan_to_pose(model, data, handles, [0.5, 0.1, 0.2], DOWN, gripper=0.0)
    assert not plan.used_rrt and len(plan.waypoints) == 2
    np.testing.assert_allclose(plan.waypoints[0], HOME, atol=1e-9)


def test_plan_to_pose_explains_impossible_goals(wall_scene):
    model, data, handles, (q_a, _) = wall_scene
    _set_arm(model, data, handles, q_a)
    with pytest.raises(motion.PlanningError) as unreachable:
        motion.plan_to_pose(model, data, handles, [1.6, 0.0, 0.2], DOWN, 1.0)
    assert unreachable.value.reason == "goal_unreachable"
    assert isinstance(unreachable.value, KeyGenError)
    with pytest.raises(motion.PlanningError) as blocked:
        motion.plan_to_pose(model, data, handles, [0.5, 0.0, 0.1], DOWN, 1.0)  # inside the wall
    assert blocked.value.reason == "goal_in_collision"
    inside_table = motion.solve_ik(model, handles, [0.5, -0.2, -0.03], DOWN, q_a).q
    _set_arm(model, data, handles, inside_table)
    with pytest.raises(motion.PlanningError) as stuck:
        motion.plan_to_pose(model, data, handles, [0.5, 0.2, 0.1], DOWN, 1.0)
    assert stuck.value.reason == "start_in_collision" and "table" in str(stuck.value)


def test_planned_actions_drive_the_env_to_the_goal():
    gym = pytest.importorskip("gymnasium")
    import keygen.sim.env  # noqa: F401  (registers the env ids)

    env = gym.make("keygen/StackBowl-v0", include_rgb=False, image_size=48, num_points=128).unwrapped
    env.reset(seed=0)
    goal = np.array([0.5, 0.2, 0.18])
    plan = motion.plan_to_pose(env.model, env.data, env.scene.robot, goal, DOWN, 1.0, seed=0)
    for action in plan.actions:
        env.step(action)
    mujoco.mj_kinematics(env.model, env.data)
    reached = env.controller.proprioception(env.model, env.data)
    assert np.linalg.norm(reached[:3] - goal) < 5e-3
    env.close()
