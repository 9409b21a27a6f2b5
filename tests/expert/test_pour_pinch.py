"""The pour expert's outside pinch: pose geometry, fit choice, choice against finger-through, an episode."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import keygen  # noqa: F401  (registers the ids, sets MUJOCO_GL before mujoco loads)
from keygen.errors import InvalidParameterError
from keygen.expert import pour_pinch
from keygen.expert.pour import GraspPlan, PourExpert, mug_clearance, planned_poses, pose_chain
from keygen.expert.pour_pinch import (
    BODY_WANTED,
    PINCH_DEPTHS,
    PINCH_OPENINGS,
    SIDE_WANTED,
    PinchPlan,
    fit_pinch,
    fit_pinch_for,
    pinch_pose,
    planned_pinch_poses,
    side_lip,
)
from keygen.expert.runner import make_expert, run_episode
from keygen.sim.robot import FINGER_MAX, PAD_SIZE

UP = np.array([0.0, 0.0, 1.0])


def _anchors(yaw: float = 0.6) -> dict:
    """A hand-built upright mug: axis at (0.5, 0.1), handle toward ``yaw``, bar 60 mm out, 40 mm up."""
    radial = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    normal = np.cross(UP, radial)
    bottom = np.array([0.5, 0.1, 0.0])
    top = bottom + 0.09 * UP
    return (
        {
            "bottom_center": bottom,
            "opening_center": top,
            "pour_point": top - 0.04 * radial,
            "handle_grasp": bottom + 0.06 * radial + 0.04 * UP,
            "grasp_approach": normal,
            "container_center": np.array([0.5, -0.2, 0.06]),
        },
        radial,
        normal,
    )


@pytest.mark.parametrize("closing_sign", [1.0, -1.0])
@pytest.mark.parametrize("pitch", pour_pinch.PINCH_PITCHES)
def test_pinch_pose_closes_across_the_handle_plane_and_straddles_the_bar(closing_sign, pitch):
    anchors, radial, normal = _anchors()
    depth = PINCH_DEPTHS[0]
    position, rotation = pinch_pose(anchors, PinchPlan(closing_sign, 1.0, 0.0, 0.0, pitch), depth)
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(rotation), 1.0)
    closing, approach = rotation[:, 1], rotation[:, 2]
    assert np.isclose(abs(closing @ normal), 1.0)  # jaws close along the handle plane's normal
    assert approach @ radial < 0 and approach[2] < 0  # toward the mug's axis, pitched downward
    assert np.isclose((position - anchors["handle_grasp"]) @ normal, 0.0, atol=1e-12)  # tcp in the plane
    # The pads (their inner faces at +-opening * FINGER_MAX along the closing axis) straddle a bar
    # up to 5 mm thick on either side of the plane, and along the approach they span the bar's
    # centreline: from 20 mm behind the tcp to the fingertips 5 mm past it.
    assert PINCH_OPENINGS[0] * FINGER_MAX > 0.005
    along = (anchors["handle_grasp"] - position) @ approach
    assert -(PAD_SIZE[2] - 0.005) < along < 0.005 and np.isclose(along, -depth)
    # The fingertips stay clear of the body (radius <= 45 mm here): they reach 11 mm past the bar.
    tip = position + 0.005 * approach
    assert np.hypot(*(tip - anchors["bottom_center"])[:2]) > 0.045


def test_side_lip_is_on_the_rim_90_degrees_from_the_handle():
    anchors, radial, normal = _anchors(yaw=-2.0)
    rim = np.linalg.norm(anchors["pour_point"] - anchors["opening_center"])
    points = []
    for side in (1.0, -1.0):
        lip, direction = side_lip(anchors, side)
        assert np.isclose(np.linalg.norm(lip - anchors["opening_center"]), rim)
        assert np.isclose(direction @ radial, 0.0, atol=1e-12) and np.isclose(direction @ normal, side)
        np.testing.assert_allclose(lip, anchors["opening_center"] + rim * direction, atol=1e-12)
        points.append(lip)
    assert np.linalg.norm(points[0] - points[1]) == pytest.approx(2 * rim)
    # The poured-over lip's pose chain: 7 poses, the last two tipped (the lip goes down on its side).
    plan = PinchPlan(1.0, 1.0, 0.0, 0.0)
    poses = planned_pinch_poses(anchors, plan, 0.004)
    assert len(poses) == 7
    tipped = poses[-1][1] @ poses[4][1].T  # world rotation from the carry to the full tip
    axis = np.array([tipped[2, 1] - tipped[1, 2], tipped[0, 2] - tipped[2, 0], tipped[1, 0] - tipped[0, 1]])
    assert abs(axis / np.linalg.norm(axis) @ radial) > 0.99  # tipped about the radial axis
    np.testing.assert_allclose(tipped @ UP @ normal, np.sin(np.deg2rad(130.0)), atol=1e-9)


def test_pose_chain_matches_the_finger_through_plan():
    anchors, _, _ = _anchors()
    plan = GraspPlan(1.0, 1.0, 0.3, 0.0)
    from keygen.expert.pour import grasp_pose

    grasp, rotation = grasp_pose(anchors, plan)
    for (p, r), (q, s) in zip(
        planned_poses(anchors, plan),
        pose_chain(anchors, grasp, rotation, 0.3, plan.lip(anchors)),
        strict=True,
    ):
        np.testing.assert_allclose(p, q)
        np.testing.assert_allclose(r, s)


class _FakeClearance:
    """Distances (handle, body) that depend only on the pose's depth past the grasp point and the opening."""

    def __init__(self, grasp_point, approach, body_at_zero: float, side_per_opening: float) -> None:
        self.grasp_point, self.approach = grasp_point, approach
        self.body_at_zero, self.side_per_opening = body_at_zero, side_per_opening

    def distances(self, position, rotation, opening):
        depth = (np.asarray(position) - self.grasp_point) @ self.approach
        return np.array([self.side_per_opening * opening - 0.003, self.body_at_zero - depth])

    def sweep(self, poses, opening):
        return np.min([self.distances(p, r, opening) for p, r in poses], axis=0)


