"""The experts' planning pieces: finger clearance, the controller preview, the knife's turn routes
and the pour's grasp fit."""

from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import keygen  # noqa: F401  (registers the ids, sets MUJOCO_GL before mujoco loads)
from keygen.errors import InvalidParameterError
from keygen.expert import pour as pour_expert
from keygen.expert.base import target
from keygen.expert.clearance import DISTMAX, FingerClearance, collision_geoms_of_body
from keygen.expert.knife_geometry import (
    CORNER_SLACK,
    PAD_CLEARANCE_Z,
    PAD_HALF_WIDTH,
    PAD_TIP_BEYOND_TCP,
    grasp_point,
    grasp_rotation,
    insert_pose,
    insertion_pitch,
)
from keygen.expert.knife_plan import LEG_ROUTES, Leg, leg_targets, transport_legs
from keygen.expert.pour import (
    BODY_MARGIN,
    GraspPlan,
    PourExpert,
    fit_grasp,
    fit_score,
    grasp_pose,
    mug_clearance,
)
from keygen.expert.preview import ControllerPreview
from keygen.geometry.rotations import axis_angle_to_matrix, rot6d_to_matrix, rotation_angle_between
from keygen.sim.tasks.pour import pregrasp_opening


@pytest.fixture(scope="module")
def pour_env():
    env = gym.make(
        "keygen/Pour-v0",
        object_split="test",
        object_id=7,
        setting="easy",
        include_rgb=False,
        image_size=32,
        num_points=64,
    ).unwrapped
    env.reset(seed=0)
    return env


def _clearance(env) -> FingerClearance:
    geoms = collision_geoms_of_body(env.model, env.task.manipulated.body_id)
    return FingerClearance(env.model, env.data, env.controller.handles, geoms)


def test_collision_geoms_leave_out_the_visual_mesh(pour_env):
    env = pour_env
    body = env.task.manipulated.body_id
    geoms = collision_geoms_of_body(env.model, body)
    all_geoms = np.flatnonzero(env.model.geom_bodyid == body)
    assert 0 < len(geoms) < len(all_geoms)  # the visual geom collides with nothing
    assert len(geoms) == len(env.task.asset.collision)


def test_clearance_far_away_is_capped_and_inside_is_negative(pour_env):
    env = pour_env
    checker = _clearance(env)
    anchors = env.task.anchors_world(env.model, env.data)
    down = np.diag([1.0, -1.0, -1.0])
    assert checker.distance(np.array([0.0, 0.6, 0.5]), down, 0.5) == pytest.approx(DISTMAX)
    # Fingers closed around the body's axis, halfway up: deep inside the mug's wall parts.
    centre = 0.5 * (anchors["bottom_center"] + anchors["opening_center"])
    assert checker.distance(centre + np.array([0.06, 0.0, 0.0]), down, 0.0) < 0.0
    per_target = checker.distances(centre, down, 0.0)
    assert per_target.shape == (len(checker.targets),)


def test_clearance_rejects_bad_input(pour_env):
    env = pour_env
    with pytest.raises(InvalidParameterError):
        FingerClearance(env.model, env.data, env.controller.handles, [])
    checker = _clearance(env)
    with pytest.raises(InvalidParameterError):
        checker.distance(np.zeros(2), np.eye(3), 0.5)


def test_grasp_fit_clears_the_handle_better_than_the_generator_opening(pour_env):
    """Mug test 7 has an ear handle barely taller than the finger: the fit finds room."""
    env = pour_env
    anchors = env.task.anchors_world(env.model, env.data)
    expert = PourExpert()
    plan = GraspPlan(1.0, 1.0, 0.0, 0.0)
    position, rotation, fit = expert.fit_for(env, anchors, plan)
    default_grasp, _ = grasp_pose(anchors, plan)
    checker = _clearance(env)
    poses = [(default_grasp - s * rotation[:, 2], rotation) for s in (0.0, 0.01, 0.02, 0.03, 0.05)]
    default = checker.sweep(poses, pregrasp_opening(env.task.asset)).min()
    assert fit.clearance > default + 0.001
    np.testing.assert_allclose(position, default_grasp + fit.offset * rotation[:, 0])
    assert 0.0 < fit.opening < 1.0 and abs(fit.offset) <= 0.008 + 1e-9


