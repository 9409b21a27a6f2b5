"""The knife expert's plan: grasp hand, insertion side and the route of the blade-down turn.

Turning a knife from lying flat to blade-down is a large rotation of the hand (90 degrees of
tilt plus a yaw); streamed as tcp targets, the env's differential IK follows it on whatever
joint branch it is on, and for many yaws that branch runs a wrist joint into its limit while
another branch would reach the same pose comfortably. So the expert chooses, before moving,
among anchor-derived candidates:

- the hand: the two top-down grasps across the handle (turned pi about the vertical);
- the insertion side: the two horizontal approaches across the slot;
- the grasp pitch: upright, or pitched about the closing axis (:data:`GRASP_PITCHES`) so that the
  blade-down insertion reaches forward and down instead of horizontally (long blades otherwise
  put the insertion at the edge of the arm's workspace);
- the route of the turn (:data:`ROUTES`): the geodesic, or the same rotation split into a turn
  about the vertical and a tilt about a horizontal axis (yaw first or tilt first, each with the
  yaw either way round), or the geodesic's long way; plus ``"joint_plan"``: the motion
  module's collision-checked joint-space plan (IK, straight joint path or RRT-Connect,
  retiming) to the pre-insertion pose, replayed as tcp targets;

and keeps the candidate whose whole target sequence, previewed through the controller
(:class:`~keygen.expert.preview.ControllerPreview`) from the current joints and checked against
the scene (:class:`~keygen.expert.motion.CollisionChecker`, the held knife left out), ends on
target, reaches the grasp, the hover and the pre-insertion pose on the way, keeps the largest
joint-limit margin, stays away from singular configurations and never falls far behind its
targets (:meth:`~keygen.expert.preview.PreviewResult.cost`). Those last three matter because the
knife creeps in the fingers (up to 3 cm measured): near a singularity or a swing between branches
the real arm follows another branch than the previewed one. Candidates are tried in order of
preference and the search stops at the first that costs (almost) nothing.

That least-cost choice (``choice="cost"``, the default) can switch the hand or the side on a few
hundredths of previewed cost. ``choice="first"`` takes those near-tie switches out: it previews
every candidate (about 24 in the hard setting) and takes the first, in a fixed order (hand 0 before
hand 1, the preferred insertion side before the other, upright before pitched, then the routes in
order), whose previewed cost is within :data:`FIRST_TOLERANCE` of the cheapest, so the plan switches
only where the preferred one becomes markedly worse. Measured on the training knife in hard
(``docs/benchmark.md``, "Knife: how many plans the expert's demonstrations mix"): the other hand in
8 of 60 episodes instead of 14, 17 plans instead of 19; the pitch stays mixed because there the
upright grasp is markedly worse for reach, not a near-tie.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from keygen.errors import InvalidParameterError
from keygen.expert.base import CLOSED, OPEN, interpolate_rotation, smooth_fraction, target
from keygen.expert.knife_geometry import (
    APPROACH_HEIGHT,
    FLOOR_CLEARANCE,
    GRASP_PITCHES,
    HOVER_TIP_HEIGHT,
    INSERT_SHARES,
    LIFT_HEIGHT,
    PRE_GRASP_HEIGHT,
    PRE_INSERT_TIP_HEIGHT,
    STEPS,
    TIP_DIRECTION_WEIGHT,
    TRANSPORT_CLEARANCE,
    Z,
    grasp_point,
    grasp_rotation,
    horizontal,
    insert_approach,
    insert_pose,
    insertion_pitch,
    unit,
)
from keygen.expert.motion import (
    Q_LOWER,
    Q_UPPER,
    CollisionChecker,
    PlanningError,
    joint_path_to_actions,
    plan_rrt_connect,
    retime,
    solve_ik,
)
from keygen.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle, yaw_matrix

# Previewing costs ~0.3 s of CPU per candidate: the routes worth it, in order of preference.
# The joint-space plan comes last and only when the tcp routes all fall short (FALLBACK_COST): it
# is re-planned from the real joints at execution, and its IK goal then need not be the previewed one.
ROUTES = ("geodesic", "yaw_first_other", "joint_plan")
FALLBACK_COST = 1.0
# Every route transport_legs draws (the others are alternatives tried while tuning the list above).
LEG_ROUTES = ("geodesic", "long", "yaw_first", "yaw_first_other", "tilt_first", "tilt_first_other")
ROUTE_COST = 0.01  # per position in ROUTES: on ties the simpler route wins
OTHER_HAND_COST = 0.02  # the hand turned pi from the home-like one
# Per 10 degrees of grasp pitch: a pitched grasp pinches less of a thin handle (it stays higher; one
# slipped out of the fingers on a 10 cm knife), so upright or the smaller pitch on near-ties.
PITCH_COST = 0.03
PREFERENCE_WEIGHT = 0.05  # per unit of the insert_approach preference (reach, blade direction)
GOOD_ENOUGH = 0.1  # a candidate below this cost (on target, margin ~0.1 rad) ends the search
PLAN_CHOICES = ("cost", "first")  # least cost among the candidates, or the first good enough in order
# "first": a candidate previewing within this much of the cheapest counts as good enough (as much
# as a millimetre of position error at a checkpoint, or 0.05 rad of joint-limit margin).
FIRST_TOLERANCE = 0.1
TURN_RATE = 0.15  # rad of hand rotation per control step at most on average (a held knife creeps)
IK_SEEDS = 4  # solve_ik calls (each with its own random seeds) when looking for a comfortable goal
GOAL_MARGIN = 0.25  # rad: goal configurations this far inside every joint limit count as comfortable


@dataclass(frozen=True)
class Leg:
    """One straight tcp move with cosine timing: to ``position``; the rotation follows the geodesic
    to ``rotation`` or, with ``yaw``, turns by that angle (any size, either sign) about world z."""

    position: np.ndarray
    rotation: np.ndarray
    steps: int
    yaw: float | None = None


@dataclass(frozen=True)
class KnifePlan:
    hand: int  # index into grasp_rotations
    approach: np.ndarray  # (3,) horizontal tcp z at insertion
    route: str  # one of ROUTES
    cost: float
    pitch: float = 0.0  # radians about the closing axis at the grasp (see knife_geometry.grasp_rotation)


def leg_targets(p0: np.ndarray, r0: np.ndarray, g0: float, leg: Leg, g1: float) -> list[np.ndarray]:
    """The (10,) actions of ``leg`` from pose (p0, r0) and gripper g0 (as the expert streams them)."""
    out = []
    for k in range(1, leg.steps + 1):
        s = smooth_fraction(k / leg.steps)
        if leg.yaw is not None:
            r = yaw_matrix(s * leg.yaw) @ r0
        else:
            r = interpolate_rotation(r0, leg.rotation, s)
        out.append(target(p0 + s * (leg.position - p0), r, g0 + s * (g1 - g0)))
    return out


def _turn_steps(angle: float) -> int:
    return int(np.clip(np.ceil(abs(angle) / TURN_RATE) + 2, STEPS["transport"], 30))


def _other_way(angle: float) -> float:
    return angle - 2 * np.pi * np.sign(angle) if angle != 0 else 2 * np.pi


def transport_legs(route: str, p0: np.ndarray, r0: np.ndarray, p1: np.ndarray, r1: np.ndarray) -> list[Leg]:
    """Two legs from the lifted pose (p0, r0) to the pre-insertion pose (p1, r1) via a raised midpoint."""
    mid = 0.5 * (p0 + p1)
    mid[2] = max(p0[2], p1[2]) + TRANSPORT_CLEARANCE
    turn = r1 @ r0.T  # world-frame rotation still to do
    if route in ("geodesic", "long"):
        rotvec = matrix_to_axis_angle(r0.T @ r1)  # in the hand frame
        angle = float(np.linalg.norm(rotvec))
        if route == "long" and angle > 1e-6:
            rotvec = rotvec / angle * _other_way(angle)
            angle = abs(_other_way(angle))
        half = r0 @ axis_angle_to_matrix(0.5 * rotvec)
        steps = _turn_steps(angle / 2)
        return [Leg(mid, half, steps), Leg(p1, r1, steps)]
    if route.startswith("yaw_first"):
        # turn = tilt(h, a) @ yaw(psi): the tilt brings world z where the turn sends it.
        tilt = _tilt_to(Z, turn @ Z)
        psi = _yaw_angle(tilt.T @ turn)
    elif route.startswith("tilt_first"):
        # turn = yaw(psi) @ tilt(h, a): the tilt sends turn^T z to z.
        tilt = _tilt_to(turn.T @ Z, Z)
        psi = _yaw_angle(turn @ tilt.T)
    else:
        raise InvalidParameterError(f"route must be one of {LEG_ROUTES}, got {route!r}")
    if route.endswith("_other"):
        psi = _other_way(psi)
    tilt_angle = float(np.linalg.norm(matrix_to_axis_angle(tilt)))
    if route.startswith("yaw_first"):
        return [
            Leg(mid, yaw_matrix(psi) @ r0, _turn_steps(psi), yaw=psi),
            Leg(p1, r1, _turn_steps(tilt_angle)),
        ]
    return [Leg(mid, tilt @ r0, _turn_steps(tilt_angle)), Leg(p1, r1, _turn_steps(psi), yaw=psi)]


def _tilt_to(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``a`` to ``b`` (about their common normal)."""
    axis = np.cross(a, b)
    s, c = float(np.linalg.norm(axis)), float(np.clip(a @ b, -1.0, 1.0))
    if s < 1e-9:
        return np.eye(3) if c > 0 else axis_angle_to_matrix(unit(np.cross(a, [1.0, 0.0, 0.0])) * np.pi)
    return axis_angle_to_matrix(axis / s * np.arctan2(s, c))


