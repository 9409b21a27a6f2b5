"""The scripted pour expert: grasp the mug by its handle, carry the lip over the box, tip it.

Phases (each a block of :meth:`PourExpert.script`)::

    plan       pick the grasp variant (approach side, jaw order, approach pitch, turn of the mug for
               the pour) whose planned pose chain the arm reaches most comfortably without touching
               the table or the box (IK reach costs + the motion module's CollisionChecker); where
               no finger gets through the handle, the outside pinch of the bar instead, poured
               over a side lip (:mod:`keygen.expert.pour_pinch`; same phases below)
    fit        among tcp offsets along the handle's height and gripper openings, the one whose way
               in keeps the fingers farthest from the mug (FingerClearance; body contact weighs more)
    pre-grasp  above, then level with, a point 10 cm short of the handle along the approach; open
               to the fitted opening; dwell so the arm settles
    approach   straight in along the approach, the last 35 mm slowly, until the tcp sits just past
               the handle bar
    grasp      close; guard: the jaws stop on something (opening stays above GRIP_MIN_OPENING) and
               the handle rises with the hand over a short test lift; on a miss: set the mug down,
               back out (closed if the jaws closed on nothing), re-fit on the mug where it now
               stands and try once more, then ExpertGaveUp("grasp_missed")
    lift       straight up
    transport  translate so that the lip sits over the box centre, above its walls
    pour       tip about the horizontal axis across the handle (the lip goes down), lowering the lip
               as the body swings up; hold while the spheres run out
    release    tip back, carry the mug back over its start, set it down, open
    retreat    back out along the approach and up

Everything is computed from ``info["anchors"]`` and the proprioception. Privileged access beyond
the anchors (``env.unwrapped``): the robot's kinematic description (``controller.handles``, for
the reach check), the live scene model (for the collision check of the plan and for the finger
clearance against the mug's collision parts, labelled handle or body by the asset) and, as a
fallback when no fitted opening gets through, the generator's handle depth and gap
(:func:`~keygen.sim.tasks.pour.pregrasp_opening`).
"""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import dataclass

import numpy as np

from keygen.errors import InvalidParameterError
from keygen.expert._pour_util import (
    ReachChecker,
    cosine_profile,
    interpolate_rotation,
    rotation_about,
)
from keygen.expert.base import CLOSED, Action, Expert, ExpertGaveUp, Step, target
from keygen.expert.clearance import FingerClearance, collision_geoms_of_body
from keygen.expert.motion import CollisionChecker
from keygen.geometry.rotations import rot6d_to_matrix
from keygen.sim.robot import FINGER_MAX
from keygen.sim.tasks.pour import pregrasp_opening