@pytest.mark.parametrize("pitch", [pour_expert.APPROACH_PITCH, pour_expert.STEEP_PITCH])
def test_pruned_grasp_fit_equals_the_exhaustive_search(pour_env, pitch):
    """fit_grasp skips a candidate's remaining poses once it cannot win: same answer as trying all."""
    env = pour_env
    anchors = env.task.anchors_world(env.model, env.data)
    grasp, rotation = grasp_pose(anchors, GraspPlan(1.0, 1.0, 0.0, 0.0, pitch))
    checker, is_handle = mug_clearance(env)
    best = None
    for offset in pour_expert.FIT_OFFSETS:
        poses = [
            (grasp + offset * rotation[:, 0] - s * rotation[:, 2], rotation) for s in pour_expert.FIT_SWEEP
        ]
        for opening in pour_expert.FIT_OPENINGS:
            dist = checker.sweep(poses, float(opening))
            handle, body = dist[is_handle].min(initial=np.inf), dist[~is_handle].min(initial=np.inf)
            ranked = fit_score(handle, body) - pour_expert.OFFSET_COST * abs(offset)
            if best is None or ranked > best[0] + 1e-9:
                best = (ranked, offset, opening, min(handle, body - BODY_MARGIN))
    fit = fit_grasp(checker, is_handle, grasp, rotation)
    assert (fit.offset, fit.opening) == (float(best[1]), float(best[2]))
    assert fit.clearance == pytest.approx(best[3])


def _preview_at_reset(env, seed):
    """A controller preview and the arm's reference joints, tcp position and orientation after a reset."""
    env.reset(seed=seed)
    start = env.controller.proprioception(env.model, env.data)
    preview = ControllerPreview(env.controller.handles)
    return preview, env.controller.q_ref, start[:3], rot6d_to_matrix(start[3:9])


def test_preview_matches_the_env_controller_exactly(pour_env):
    env = pour_env
    preview, q0, tcp, rotation = _preview_at_reset(env, seed=1)
    targets = [target(tcp + np.array([0.0, 0.01 * k, -0.01 * k]), rotation, 1.0) for k in range(1, 5)]
    result = preview.rollout(q0, targets)
    for action in targets:
        env.step(action)
    # The reference is kinematic: the physics (and its lag) never feeds back into it.
    np.testing.assert_allclose(result.q[-1], env.controller.q_ref, atol=1e-6)
    assert result.q.shape == (4, 7) and result.limit_margin > 0 and result.collisions == 0
    with pytest.raises(InvalidParameterError):
        preview.rollout(q0, np.zeros((3, 9)))


def test_preview_scores_checkpoints_lag_and_reach(pour_env):
    preview, q0, tcp, rotation = _preview_at_reset(pour_env, seed=2)
    near = [target(tcp + np.array([0.0, 0.0, -0.005 * k]), rotation, 1.0) for k in range(1, 6)]
    easy = preview.rollout(q0, near, checkpoints=[2])
    assert easy.checkpoint_position_error < 0.01 and easy.max_position_error < 0.02
    assert 0.0 < easy.manipulability < np.inf
    # A jump 1.5 m away cannot be reached: the tcp lags far behind, and a checkpoint there counts.
    far = near[:2] + [target(tcp + np.array([1.5, 0.0, 0.0]), rotation, 1.0)] + near[2:]
    hard = preview.rollout(q0, far, checkpoints=[2])
    assert hard.checkpoint_position_error > 0.5 and hard.max_position_error >= hard.checkpoint_position_error
    assert hard.final_position_error < 0.05  # it comes back to the last target ...
    assert hard.cost() > easy.cost() + 50.0  # ... but the miss on the way is paid for
    # Without the checkpoint only the lag counts (10 per metre beyond 5 cm).
    unchecked = preview.rollout(q0, far)
    assert unchecked.checkpoint_position_error == 0.0
    assert hard.cost() - unchecked.cost() == pytest.approx(100.0 * hard.checkpoint_position_error, rel=0.05)