def _yaw_angle(r: np.ndarray) -> float:
    """The angle of a rotation about world z."""
    return float(np.arctan2(r[1, 0], r[0, 0]))


def grasp_targets(
    anchors: dict, hand: int, p0: np.ndarray, r0: np.ndarray, pitch: float = 0.0
) -> tuple[list, np.ndarray, np.ndarray]:
    """Actions from the current tcp pose to the lifted knife (no miss), the grasp position (where the
    knife's pose in the hand is fixed, with the anchors before the grasp) and the hand rotation."""
    grasp, down = grasp_point(anchors, pitch), grasp_rotation(anchors, hand, pitch)
    above = np.array([grasp[0], grasp[1], PRE_GRASP_HEIGHT])
    low = np.array([grasp[0], grasp[1], APPROACH_HEIGHT])
    lifted = np.array([grasp[0], grasp[1], LIFT_HEIGHT])
    legs = [
        (Leg(above, down, STEPS["pre_grasp"]), OPEN),
        (Leg(low, down, STEPS["approach"]), OPEN),
        (Leg(grasp, down, STEPS["descend"]), OPEN),
        (Leg(grasp, down, STEPS["close"]), CLOSED),
        (Leg(lifted, down, STEPS["lift"]), CLOSED),
    ]
    actions, p, r, g = [], p0, r0, OPEN
    for leg, grip in legs:
        actions += leg_targets(p, r, g, leg, grip)
        p, r, g = leg.position, leg.rotation, grip
    return actions, grasp, down