def test_fit_pinch_takes_the_deepest_depth_and_narrowest_opening_meeting_the_clearances():
    anchors, _, _ = _anchors()
    _, rotation = pinch_pose(anchors, PinchPlan(1.0, 1.0, 0.0, 0.0), 0.0)
    is_handle = np.array([True, False])
    far = _FakeClearance(anchors["handle_grasp"], rotation[:, 2], 0.05, 0.04)
    fit = fit_pinch(far, is_handle, anchors["handle_grasp"], rotation)
    assert fit.depth == PINCH_DEPTHS[0] and fit.margin >= 0
    assert fit.side >= SIDE_WANTED and fit.opening == pytest.approx(0.2)  # 0.04 * 0.2 - 0.003 >= 0.004
    # A body 9 mm past the grasp point: only depths up to 3 mm leave BODY_WANTED (6 mm).
    near = _FakeClearance(anchors["handle_grasp"], rotation[:, 2], 0.009, 0.04)
    fit = fit_pinch(near, is_handle, anchors["handle_grasp"], rotation)
    assert fit.depth == 0.002 and fit.body >= BODY_WANTED
    # Nothing meets the wanted body clearance: the best margin (the shallowest depth) is returned.
    touching = _FakeClearance(anchors["handle_grasp"], rotation[:, 2], 0.0, 0.04)
    fit = fit_pinch(touching, is_handle, anchors["handle_grasp"], rotation)
    assert fit.depth == PINCH_DEPTHS[-1] and fit.margin < 0


def _env(split: str, index: int, scale: float):
    return gym.make(
        "keygen/Pour-v0",
        object_split=split,
        object_id=index,
        setting="hard",
        scale=scale,
        include_rgb=False,
        image_size=64,
        num_points=256,
    ).unwrapped


def test_fitted_pinch_on_a_small_mug_clears_it_open_and_squeezes_the_handle_closed():
    env = _env("test", 2, 0.7)  # an "ear" handle whose gap no finger gets through at this scale
    _, info = env.reset(seed=3)
    anchors = info["anchors"]
    position, rotation, fit = fit_pinch_for(env, anchors, PinchPlan(1.0, 1.0, 0.0, 0.0))
    assert fit.margin >= 0.0
    checker, is_handle = mug_clearance(env)
    open_dist = checker.distances(position, rotation, fit.opening)
    closed_dist = checker.distances(position, rotation, 0.0)
    assert open_dist[is_handle].min() >= SIDE_WANTED - 1e-9 and open_dist[~is_handle].min() >= BODY_WANTED
    assert closed_dist[is_handle].min() < 0.0  # the bar lies between the pads
    assert closed_dist[~is_handle].min() >= BODY_WANTED  # and closing does not bring them to the body


def test_choice_keeps_finger_through_when_it_fits_and_pinches_when_it_cannot():
    expert = PourExpert()
    env = _env("test", 4, 1.0)  # finger-through clearance ~7 mm
    _, info = env.reset(seed=3)
    plan = expert.choose_plan(env, info["anchors"])
    assert isinstance(plan, GraspPlan) and expert.through_clearance > pour_pinch.PINCH_SWITCH
    env = _env("test", 2, 0.7)  # finger-through overlaps the mug by ~4 mm
    _, info = env.reset(seed=3)
    plan = expert.choose_plan(env, info["anchors"])
    assert expert.through_clearance < pour_pinch.PINCH_SWITCH
    assert isinstance(plan, PinchPlan) and plan.lip_side in (1.0, -1.0)


def test_grasp_mode_overrides_the_choice_both_ways():
    env = _env("test", 4, 1.0)  # finger-through fits here: auto takes it, pinch mode does not
    _, info = env.reset(seed=3)
    assert isinstance(PourExpert(grasp="pinch").choose_plan(env, info["anchors"]), PinchPlan)
    env = _env("test", 2, 0.7)  # no finger fits: auto pinches, through mode does not
    _, info = env.reset(seed=3)
    assert isinstance(PourExpert(grasp="through").choose_plan(env, info["anchors"]), GraspPlan)


def test_unknown_grasp_mode_is_refused():
    with pytest.raises(InvalidParameterError, match="grasp must be one of"):
        PourExpert(grasp="scoop")
    with pytest.raises(InvalidParameterError):
        make_expert("pour", grasp="scoop")


def test_pinch_episode_on_a_small_mug_pours():
    env = _env("test", 9, 0.7)
    expert = PourExpert(grasp="pinch")  # this mug's finger-through fit is positive: force the pinch
    result = run_episode(env, expert, seed=int(np.random.SeedSequence([0, 9]).generate_state(1)[0]))
    assert isinstance(expert.plan, PinchPlan)
    assert result.success, (result.failure, expert.phase, result.metrics)
    assert result.metrics["held_by_handle"] == 1.0 and expert.grasp_attempts == 1