def _lying_knife(yaw: float, slot_yaw: float) -> dict[str, np.ndarray]:
    """Anchors of a knife lying flat (blade along ``yaw``) and of a slot along ``slot_yaw``."""
    axis = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    grasp = np.array([0.5, 0.12, 0.009])  # a thin handle: the table clearance sets the grasp height
    return {
        "handle_axis": axis,
        "handle_grasp": grasp,
        "blade_base": grasp + 0.05 * axis,
        "blade_tip": grasp + 0.25 * axis,
        "blade_axis": axis,
        "edge_direction": np.cross([0.0, 0.0, 1.0], axis),
        "slot_axis": np.array([np.cos(slot_yaw), np.sin(slot_yaw), 0.0]),
        "slot_center_top": np.array([0.5, -0.18, 0.12]),
    }


def test_pitched_grasp_keeps_the_pinch_and_the_table_clearance():
    rng = np.random.default_rng(4)
    for _ in range(10):
        anchors = _lying_knife(rng.uniform(-np.pi, np.pi), 0.0)
        for hand in (0, 1):
            upright = grasp_rotation(anchors, hand)
            for pitch in (-0.6, -0.3, 0.3, 0.6):
                rot = grasp_rotation(anchors, hand, pitch)
                np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
                np.testing.assert_allclose(rot[:, 1], upright[:, 1], atol=1e-12)  # same closing axis
                assert rot[:, 2] @ upright[:, 2] == pytest.approx(np.cos(pitch))
                # The lower pad corner keeps the upright tips' clearance above the table (less a slack).
                tcp = grasp_point(anchors, pitch)
                tips = [rot @ np.array([s * PAD_HALF_WIDTH, 0.0, PAD_TIP_BEYOND_TCP]) for s in (-1, 1)]
                lowest = tcp[2] + min(t[2] for t in tips)
                assert lowest == pytest.approx(PAD_CLEARANCE_Z - PAD_TIP_BEYOND_TCP - CORNER_SLACK, abs=1e-9)
    np.testing.assert_allclose(grasp_point(anchors, 0.0)[2], PAD_CLEARANCE_Z)


def test_insertion_pitch_points_the_approach_below_the_horizontal():
    rng = np.random.default_rng(5)
    for _ in range(10):
        anchors = _lying_knife(rng.uniform(-np.pi, np.pi), rng.uniform(-np.pi, np.pi))
        across = np.cross([0.0, 0.0, 1.0], anchors["slot_axis"])
        for hand in (0, 1):
            for approach in (across, -across):
                pitch = insertion_pitch(anchors, hand, approach, 0.0, 0.5)
                assert abs(pitch) == 0.5
                grasp, rot = grasp_point(anchors, pitch), grasp_rotation(anchors, hand, pitch)
                _, insert_rot = insert_pose(grasp, rot, anchors, approach, 0.0, 0.0)
                assert insert_rot[2, 2] == pytest.approx(-np.sin(0.5), abs=1e-9)  # 0.5 rad below level
                assert insert_rot[:, 2] @ approach > 0.0


def test_fit_score_puts_any_overlap_below_every_clear_fit():
    assert fit_score(0.004, 0.01) == pytest.approx(0.004)
    assert fit_score(0.004, 0.005) == pytest.approx(0.005 - BODY_MARGIN)
    # Train mug 22: 1.0 / 1.2 mm clear of handle / body beats 0.4 mm into the handle, 2 mm off the body.
    assert fit_score(0.0010, 0.0012) > fit_score(-0.0004, 0.0020)
    assert fit_score(-0.0001, 0.03) < -BODY_MARGIN <= fit_score(0.0, 0.0)
    assert fit_score(-0.002, 0.01) < fit_score(-0.001, 0.01)


@pytest.mark.parametrize("route", LEG_ROUTES)
def test_transport_routes_end_on_the_goal_pose(route):
    rng = np.random.default_rng(3)
    for _ in range(5):
        r0 = axis_angle_to_matrix(rng.normal(size=3))
        r1 = axis_angle_to_matrix(rng.normal(size=3))
        p0, p1 = np.array([0.5, 0.1, 0.15]), np.array([0.5, -0.2, 0.3])
        legs = transport_legs(route, p0, r0, p1, r1)
        p, r, actions = p0, r0, []
        for leg in legs:
            actions += leg_targets(p, r, 0.0, leg, 0.0)
            p, r = leg.position, leg.rotation
        assert rotation_angle_between(rot6d_to_matrix(actions[-1][3:9]), r1) < 1e-6
        np.testing.assert_allclose(actions[-1][:3], p1, atol=1e-12)
        assert legs[0].position[2] > max(p0[2], p1[2])  # raised midpoint


