"""Scripted expert for bowl stacking: pick bowl A by its rim and set it down inside bowl B.

The grasp is top-down on A's rim wall: the tcp z axis points straight down and the finger closing
axis lies along the rim's radial direction, so one finger goes inside the bowl and one outside.
Where on the rim: always its far side from the robot (world +x), at the height and radius of the
``rim_grasp`` anchor. A round bowl's yaw cannot be seen, so grasping at ``rim_grasp`` itself (a
point fixed in the bowl's frame) would put the hand at a random place on the rim in the ``hard``
setting, and demonstrations would disagree for no visible reason; the far side is what ``easy``
(yaw 0) already does. This assumes a round rim, as every generated bowl has.
The jaws are symmetric, so the closing axis may point either way along the radius: the expert
takes the sign that needs the least wrist turn from the current hand pose, which keeps joint 7
away from its limits.

Everything is computed from the privileged anchors in ``info["anchors"]`` (A: ``rim_grasp``,
``opening_center``, ``bottom_center``, ``rim_radius``; B: ``base_opening_center``,
``base_inner_bottom_center``, ``base_rim_radius``) and the proprioception; nothing is read
from ``env.unwrapped``. Since the anchors follow A's body every step, the hand-to-bowl transform
after the grasp is measured, not assumed, and the placement compensates for how A sits in the hand.

Phases: pre-grasp, approach, grasp (guarded, one retry), lift, transport, lower (guarded), release,
retreat, settle.
"""

from __future__ import annotations

from collections.abc import Generator

import numpy as np

from keygen.expert.base import Action, Expert, ExpertGaveUp, Step, smooth_fraction, target
from keygen.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle, rot6d_to_matrix

UP = np.array([0.0, 0.0, 1.0])

# Motion limits of the interpolated tcp path (per 0.1 s control step).
MAX_STEP_M = 0.025  # 0.25 m/s
MAX_STEP_RAD = np.deg2rad(12.0)
MIN_STEPS = 3

# Gripper.
APPROACH_OPENING = 0.6  # 48 mm between the jaws: room for a <= 10 mm wall, clear of bowl B
RELEASE_OPENING = 1.0  # wide: a released rim must not rub on either finger on the way out
CLOSE_STEPS = 5
# Opening fraction (mean finger travel / 40 mm) above which something is between the fingers:
# the thinnest rim wall (3 mm) leaves ~0.04; an empty hand closes to ~0.
GRIP_MIN_OPENING = 0.02
# The bowl must follow the hand during the guard lift: at least this fraction of the lift.
GRIP_FOLLOW_FRACTION = 0.5
GUARD_LIFT = 0.02  # m

# Geometry margins.
# tcp this far below the rim_grasp anchor: the pads (tcp - 5 mm to tcp + 20 mm) then cover more of
# the wall, which resists the bowl's swing in the hand better
GRASP_DEPTH = 0.006
PREGRASP_HEIGHT = 0.10  # above the grasp point
CLEARANCE_OVER_B = 0.04  # A's bottom above B's rim while carried
PLACE_DROP = 0.01  # stop lowering with A's lowest point this far above B's inner bottom
BLOCKED_LAG = 0.006  # m: A's bottom this far above its commanded height means A rests on B
MAX_HELD_SLIP = 0.04  # m between the tcp and A's rim grasp point while carried
MAX_RECENTRE = 0.02  # m: largest sideways correction onto the released rim before retreating
SWING_SETTLE_STEPS = 3  # control steps to let A's swing in the hand die down after the lift
RETREAT_HEIGHT = 0.12
SETTLE_WAIT_STEPS = 40  # the episode's step limit ends it sooner if need be


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _horizontal(v: np.ndarray) -> np.ndarray:
    return np.array([v[0], v[1], 0.0])


def lowest_point_z(anchors: dict[str, np.ndarray]) -> float:
    """Height of bowl A's lowest point, bounded from its anchors.

    The bowl lies within the rim radius of its axis, so a bowl tilted by ``t`` reaches at most
    ``rim_radius * sin(t)`` below the lower of its bottom centre and opening centre.
    """
    axis = _unit(anchors["opening_center"] - anchors["bottom_center"])
    sin_tilt = float(np.hypot(axis[0], axis[1]))
    low = min(anchors["bottom_center"][2], anchors["opening_center"][2])
    return float(low - anchors["rim_radius"][0] * sin_tilt)


def rim_point(anchors: dict[str, np.ndarray], angle: float) -> np.ndarray:
    """The point of A's rim at ``angle`` about A's axis from ``rim_grasp`` (same height and radius)."""
    axis = _unit(anchors["opening_center"] - anchors["bottom_center"])
    offset = anchors["rim_grasp"] - anchors["opening_center"]
    height = float(offset @ axis)
    radial = offset - height * axis
    radius = float(np.linalg.norm(radial))
    e1 = radial / radius
    e2 = np.cross(axis, e1)
    return anchors["opening_center"] + height * axis + radius * (np.cos(angle) * e1 + np.sin(angle) * e2)


