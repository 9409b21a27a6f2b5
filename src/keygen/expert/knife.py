"""Scripted expert of the knife task: grasp the handle from above, turn the blade down, insert it.

The state machine reads only the privileged anchors (``info["anchors"]``) and the proprioception
(``obs["proprio"]``: tcp pose and gripper opening); every pose is derived from them, so the same
script serves every knife, yaw, face and scale. The one measure the anchors lack is where the
middle of the blade's width lies off its base-to-tip line (``center_offset``, non-zero on knives
whose tip sits off the centre line); it is read from the task (``env.unwrapped.task.blade``).

Phases (``self.phase``):

    plan        choose the grasp hand and pitch, the insertion side and the route of the
                blade-down turn by previewing the whole target sequence through the controller
                (joint limits, reach, scene collisions; :mod:`keygen.expert.knife_plan`)
    pre_grasp   above the grasp point, fingers open and across the handle
    approach    straight down to the handle
    close       close the gripper; guard: the opening stays above GRIP_MIN_OPENING
    lift        straight up; guard: the handle rose with the hand
                (a miss on either guard opens, backs up and retries once from pre_grasp, on fresh
                anchors; a second miss gives up with ``grasp_missed``)
    transport   over the slot while turning the blade down (fingers horizontal, across the slot)
                along the chosen route (or the motion module's joint-space plan)
    aim         re-aim on the knife's measured pose in the hand (it creeps while turning)
    insert      lower the blade into the slot, re-aiming on the way
    release     open the gripper
    retreat     back off along the approach axis, then up; wait for the knife to settle
"""

from __future__ import annotations

from collections.abc import Generator
from typing import Any

import numpy as np

from keygen.errors import InvalidParameterError
from keygen.expert.base import (
    CLOSED,
    OPEN,
    Action,
    Expert,
    ExpertGaveUp,
    Step,
    interpolate_rotation,
    smooth_fraction,
    target,
)
from keygen.expert.knife_geometry import (  # noqa: F401  (re-exported: the expert's geometry)
    AIM_TIP_HEIGHT,
    APPROACH_HEIGHT,
    FLOOR_CLEARANCE,
    GRASP_RETRIES,
    GRIP_MIN_OPENING,
    HOVER_TIP_HEIGHT,
    INSERT_SHARES,
    LIFT_FOLLOW_SHARE,
    LIFT_HEIGHT,
    PRE_GRASP_HEIGHT,
    PRE_INSERT_TIP_HEIGHT,
    RETREAT_BACK,
    RETREAT_UP,
    SETTLE_WAIT_STEPS,
    STEPS,
    Z,
    grasp_point,
    grasp_rotation,
    grasp_rotations,
    insert_approach,
    insert_pose,
    knife_in_hand,
)
from keygen.expert.knife_plan import (
    PLAN_CHOICES,
    KnifePlan,
    KnifePlanner,
    joint_space_move,
    transport_legs,
)
from keygen.expert.motion import CollisionChecker
from keygen.expert.preview import ControllerPreview
from keygen.geometry.rotations import rot6d_to_matrix, yaw_matrix