def test_leg_targets_turn_about_the_vertical_by_the_yaw():
    r0 = np.diag([1.0, -1.0, -1.0])
    leg = Leg(np.zeros(3), r0, 10, yaw=1.5 * np.pi)
    actions = leg_targets(np.zeros(3), r0, 1.0, leg, 0.0)
    assert len(actions) == 10 and actions[-1][9] == 0.0
    end = rot6d_to_matrix(actions[-1][3:9])
    np.testing.assert_allclose(end, axis_angle_to_matrix(np.array([0, 0, 1.5 * np.pi])) @ r0, atol=1e-9)
    with pytest.raises(InvalidParameterError):
        transport_legs("sideways", np.zeros(3), r0, np.ones(3), r0)


@pytest.mark.slow
def test_pour_plan_keeps_the_arm_off_the_container():
    """Test mug 11, hard episode 11 of seed 0: the handle faces the box and the plain approach puts
    the hand on the box wall; the chosen plan's whole pose chain is collision-free."""
    from keygen.expert._pour_util import ReachChecker
    from keygen.expert.collect import RunSpec
    from keygen.expert.pour import planned_poses

    _, seed = RunSpec("pour", "test", tuple(range(12)), "hard", 1.0, 0, False).episode(11)
    env = gym.make(
        "keygen/Pour-v0",
        object_split="test",
        object_id=11,
        setting="hard",
        include_rgb=False,
        image_size=32,
        num_points=64,
    ).unwrapped
    _, info = env.reset(seed=seed)
    expert = PourExpert()
    plan = expert.choose_plan(env, info["anchors"])
    checker = expert.scene_checker(env)
    reach = ReachChecker(env.controller.handles)
    q = None
    for position, rotation in planned_poses(info["anchors"], plan):
        q = reach.solve(position, rotation, q).qpos
        assert checker.is_free(q), checker.contacts(q)


def test_reach_rotation_error_is_the_column_cross_product_sum():
    """The written-out error is bit-identical to 0.5 * sum_k current[:, k] x goal[:, k], zero at the goal,
    and points along the rotation axis taking current to goal."""
    from scipy.spatial.transform import Rotation

    from keygen.expert._pour_util import _norm3, _rotation_error

    rng = np.random.default_rng(3)
    for _ in range(200):
        goal, current = Rotation.random(2, random_state=int(rng.integers(1 << 30))).as_matrix()
        reference = 0.5 * sum(np.cross(current[:, k], goal[:, k]) for k in range(3))
        assert np.array_equal(_rotation_error(goal, current), reference)
        assert not np.any(_rotation_error(goal, goal))
        v = rng.normal(size=3)
        assert _norm3(v) == np.linalg.norm(v)
    axis = np.array([0.0, 0.0, 1.0])
    small = Rotation.from_rotvec(0.1 * axis).as_matrix()
    err = _rotation_error(small, np.eye(3))  # goal = current turned by 0.1 rad about z
    np.testing.assert_allclose(err, np.sin(0.1) * axis, atol=1e-12)


def test_reach_checker_solves_a_reachable_pose(pour_env):
    """IK from home onto the pose of another posture's tcp: residuals at the solver's tolerance."""
    from keygen.expert._pour_util import ReachChecker
    from keygen.sim.robot import HOME_QPOS

    reach = ReachChecker(pour_env.unwrapped.controller.handles)
    m, d = reach.model, reach.data
    q_goal = np.array(HOME_QPOS, float) + np.array([0.2, -0.1, 0.1, 0.15, -0.1, 0.1, 0.2])
    d.qpos[reach._qadr] = q_goal
    mujoco.mj_kinematics(m, d)
    position, rotation = d.site_xpos[reach._site].copy(), d.site_xmat[reach._site].reshape(3, 3).copy()
    result = reach.solve(position, rotation)
    assert result.position_error < 1e-3 and result.rotation_error < 1e-2
    assert result.cost() < 0.05
    again = reach.solve(position, rotation)  # scratch arrays are reused: the same answer
    assert np.array_equal(again.qpos, result.qpos)