UP = np.array([0.0, 0.0, 1.0])
GRASP_MODES = ("auto", "through", "pinch")
APPROACH_PITCH = np.deg2rad(15.0)  # approach tilted downward: the wrist stays clear of the table
# A steeper approach lifts the hand over a container wall next to the handle, at the price of a
# taller footprint of the finger in the handle's plane (checked by the grasp fit).
STEEP_PITCH = np.deg2rad(35.0)
STEEP_COST = 0.02
FIT_WANTED = 0.002  # m of finger clearance through the handle below which a plan is penalised
FIT_COST = 500.0  # per m of clearance missing (0.5 per mm)
GRASP_DEPTH = 0.005  # m past handle_grasp along the approach: fingertips reach beyond the bar
PREGRASP_BACKOFF = 0.10  # m short of the grasp along the approach
PREGRASP_RISE = 0.08  # m above the pre-grasp for the first waypoint (comes down outside the mug)
GRIP_MIN_OPENING = 0.03  # opening fraction: below it the jaws closed on nothing
TEST_LIFT = 0.03  # m: the short lift that checks the mug comes along
LIFT_FOLLOW = 0.5  # fraction of the test lift the handle must follow
LIFT_HEIGHT = 0.15  # m, total lift above the grasp
LIP_OVER_WALL = 0.03  # m between the lip and the box wall top before tipping (beyond the mug height)
LIP_SHIFT = 0.02  # m toward the handle side: the stream leaves the lip slightly outward
POUR_ANGLE = np.deg2rad(130.0)
# Tipping schedule: at POUR_ANGLE / 30 per step to TIP_SPILL_ANGLE (the spheres start to leave
# the mug at 105-115 degrees), then at 2 degrees per step (about half) to POUR_ANGLE, then hold.
# Tipped at full rate to the end, the spheres first move on a ~40-degree wall and fly up to 13 cm
# past the box's far wall (train/hard mugs 11 and 24). A faster first part (6 degrees per step)
# shook the mug out of an edge grip (test/hard mug 7, dropped at 85 degrees).
TIP_SPILL_ANGLE = np.deg2rad(100.0)
TIP_FAST_STEPS = 23
TIP_SLOW_STEPS = 15
TIP_HOLD_STEPS = 15
POUR_LIP_CLEARANCE = 0.025  # m above the wall top for the lip when fully tipped
SET_DOWN_CLEARANCE = 0.01  # m above the table for the mug's bottom when releasing
# Turns of the mug about world z during transport, tried in this order when the plain carry is hard.
POUR_TURNS = tuple(np.deg2rad(d) for d in (0.0, 45.0, -45.0, 90.0, -90.0, 135.0, -135.0, 180.0))
TURN_COST = 0.01  # per rad: prefer small turns among comfortable plans
# The mirrored approach (from the other side of the handle) missed the bar far more often in the
# benchmark (easy: 6 of 6 misses) than the anchor's own approach: used only when clearly easier to reach.
MIRROR_COST = 0.03
GOOD_ENOUGH = 0.02  # reach cost below which the search stops
# Grasp fit: the finger must pass through the handle opening, which on "ear" and narrow-necked
# handles is barely taller than the finger. Candidates: offsets of the tcp along its x axis (the
# handle's height direction) and gripper openings (how far the inner finger sits from the bar).
FIT_OFFSETS = np.arange(-0.008, 0.0081, 0.002)  # m
FIT_OPENINGS = np.arange(0.06, 0.501, 0.02)  # fraction of FINGER_MAX
FIT_SWEEP = (0.0, 0.01, 0.02, 0.03, 0.05)  # m short of the grasp along the approach: poses checked
BODY_MARGIN = 0.003  # m: a finger on the body fails the task, on the handle it only nudges the mug
OFFSET_COST = 0.05  # m of clearance per m of offset: prefer the anchor's own grasp point on ties
# Below this clearance no candidate gets the finger through the handle (small mugs: at scale 0.7
# most handle gaps are narrower than the 18 mm finger); then the generator's centred opening.
FIT_FALLBACK = -0.004  # m
# Approach in two stages: fast to ENTRY short of the grasp, then slowly through the handle so that
# the arm's tracking error (mm at speed) stays below the fit's clearance.
ENTRY = 0.035  # m short of the grasp
PREGRASP_DWELL = 3  # control steps holding the pre-grasp: the arm settles before going in


@dataclass(frozen=True)
class GraspPlan:
    """One grasp variant, fixed for the episode: signs relative to the anchors' directions."""

    approach_sign: float  # +1: along grasp_approach; -1: the mirror approach from the other side
    closing_sign: float  # +1: tcp y along the handle's radial axis; -1: the jaws swapped
    pour_turn: float  # rad about world z applied to the mug during transport (reach for the pour)
    cost: float
    pitch: float = APPROACH_PITCH  # rad, approach tilted downward

    def lip(self, anchors: dict) -> tuple[np.ndarray, np.ndarray]:
        """The lip opposite the handle and its horizontal direction from the mug's axis."""
        return anchors["pour_point"], -radial_axis(anchors)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _horizontal(v: np.ndarray) -> np.ndarray:
    return _unit(np.array([v[0], v[1], 0.0]))