class KnifeExpert(Expert):
    """Grasp-turn-insert state machine of the knife task, parameterised by the anchors only."""

    task = "knife"

    def __init__(self, plan_choice: str = "cost") -> None:
        """``plan_choice``: ``cost`` (the least-cost plan) or ``first`` (the first good-enough plan in
        a fixed order, one plan family across episodes; see :mod:`keygen.expert.knife_plan`)."""
        super().__init__()
        if plan_choice not in PLAN_CHOICES:
            raise InvalidParameterError(f"plan_choice must be one of {PLAN_CHOICES}, got {plan_choice!r}")
        self.plan_choice = plan_choice
        self.grasp_attempts = 0
        self.plan: KnifePlan | None = None
        self.planner: str | None = None  # how the transport moved: the route, or joint_plan (line/rrt)
        self._preview: ControllerPreview | None = None
        self._planner: KnifePlanner | None = None

    def reset(self, env, obs: dict, info: dict) -> None:
        self.grasp_attempts = 0
        super().reset(env, obs, info)

    # -- planning ----------------------------------------------------------------------------------
    def choose_plan(self, env, obs: dict, anchors: dict, center_offset: float) -> KnifePlan:
        """Hand, insertion side and turn route, by previewing each candidate's targets through the
        controller from the arm's current joints (see :mod:`keygen.expert.knife_plan`)."""
        env = getattr(env, "unwrapped", env)
        handles = env.controller.handles
        if self._preview is None or self._preview.handles is not handles:
            self._preview = ControllerPreview(handles)
        checker = CollisionChecker(env.model, handles, data=env.data, ignore_geoms=self._knife_geoms(env))
        self._planner = KnifePlanner(
            env, self._preview, checker, self._knife_geoms(env), choice=self.plan_choice
        )
        q0 = np.array([env.data.qpos[env.model.joint(n).qposadr[0]] for n in handles.arm_joints])
        return self._planner.choose(anchors, center_offset, q0, self._tcp(obs))

    @staticmethod
    def _knife_geoms(env) -> list[str]:
        m = env.model
        knife = env.task.manipulated.body_id
        return [m.geom(g).name for g in range(m.ngeom) if int(m.geom_bodyid[g]) == knife and m.geom(g).name]

    # -- motion primitives -------------------------------------------------------------------------
    def _move(
        self, pos: np.ndarray, rot: np.ndarray, grip: float, steps: int, yaw: float | None = None
    ) -> Generator[Action, Step, Step]:
        """Straight-line tcp motion with cosine timing from the last commanded pose; returns the
        last (obs, info). The rotation follows the geodesic to ``rot``, or, with ``yaw``, turns by
        that angle (radians, any size, its sign chosen by the caller) about the world z axis."""
        p0, R0, g0 = self._pos, self._rot, self._grip
        pos = np.asarray(pos, float)
        if yaw is not None:
            rot = yaw_matrix(yaw) @ R0
        step = None
        for k in range(1, steps + 1):
            s = smooth_fraction(k / steps)
            R = yaw_matrix(s * yaw) @ R0 if yaw is not None else interpolate_rotation(R0, rot, s)
            step = yield target(p0 + s * (pos - p0), R, g0 + s * (grip - g0))
        self._pos, self._rot, self._grip = pos, rot, grip
        return step

    def _tcp(self, obs: dict) -> tuple[np.ndarray, np.ndarray]:
        p = np.asarray(obs["proprio"], np.float64)
        return p[:3], rot6d_to_matrix(p[3:9])

    # -- the script --------------------------------------------------------------------------------
    def script(self, env, obs: dict, info: dict) -> Generator[Action, Step, None]:
        self._pos, self._rot = self._tcp(obs)
        self._grip = OPEN
        task = getattr(env, "unwrapped", env).task
        # Privileged: the middle of the blade's width off its base-to-tip line (no anchor says it).
        center_offset = float(task.blade.center_offset)

        # plan: grasp hand and insertion side, fixed for the episode.
        self.phase = "plan"
        self.plan = self.choose_plan(env, obs, info["anchors"], center_offset)

        obs, info = yield from self._grasp(obs, info)

        # lift: straight up with the knife
        self.phase = "lift"
        start_z = float(info["anchors"]["handle_grasp"][2])
        hand_z = self._pos[2]
        obs, info = yield from self._move(
            np.array([*self._pos[:2], LIFT_HEIGHT]), self._rot, CLOSED, STEPS["lift"]
        )
        a = info["anchors"]
        if a["handle_grasp"][2] - start_z < LIFT_FOLLOW_SHARE * (LIFT_HEIGHT - hand_z):
            raise ExpertGaveUp("knife_slipped_on_lift")

        # transport: turn the blade down over the slot along the planned route; the joint-space
        # plan (IK, collision-checked joint path or RRT-Connect) when that route was chosen, and
        # the geodesic turn if it cannot be planned from where the arm really is.
        self.phase = "transport"
        self.approach = self.plan.approach
        tcp_pos, tcp_rot = self._tcp(obs)
        pre, blade_down = insert_pose(
            tcp_pos, tcp_rot, a, self.approach, -PRE_INSERT_TIP_HEIGHT, center_offset
        )
        hover = insert_pose(tcp_pos, tcp_rot, a, self.approach, -HOVER_TIP_HEIGHT, center_offset)
        route = self.plan.route
        if route == "joint_plan":
            env = getattr(env, "unwrapped", env)
            handles = env.controller.handles
            q_now = np.array([env.data.qpos[env.model.joint(n).qposadr[0]] for n in handles.arm_joints])
            checker = CollisionChecker(env.model, handles, data=env.data, ignore_geoms=self._knife_geoms(env))
            actions = joint_space_move(env.model, handles, checker, q_now, hover)
            if actions is None:
                route = "geodesic (no joint plan)"
            else:
                self.planner = "joint_plan"
                for action in actions:
                    obs, info = yield action
                self._pos, self._rot = hover
                obs, info = yield from self._move(*hover, CLOSED, STEPS["hold"])
        if route != "joint_plan":
            self.planner = route
            for leg in transport_legs(route.split(" ")[0], self._pos, self._rot, *hover):
                obs, info = yield from self._move(leg.position, leg.rotation, CLOSED, leg.steps, yaw=leg.yaw)
        # down: straight down from the hover to just above the slot.
        obs, info = yield from self._move(pre, blade_down, CLOSED, STEPS["insert"])

        # aim: the knife creeps in the fingers while turning; re-aim on its measured pose
        self.phase = "aim"
        for _ in range(2):
            pose = insert_pose(
                *self._tcp(obs), info["anchors"], self.approach, -AIM_TIP_HEIGHT, center_offset
            )
            obs, info = yield from self._move(*pose, CLOSED, STEPS["aim"])

        # insert: lower the tip to just above the slot's floor, re-aiming at each stage
        self.phase = "insert"
        depth = float(info["anchors"]["slot_depth"][0]) - FLOOR_CLEARANCE
        for share in INSERT_SHARES:
            pose = insert_pose(*self._tcp(obs), info["anchors"], self.approach, share * depth, center_offset)
            obs, info = yield from self._move(*pose, CLOSED, STEPS["insert"])
        obs, info = yield from self._move(self._pos, self._rot, CLOSED, STEPS["hold"])

        # release
        self.phase = "release"
        obs, info = yield from self._move(self._pos, self._rot, OPEN, STEPS["release"])

        # retreat: back along the approach axis (fingers slide off the handle), then up
        self.phase = "retreat"
        back = self._pos - RETREAT_BACK * self._rot[:, 2]
        obs, info = yield from self._move(back, self._rot, OPEN, STEPS["back"])
        obs, info = yield from self._move(back + RETREAT_UP * Z, self._rot, OPEN, STEPS["up"])
        for _ in range(SETTLE_WAIT_STEPS):
            if info["success"] or info["failure"]:
                return
            obs, info = yield target(self._pos, self._rot, OPEN)

    def _grasp(self, obs: dict, info: dict) -> Generator[Action, Step, Step]:
        """pre_grasp -> approach -> close, with one retry from pre_grasp on a miss."""
        while True:
            self.grasp_attempts += 1
            a = info["anchors"]  # fresh anchors each attempt: a miss may have pushed the knife
            pitch = self.plan.pitch
            grasp, down = grasp_point(a, pitch), grasp_rotation(a, self.plan.hand, pitch)

            # pre-grasp: above the grasp point, open, fingers across the handle
            self.phase = "pre_grasp"
            above = np.array([grasp[0], grasp[1], PRE_GRASP_HEIGHT])
            obs, info = yield from self._move(above, down, OPEN, STEPS["pre_grasp"])

            # approach: down to just above the handle, then slowly onto it
            self.phase = "approach"
            obs, info = yield from self._move(
                np.array([grasp[0], grasp[1], APPROACH_HEIGHT]), down, OPEN, STEPS["approach"]
            )
            obs, info = yield from self._move(grasp, down, OPEN, STEPS["descend"])

            # close; guard: something is between the fingers
            self.phase = "close"
            obs, info = yield from self._move(grasp, down, CLOSED, STEPS["close"])
            if self.grip_detected(obs, info):
                return obs, info
            if self.grasp_attempts > GRASP_RETRIES:
                raise ExpertGaveUp("grasp_missed")
            # miss: open and rise back to the pre-grasp height before trying again
            self.phase = "reopen"
            obs, info = yield from self._move(grasp, down, OPEN, STEPS["reopen"])
            obs, info = yield from self._move(above, down, OPEN, STEPS["approach"])

    def grip_detected(self, obs: dict, info: dict[str, Any]) -> bool:
        """The fingers stopped on something: the opening stays above an empty close's."""
        return float(obs["proprio"][9]) > GRIP_MIN_OPENING