def far_side_angle(anchors: dict[str, np.ndarray]) -> float:
    """The rim angle (for :func:`rim_point`) whose radial direction points to world +x."""
    axis = _unit(anchors["opening_center"] - anchors["bottom_center"])
    offset = anchors["rim_grasp"] - anchors["opening_center"]
    e1 = _unit(offset - float(offset @ axis) * axis)
    e2 = np.cross(axis, e1)
    x = np.array([1.0, 0.0, 0.0])
    x = x - float(x @ axis) * axis
    return float(np.arctan2(x @ e2, x @ e1))


def grasp_rotation(radial: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Top-down tcp rotation closing along ``radial`` (either sign), the one nearest ``current``.

    Columns are the tcp axes in the world: z straight down, y along the rim radius, x = y cross z.
    """
    approach = -UP
    options = []
    for sign in (1.0, -1.0):
        closing = sign * _unit(_horizontal(radial))
        options.append(np.column_stack([np.cross(closing, approach), closing, approach]))
    return max(options, key=lambda R: float(np.trace(current.T @ R)))


class StackExpert(Expert):
    task = "stack"

    def __init__(self) -> None:
        super().__init__()
        self.attempts = 0
        self._rim_angle = 0.0

    # -- motion primitives ----------------------------------------------------------------------
    def _start(self, obs: dict, info: dict) -> None:
        p = np.asarray(obs["proprio"], dtype=np.float64)
        self._pos, self._rot, self._grip = p[:3].copy(), rot6d_to_matrix(p[3:9]), float(p[9])
        self._obs, self._info = obs, info

    def _move(
        self, pos: np.ndarray, rot: np.ndarray | None = None, grip: float | None = None, min_steps: int = 0
    ) -> Generator[Action, Step, None]:
        """Straight tcp line with cosine timing, rotation about one fixed axis, gripper ramped.

        The number of steps follows from the distance and the turn (speed limits above).
        """
        rot = self._rot if rot is None else rot
        grip = self._grip if grip is None else grip
        p0, r0, g0 = self._pos, self._rot, self._grip
        turn = matrix_to_axis_angle(rot @ r0.T)
        steps = max(
            MIN_STEPS,
            min_steps,
            int(np.ceil(np.linalg.norm(pos - p0) / MAX_STEP_M)),
            int(np.ceil(np.linalg.norm(turn) / MAX_STEP_RAD)),
        )
        for k in range(1, steps + 1):
            s = smooth_fraction(k / steps)
            r = axis_angle_to_matrix(s * turn) @ r0
            self._obs, self._info = yield target(p0 + s * (pos - p0), r, g0 + s * (grip - g0))
        self._pos, self._rot, self._grip = np.asarray(pos, np.float64), rot, grip

    def _hold(self, steps: int) -> Generator[Action, Step, None]:
        for _ in range(steps):
            self._obs, self._info = yield target(self._pos, self._rot, self._grip)

    @property
    def _anchors(self) -> dict[str, np.ndarray]:
        return self._info["anchors"]

    def _grip_point(self) -> np.ndarray:
        """Where on A's rim the fingers are (or go): follows A's body every step."""
        return rim_point(self._anchors, self._rim_angle)

    def _opening(self) -> float:
        return float(self._obs["proprio"][9])

    # -- guards ---------------------------------------------------------------------------------
    def grip_detected(self, held_before: np.ndarray) -> bool:
        """Something between the fingers, and A's rim rose with the hand during the guard lift.

        The rim point under the fingers is watched, not A's centre: a bowl lifted by one side
        tilts about its opposite foot at first, so its centre rises only about half as much.
        """
        rose = float(self._grip_point()[2] - held_before[2])
        return self._opening() > GRIP_MIN_OPENING and rose > GRIP_FOLLOW_FRACTION * GUARD_LIFT

    def _check_held(self) -> None:
        """Guard while carrying: the fingers still pinch something and A's rim is still at the tcp."""
        slip = float(np.linalg.norm(self._grip_point() - self._tcp()))
        if self._opening() < GRIP_MIN_OPENING or slip > MAX_HELD_SLIP:
            raise ExpertGaveUp("dropped")

    # -- the state machine ------------------------------------------------------------------------
    def script(self, env, obs: dict, info: dict) -> Generator[Action, Step, None]:
        self.attempts = 0
        self._start(obs, info)

        # grasp (with one retry): pre-grasp above the rim, approach down, close, guard lift
        while True:
            self.attempts += 1
            a = self._anchors
            self._rim_angle = far_side_angle(a)
            radial = self._grip_point() - a["opening_center"]
            rot = grasp_rotation(radial, self._rot)
            grasp = self._grip_point() - GRASP_DEPTH * UP
            self.phase = "pre_grasp"
            yield from self._move(grasp + PREGRASP_HEIGHT * UP, rot, APPROACH_OPENING)
            self.phase = "approach"
            yield from self._move(grasp, min_steps=6)
            self.phase = "grasp"
            yield from self._move(grasp, grip=0.0, min_steps=CLOSE_STEPS)
            held_before = self._grip_point()
            yield from self._move(grasp + GUARD_LIFT * UP, min_steps=3)
            if self.grip_detected(held_before):
                break
            # miss: open, back up to the pre-grasp height, and (once) try again from fresh anchors
            self.phase = "regrasp"
            yield from self._move(self._pos, grip=APPROACH_OPENING)
            yield from self._move(grasp + PREGRASP_HEIGHT * UP)
            if self.attempts >= 2:
                raise ExpertGaveUp("grasp_missed")

        # lift: held from one side, A swings about the grip into a tilt (10-45 deg, more for heavy,
        # wide bowls). Lift high enough for any such tilt to clear B's rim, wait for the swing to
        # die down, then measure where A's lowest point actually is and raise further if needed.
        self.phase = "lift"
        a = self._anchors
        height_a = float(a["opening_center"][2] - a["bottom_center"][2])
        radius_a = float(a["rim_radius"][0])
        rim_b = float(a["base_opening_center"][2])
        swing_drop = height_a + 1.5 * radius_a  # grip point to A's lowest point, tilts up to ~50 deg
        carry_z = self._pos[2] + max(0.05, rim_b + CLEARANCE_OVER_B + swing_drop - self._grip_point()[2])
        yield from self._move(np.array([self._pos[0], self._pos[1], carry_z]))
        yield from self._hold(SWING_SETTLE_STEPS)
        self._check_held()
        shortfall = rim_b + CLEARANCE_OVER_B - lowest_point_z(self._anchors)
        if shortfall > 0.0:
            yield from self._move(self._pos + shortfall * UP)

        # transport: A's bottom centre over B's centre at the carry height; the hand keeps its
        # orientation, so the measured hand-to-bottom offset stays valid
        self.phase = "transport"
        a = self._anchors
        tcp_to_bottom = a["bottom_center"] - self._tcp()
        over_b = _horizontal(a["base_opening_center"] - tcp_to_bottom) + self._pos[2] * UP
        yield from self._move(over_b)
        self._check_held()

        # lower: guarded descent until A's lowest point is just above B's inner bottom, or until A
        # lags the hand (it rests on B's wall)
        self.phase = "lower"
        a = self._anchors
        descent = lowest_point_z(a) - (a["base_inner_bottom_center"][2] + PLACE_DROP)
        yield from self._guarded_descent(self._pos - max(descent, 0.0) * UP, tcp_to_bottom)

        # release: open; A, tilted in the hand, swings back upright and moves its rim sideways
        self.phase = "release"
        yield from self._move(self._pos, grip=RELEASE_OPENING, min_steps=3)

        # retreat: first centre the fingers on the rim where it now is (a rim pressed against one
        # finger gets carried up by friction), then go straight up, clear of both bowls
        self.phase = "retreat"
        correction = _horizontal(self._grip_point() - self._pos)
        correction *= min(1.0, MAX_RECENTRE / max(float(np.linalg.norm(correction)), 1e-9))
        yield from self._move(self._pos + correction, min_steps=2)
        yield from self._move(self._pos + RETREAT_HEIGHT * UP, min_steps=5)

        # settle: wait (holding still) for the task to report success
        self.phase = "settle"
        for _ in range(SETTLE_WAIT_STEPS):
            if self._info.get("success"):
                return
            yield from self._hold(1)

    def _tcp(self) -> np.ndarray:
        return np.asarray(self._obs["proprio"][:3], np.float64).copy()

    def _guarded_descent(self, goal: np.ndarray, bottom_offset: np.ndarray) -> Generator[Action, Step, None]:
        """Lower step by step; stop early when A lags its commanded height (it rests on B)."""
        start = self._pos.copy()
        steps = max(MIN_STEPS, int(np.ceil(np.linalg.norm(goal - start) / (0.6 * MAX_STEP_M))))
        for k in range(1, steps + 1):
            s = smooth_fraction(k / steps)
            commanded = start + s * (goal - start)
            self._obs, self._info = yield target(commanded, self._rot, self._grip)
            self._pos = commanded
            lag = self._anchors["bottom_center"][2] - (commanded + bottom_offset)[2]
            if lag > BLOCKED_LAG:
                # A sits on B: command the pose where it actually is so the release does not push
                self._pos = self._tcp()
                return