def grasp_pose(anchors: dict, plan: GraspPlan) -> tuple[np.ndarray, np.ndarray]:
    """tcp position and rotation for the handle grasp of ``plan`` from the current anchors."""
    radial = _horizontal(anchors["handle_grasp"] - anchors["bottom_center"])
    side = plan.approach_sign * _horizontal(anchors["grasp_approach"])
    approach = np.cos(plan.pitch) * side - np.sin(plan.pitch) * UP
    closing = plan.closing_sign * radial
    closing = _unit(closing - (closing @ approach) * approach)
    rotation = np.column_stack([np.cross(closing, approach), closing, approach])
    return anchors["handle_grasp"] + GRASP_DEPTH * approach, rotation


def pregrasp_pose(grasp: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    return grasp - PREGRASP_BACKOFF * rotation[:, 2]


def mug_height(anchors: dict) -> float:
    return float(np.linalg.norm(anchors["opening_center"] - anchors["bottom_center"]))


def radial_axis(anchors: dict) -> np.ndarray:
    """Horizontal unit vector from the mug's axis toward its handle."""
    return _horizontal(anchors["handle_grasp"] - anchors["bottom_center"])


def lip_goal(anchors: dict, radial: np.ndarray) -> np.ndarray:
    """Where the lip goes before tipping: over the box centre, the mug's height above the walls."""
    lift = mug_height(anchors) + LIP_OVER_WALL
    return anchors["container_center"] + LIP_SHIFT * radial + lift * UP


def carry_pose(
    anchors: dict,
    tcp: np.ndarray,
    rotation: np.ndarray,
    turn: float,
    lip_at: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """tcp pose that puts the lip at its goal with the mug turned ``turn`` about world z; and the lip.

    ``lip_at``: the lip point and its horizontal direction from the mug's axis (default: the
    pour_point, opposite the handle); the stream leaves LIP_SHIFT outward of the box centre.
    """
    point, direction = lip_at if lip_at is not None else (anchors["pour_point"], -radial_axis(anchors))
    yaw = rotation_about(UP, turn) if turn else np.eye(3)
    lip = lip_goal(anchors, -(yaw @ direction))
    return lip + yaw @ (tcp - point), yaw @ rotation, lip


def tipped_pose(
    anchors: dict, tcp: np.ndarray, rotation: np.ndarray, lip: np.ndarray, radial: np.ndarray, angle: float
) -> tuple[np.ndarray, np.ndarray]:
    """tcp pose tipped by ``angle`` about the lip; the lip sinks as the mug's body swings up.

    The axis ``radial x z`` turns the ``radial`` side up and the lip (on the other side) down; a
    side lip passes ``radial`` = minus its own direction.
    """
    turn = rotation_about(np.cross(radial, UP), angle)
    top = anchors["container_center"][2]
    sink = max(mug_height(anchors) * np.cos(angle), 0.0)
    lip_now = np.array([lip[0], lip[1], top + POUR_LIP_CLEARANCE + sink])
    return lip_now + turn @ (tcp - lip), turn @ rotation


def tip_angles() -> np.ndarray:
    """Tilt per control step of the pour phase (rad): fast, slow past the spill angle, hold."""
    fast = TIP_SPILL_ANGLE * np.arange(1, TIP_FAST_STEPS + 1) / TIP_FAST_STEPS
    rise = np.arange(1, TIP_SLOW_STEPS + 1) / TIP_SLOW_STEPS
    slow = TIP_SPILL_ANGLE + (POUR_ANGLE - TIP_SPILL_ANGLE) * rise
    return np.concatenate([fast, slow, np.full(TIP_HOLD_STEPS, POUR_ANGLE)])


def planned_poses(anchors: dict, plan: GraspPlan) -> list[tuple[np.ndarray, np.ndarray]]:
    """The chain of tcp poses the script will command for ``plan`` (rigid grasp assumed)."""
    grasp, rotation = grasp_pose(anchors, plan)
    return pose_chain(anchors, grasp, rotation, plan.pour_turn, plan.lip(anchors))


def pose_chain(
    anchors: dict,
    grasp: np.ndarray,
    rotation: np.ndarray,
    turn: float,
    lip_at: tuple[np.ndarray, np.ndarray],
) -> list[tuple[np.ndarray, np.ndarray]]:
    """tcp poses from a grasp pose on: pre-grasp (raised, level), grasp, lift, carry, half and full tip.

    ``lip_at``: the lip point and its horizontal direction from the mug's axis; the mug tips
    about the horizontal axis across that direction (the lip goes down).
    """
    pre = pregrasp_pose(grasp, rotation)
    lifted = grasp + LIFT_HEIGHT * UP
    carried, carried_rot, lip = carry_pose(anchors, grasp, rotation, turn, lip_at)
    away = -(rotation_about(UP, turn) @ lip_at[1])  # horizontal, from the lip across the mug
    poses = [(pre + PREGRASP_RISE * UP, rotation), (pre, rotation), (grasp, rotation), (lifted, rotation)]
    poses.append((carried, carried_rot))
    for angle in (0.5 * POUR_ANGLE, POUR_ANGLE):
        poses.append(tipped_pose(anchors, carried, carried_rot, lip, away, angle))
    return poses


@dataclass(frozen=True)
class GraspFit:
    """Where the fingers go through the handle, fixed before the approach."""

    offset: float  # m along the tcp x axis from the anchor's grasp point
    opening: float  # gripper command while approaching (fraction of the stroke)
    clearance: float  # m: smallest finger-to-handle distance (or body distance - BODY_MARGIN) on the way in


def fit_score(handle: float, body: float) -> float:
    """Rank of a candidate from its smallest finger distances (m) to the handle and the body.

    Clear of both: the smaller of the handle distance and the body distance less BODY_MARGIN
    (a body contact fails the episode, so the body is kept farther). Overlapping either: below
    every clear candidate (under -BODY_MARGIN), by the overlap. An overlap is a certain contact on
    the way in, which pushes the mug onto the inner finger; a finger nearer the body than the
    margin only risks one (on train mug 22 the margin alone preferred a 0.4 mm overlap of the
    handle to 1.0 / 1.2 mm of clearance from handle / body).
    """
    overlap = min(handle, body)
    if overlap < 0.0:
        return overlap - BODY_MARGIN
    return min(handle, body - BODY_MARGIN)


def fit_grasp(
    clearance: FingerClearance, is_handle: np.ndarray, grasp: np.ndarray, rotation: np.ndarray
) -> GraspFit:
    """The offset and opening whose approach sweep keeps the fingers farthest from the mug.

    ``is_handle`` (T,) marks the checker's targets that belong to the handle; the body counts
    BODY_MARGIN closer than it is, because touching it fails the episode.
    """
    best = None
    for offset in FIT_OFFSETS:
        poses = [(grasp + offset * rotation[:, 0] - s * rotation[:, 2], rotation) for s in FIT_SWEEP]
        penalty = OFFSET_COST * abs(offset)
        for opening in FIT_OPENINGS:
            handle = body = np.inf
            for position, rot in poses:
                dist = clearance.distances(position, rot, float(opening))  # (T,)
                handle = min(handle, dist[is_handle].min(initial=np.inf))
                body = min(body, dist[~is_handle].min(initial=np.inf))
                # The distances only shrink as poses are added and the score grows with both: a
                # candidate already no better than the best cannot win (exact; the fit runs 2.4-4x faster).
                if best is not None and fit_score(handle, body) - penalty <= best[0] + 1e-9:
                    break
            else:
                ranked = fit_score(handle, body) - penalty
                if best is None or ranked > best[0] + 1e-9:
                    gap = min(handle, body - BODY_MARGIN)
                    best = (ranked, GraspFit(float(offset), float(opening), float(gap)))
    return best[1]


def mug_clearance(env) -> tuple[FingerClearance, np.ndarray]:
    """Finger clearance against the mug's collision parts where it stands now, and (T,) which of
    the checker's targets belong to the handle (by the asset's part labels; unlabelled: body)."""
    env = env.unwrapped
    task = env.task
    geoms = collision_geoms_of_body(env.model, task.manipulated.body_id)
    labels = [part.label for part in task.asset.collision]
    if len(labels) == len(geoms):
        is_handle = np.array([lab == "handle" for lab in labels])
    else:
        is_handle = np.zeros(len(geoms), bool)
    checker = FingerClearance(env.model, env.data, env.scene.robot, geoms)
    # The checker sorts its targets; keep the labels in the same order.
    order = {int(g): i for i, g in enumerate(geoms)}
    return checker, np.array([is_handle[order[int(t)]] for t in checker.targets])


class PourExpert(Expert):
    """Handle grasp, lift, carry over the box, tip about the lip; one grasp retry."""

    task = "pour"

    def __init__(self, grasp: str = "auto") -> None:
        """``grasp``: ``auto`` (finger through the handle where a finger fits, else the outside
        pinch), ``through`` (never the pinch) or ``pinch`` (always the outside pinch of the bar)."""
        super().__init__()
        if grasp not in GRASP_MODES:
            raise InvalidParameterError(f"grasp must be one of {GRASP_MODES}, got {grasp!r}")
        self.grasp = grasp
        self.plan: GraspPlan | None = None
        self.grasp_attempts = 0
        self._reach: ReachChecker | None = None
        self._reach_handles = None
        self.fit: GraspFit | None = None
        self.through_clearance: float | None = None  # best finger-through fit of the last plan, m

    # -- helpers ---------------------------------------------------------------------------------
    def choose_plan(self, env, anchors: dict):  # -> GraspPlan | pour_pinch.PinchPlan
        """The grasp variant whose planned pose chain the arm reaches at the lowest cost.

        Cost: reach (IK residuals, joint-limit margins, wrist height) plus arm-versus-scene
        collisions of every planned pose and of the joint segments between them (the motion
        module's CollisionChecker), plus a penalty when the finger's way through the handle at
        the variant's pitch leaves less than FIT_WANTED of clearance.

        When even the best fit overlaps the mug (by more than pour_pinch.PINCH_SWITCH), the
        outside pinch of the bar (:func:`keygen.expert.pour_pinch.choose_pinch`) is planned
        instead: the finger would push the mug on its way in, and a touch on the body fails.
        """
        handles = env.unwrapped.controller.handles
        if self._reach is None or self._reach_handles is not handles:
            self._reach, self._reach_handles = ReachChecker(handles), handles
        checker = self.scene_checker(env)
        fit_penalty, through = {}, -np.inf
        for pitch in (APPROACH_PITCH, STEEP_PITCH):
            _, _, fit = self.fit_for(env, anchors, GraspPlan(1.0, 1.0, 0.0, 0.0, pitch))
            fit_penalty[pitch] = FIT_COST * max(FIT_WANTED - fit.clearance, 0.0)
            fit_penalty[pitch] += STEEP_COST * (pitch != APPROACH_PITCH)
            through = max(through, fit.clearance)
        self.through_clearance = float(through)
        from keygen.expert import pour_pinch  # deferred: pour_pinch imports this module

        if self.grasp == "pinch" or (self.grasp == "auto" and through < pour_pinch.PINCH_SWITCH):
            # No finger gets through the handle without pushing the mug: pinch the bar from outside.
            return pour_pinch.choose_pinch(env, anchors, self._reach, checker)
        best = None
        # Without a turn first: a plan that needs no turn and costs nothing is taken at once.
        for turn in POUR_TURNS:
            for pitch in (APPROACH_PITCH, STEEP_PITCH):
                for approach_sign in (1.0, -1.0):
                    for closing_sign in (1.0, -1.0):
                        probe = GraspPlan(approach_sign, closing_sign, turn, 0.0, pitch)
                        extra = TURN_COST * abs(turn) + MIRROR_COST * (approach_sign < 0) + fit_penalty[pitch]
                        bound = np.inf if best is None else best.cost - extra
                        cost = self._reach.path_cost(planned_poses(anchors, probe), bound, checker) + extra
                        if best is None or cost < best.cost - 1e-9:  # ties go to the earlier variant
                            best = GraspPlan(approach_sign, closing_sign, turn, cost, pitch)
            if best.cost < GOOD_ENOUGH:
                break
        return best

    @staticmethod
    def scene_checker(env) -> CollisionChecker:
        """Arm-versus-scene collision checker for the plan: table and container count; the mug and
        its spheres do not (they move with the hand once grasped, and the fingers' way through
        the handle is checked by :meth:`fit_for`)."""
        env = env.unwrapped
        m = env.model
        carried = {
            env.task.manipulated.body_id,
            *(m.body(n).id for n in getattr(env.task, "particle_names", ())),
        }
        ignore = [
            m.geom(g).name for g in range(m.ngeom) if int(m.geom_bodyid[g]) in carried and m.geom(g).name
        ]
        return CollisionChecker(m, env.controller.handles, data=env.data, ignore_geoms=ignore)

    def fit_for(self, env, anchors: dict, plan: GraspPlan) -> tuple[np.ndarray, np.ndarray, GraspFit]:
        """The grasp pose (offset applied) and fit for the mug where it stands now.

        Reads the mug's collision parts in the live scene (privileged, like the anchors) and
        labels each as handle or body from the asset's part labels (unlabelled parts: body).
        """
        if not isinstance(plan, GraspPlan):  # the outside pinch (pour_pinch.PinchPlan)
            from keygen.expert.pour_pinch import fit_pinch_for  # deferred: pour_pinch imports this module

            return fit_pinch_for(env, anchors, plan)
        checker, is_handle = mug_clearance(env)
        grasp, rotation = grasp_pose(anchors, plan)
        fit = fit_grasp(checker, is_handle, grasp, rotation)
        if fit.clearance < FIT_FALLBACK:
            # Not even the best candidate gets through: fall back on the generator's opening.
            fit = GraspFit(0.0, pregrasp_opening(env.unwrapped.task.asset), fit.clearance)
        return grasp + fit.offset * rotation[:, 0], rotation, fit

    def grip_detected(self, obs: dict, info: dict, handle_before: np.ndarray, tcp_before: np.ndarray) -> bool:
        """Something between the jaws and, over the test lift, the handle rose with the hand.

        Compared with the tcp's measured rise (not the commanded one): the arm lags its target.
        """
        opening = float(obs["proprio"][9])
        tcp_rise = float(obs["proprio"][2] - tcp_before[2])
        rise = float(info["anchors"]["handle_grasp"][2] - handle_before[2])
        return opening > GRIP_MIN_OPENING and tcp_rise > 0.005 and rise > LIFT_FOLLOW * tcp_rise

    def _move(
        self, position: np.ndarray, rotation: np.ndarray, gripper: float, steps: int, phase: str
    ) -> Generator[Action, Step, Step]:
        """Cosine-timed straight line from the last commanded pose; returns the last (obs, info)."""
        self.phase = phase
        p0, r0 = self._pose
        step = None
        for f in cosine_profile(steps):
            p = p0 + f * (position - p0)
            r = interpolate_rotation(r0, rotation, float(f))
            step = yield target(p, r, gripper)
        self._pose = (np.asarray(position, float), np.asarray(rotation, float))
        return step

    # -- the state machine -------------------------------------------------------------------------
    def script(self, env, obs: dict, info: dict) -> Generator[Action, Step, None]:
        proprio = np.asarray(obs["proprio"], float)
        self._pose = (proprio[:3], rot6d_to_matrix(proprio[3:9]))
        self.grasp_attempts = 0
        anchors = info["anchors"]

        # plan: the grasp variant, fixed for the episode (a retry reuses it).
        self.phase = "plan"
        self.plan = plan = self.choose_plan(env, anchors)

        while True:
            self.grasp_attempts += 1
            # fit: offset and opening that keep the fingers clear of the mug on the way in.
            grasp, rotation, self.fit = self.fit_for(env, info["anchors"], plan)
            opening = self.fit.opening
            # pre-grasp: come down outside the handle, gripper at the fitted opening; let the arm settle.
            pre = pregrasp_pose(grasp, rotation)
            yield from self._move(pre + PREGRASP_RISE * UP, rotation, opening, 18, "pregrasp")
            yield from self._move(pre, rotation, opening, 6, "pregrasp")
            obs, info = yield from self._move(pre, rotation, opening, PREGRASP_DWELL, "pregrasp")
            # approach: straight in along the approach axis, slowly through the handle.
            yield from self._move(grasp - ENTRY * rotation[:, 2], rotation, opening, 8, "approach")
            yield from self._move(grasp, rotation, opening, 12, "approach")
            # grasp: close, then a short test lift; the guard reads the jaws and the handle anchor.
            obs, info = yield from self._move(grasp, rotation, CLOSED, 8, "grasp")
            tcp_before = np.asarray(obs["proprio"][:3], float).copy()
            handle_before = np.asarray(info["anchors"]["handle_grasp"], float).copy()
            obs, info = yield from self._move(grasp + TEST_LIFT * UP, rotation, CLOSED, 5, "grasp")
            if self.grip_detected(obs, info, handle_before, tcp_before):
                break
            if self.grasp_attempts >= 2:
                raise ExpertGaveUp("grasp_missed")
            # retry: set the mug down, back out and come again on the (possibly moved) handle. Jaws
            # that closed on nothing back out closed (opening them would swing the inner finger
            # into the body); jaws on the handle open only by a few millimetres.
            down = grasp - 0.002 * UP
            yield from self._move(down, rotation, CLOSED, 4, "retry")
            closed_on_nothing = float(obs["proprio"][9]) <= GRIP_MIN_OPENING
            release = CLOSED if closed_on_nothing else float(obs["proprio"][9]) + 0.004 / FINGER_MAX
            obs, info = yield from self._move(down, rotation, release, 3, "retry")
            yield from self._move(pregrasp_pose(down, rotation), rotation, release, 8, "retry")
            obs, info = yield from self._move(
                self._pose[0] + PREGRASP_RISE * UP, rotation, release, 5, "retry"
            )

        # lift: straight up.
        obs, info = yield from self._move(grasp + LIFT_HEIGHT * UP, rotation, CLOSED, 10, "lift")

        # transport: the lip over the box; the grasp's measured offset to the lip is kept.
        anchors = info["anchors"]
        tcp, tcp_rot = self._pose
        carried, carried_rot, _ = carry_pose(anchors, tcp, tcp_rot, plan.pour_turn, plan.lip(anchors))
        yield from self._move(carried, carried_rot, CLOSED, 25, "transport")
        obs, info = yield from self._move(carried, carried_rot, CLOSED, 4, "transport")

        # pour: tip about the lip, slowly once spheres can leave, then hold while they run out.
        anchors = info["anchors"]
        lip, direction = plan.lip(anchors)
        self.phase = "pour"
        for angle in tip_angles():
            position, rot = tipped_pose(anchors, carried, carried_rot, lip, -direction, angle)
            self._pose = (position, rot)
            obs, info = yield target(position, rot, CLOSED)

        # release: tip back, carry the mug over its start spot, set it down and open.
        yield from self._move(carried, carried_rot, CLOSED, 15, "release")
        down = grasp + SET_DOWN_CLEARANCE * UP
        yield from self._move(down + LIFT_HEIGHT * UP, tcp_rot, CLOSED, 20, "release")
        yield from self._move(down, tcp_rot, CLOSED, 10, "release")
        yield from self._move(down, tcp_rot, opening, 4, "release")

        # retreat: back out along the approach, then up.
        back = pregrasp_pose(down, tcp_rot)
        yield from self._move(back, tcp_rot, opening, 8, "retreat")
        yield from self._move(back + PREGRASP_RISE * UP, tcp_rot, opening, 6, "retreat")
        self.phase = "done"