def grasp_checkpoint() -> int:
    """Index into :func:`grasp_targets`' actions of the last period before the fingers close."""
    return STEPS["pre_grasp"] + STEPS["approach"] + STEPS["descend"] - 1


def insertion_targets(
    pre: tuple[np.ndarray, np.ndarray], stages: Sequence[tuple[np.ndarray, np.ndarray]]
) -> list:
    """Actions from the pre-insertion pose down through the insertion stages (no re-aim)."""
    actions, (p, r) = [], pre
    for stage in stages:
        actions += leg_targets(p, r, CLOSED, Leg(stage[0], stage[1], STEPS["insert"]), CLOSED)
        p, r = stage
    return actions


class KnifePlanner:
    """Chooses a :class:`KnifePlan` for the scene of ``env`` (see the module docstring)."""

    def __init__(self, env, preview, checker, knife_geoms: Sequence[str], choice: str = "cost") -> None:
        if choice not in PLAN_CHOICES:
            raise InvalidParameterError(f"plan choice must be one of {PLAN_CHOICES}, got {choice!r}")
        self.env, self.preview, self.checker, self.knife_geoms = env, preview, checker, list(knife_geoms)
        self.choice = choice

    def choose(self, anchors: dict, center_offset: float, q0: np.ndarray, tcp: tuple) -> KnifePlan:
        across = unit(np.cross(Z, anchors["slot_axis"]))
        preferred = insert_approach(anchors)
        outward, tip_dir = horizontal(anchors["slot_center_top"]), horizontal(anchors["blade_axis"])
        candidates = []
        for hand in (0, 1):
            for approach in sorted((across, -across), key=lambda v: -(v @ preferred)):
                preference = approach @ outward - TIP_DIRECTION_WEIGHT * (approach @ tip_dir)
                extra = PREFERENCE_WEIGHT * (1.0 - preference) + OTHER_HAND_COST * hand
                candidates.append((extra, hand, approach, 0.0))
                for size in GRASP_PITCHES:
                    pitch = insertion_pitch(anchors, hand, approach, center_offset, size)
                    candidates.append((extra + PITCH_COST * size / np.radians(10.0), hand, approach, pitch))
        if self.choice == "first":
            return self._first_good_enough(candidates, anchors, center_offset, q0, tcp)
        candidates.sort(key=lambda c: c[0])
        best: KnifePlan | None = None
        self._lifted = {}
        for r_index, route in enumerate(ROUTES):
            if route == "joint_plan" and best is not None and best.cost < FALLBACK_COST:
                break
            for extra, hand, approach, pitch in candidates:
                extra = extra + ROUTE_COST * r_index
                if best is not None and extra >= best.cost:
                    continue
                previewed = self._preview_cost(anchors, center_offset, q0, tcp, hand, approach, pitch, route)
                if previewed is None:
                    continue
                cost = extra + previewed
                if best is None or cost < best.cost - 1e-9:
                    best = KnifePlan(hand, approach, route, cost, pitch)
            if best is not None and best.cost < GOOD_ENOUGH:
                break
        return best

    def _first_good_enough(self, candidates, anchors, center_offset, q0, tcp) -> KnifePlan | None:
        """Every candidate previewed; the first in the built order (hand, side, pitch, then route)
        whose previewed cost is within FIRST_TOLERANCE of the lowest. Kept in ``self.scored``."""
        self._lifted, self.scored = {}, []
        for r_index, route in enumerate(ROUTES):
            if route == "joint_plan" and self.scored and min(c for *_, c in self.scored) < FALLBACK_COST:
                break
            for c_index, (extra, hand, approach, pitch) in enumerate(candidates):
                previewed = self._preview_cost(anchors, center_offset, q0, tcp, hand, approach, pitch, route)
                if previewed is not None:
                    plan = KnifePlan(hand, approach, route, extra + ROUTE_COST * r_index + previewed, pitch)
                    self.scored.append(((c_index, r_index), plan, previewed))
        if not self.scored:
            return None
        bound = min(c for *_, c in self.scored) + FIRST_TOLERANCE
        return min((key, plan) for key, plan, c in self.scored if c <= bound)[1]

    def _preview_cost(self, anchors, center_offset, q0, tcp, hand, approach, pitch, route) -> float | None:
        """Previewed cost of grasping with (hand, pitch), then moving by route to insert from approach."""
        depth = float(anchors["slot_depth"][0]) - FLOOR_CLEARANCE
        if (hand, pitch) not in self._lifted:  # the grasp is shared by every side and route
            actions, grasp, down = grasp_targets(anchors, hand, *tcp, pitch=pitch)
            result = self.preview.rollout(q0, actions, self.checker, [grasp_checkpoint()])
            self._lifted[hand, pitch] = (result, grasp, down)
        before, grasp, down = self._lifted[hand, pitch]
        # The knife's pose in the hand from the grasp pose and the anchors before the grasp.
        hover = insert_pose(grasp, down, anchors, approach, -HOVER_TIP_HEIGHT, center_offset)
        pre = insert_pose(grasp, down, anchors, approach, -PRE_INSERT_TIP_HEIGHT, center_offset)
        stages = [
            insert_pose(grasp, down, anchors, approach, share * depth, center_offset)
            for share in INSERT_SHARES
        ]
        lifted = np.array([grasp[0], grasp[1], LIFT_HEIGHT])
        actions = self._transport(route, before.q[-1], lifted, down, hover)
        if actions is None:
            return None
        # The hover and the pre-insertion pose must be reached, not only the last stage.
        checkpoints = [len(actions) - 1, len(actions) - 1 + STEPS["insert"]]
        actions += insertion_targets(hover, [pre, *stages])
        after = self.preview.rollout(before.q[-1], actions, self.checker, checkpoints)
        return before.cost() + after.cost()

    def _transport(self, route, q_lifted, lifted, down, pre) -> list | None:
        if route != "joint_plan":
            actions, p, r = [], lifted, down
            for leg in transport_legs(route, lifted, down, *pre):
                actions += leg_targets(p, r, CLOSED, leg, CLOSED)
                p, r = leg.position, leg.rotation
            return actions
        actions = self.joint_plan(q_lifted, pre)
        return None if actions is None else list(actions)

    def joint_plan(self, q_arm: np.ndarray, pose: tuple[np.ndarray, np.ndarray]) -> np.ndarray | None:
        """(T, 10) actions of a joint-space move from arm joints ``q_arm`` to a tcp pose, or None."""
        return joint_space_move(self.env.model, self.env.controller.handles, self.checker, q_arm, pose)


def joint_space_move(
    model: mujoco.MjModel, handles, checker: CollisionChecker, q_start: np.ndarray, pose: tuple
) -> np.ndarray | None:
    """The motion module's pipeline with a chosen goal: IK solutions from several seeds, the
    collision-free one with the widest joint-limit margin (up to GOAL_MARGIN) nearest ``q_start``;
    a straight joint path if it is free, else RRT-Connect; retimed; as (T, 10) tcp actions with
    the gripper closed. None when no collision-free goal or path exists."""
    q_start = np.clip(np.asarray(q_start, float), Q_LOWER, Q_UPPER)
    goals = []
    for seed in range(IK_SEEDS):
        ik = solve_ik(model, handles, *pose, q_start, seed=seed, accept=checker.is_free)
        if ik.ok:
            margin = float(np.min(np.minimum(ik.q - Q_LOWER, Q_UPPER - ik.q)))
            goals.append((min(margin, GOAL_MARGIN), -float(np.linalg.norm(ik.q - q_start)), seed, ik.q))
    if not goals or not checker.is_free(q_start):
        return None
    q_goal = max(goals, key=lambda g: g[:3])[3]
    if checker.segment_is_free(q_start, q_goal):
        waypoints = np.stack([q_start, q_goal])
    else:
        try:
            waypoints = plan_rrt_connect(checker, q_start, q_goal, seed=0, max_iters=1500)
        except PlanningError:
            return None
    trajectory = retime(waypoints)
    return joint_path_to_actions(model, handles, trajectory.q[1:], CLOSED)
