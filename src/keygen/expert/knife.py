"""Scripted expert of the knife task: grasp the handle from above, turn the blade down, insert it.

The state machine reads only the privileged anchors (``info["anchors"]``) and the proprioception
(``obs["proprio"]``: tcp pose and gripper opening); every pose is derived from them, so the same
script serves every knife, yaw, face and scale. The one measure the anchors lack is where the
middle of the blade's width lies off its base-to-tip line (``center_offset``, non-zero on knives
whose tip sits off the centre line); it is read from the task (``env.unwrapped.task.blade``).

Phases (``self.phase``):

    pre_grasp   above the grasp point, fingers open and across the handle
    approach    straight down to the handle
    close       close the gripper; guard: the opening stays above GRIP_MIN_OPENING
    lift        straight up; guard: the handle rose with the hand
                (a miss on either guard opens, backs up and retries once from pre_grasp, on fresh
                anchors; a second miss gives up with ``grasp_missed``)
    transport   over the slot while turning the blade down (fingers horizontal, across the slot)
    aim         re-aim on the knife's measured pose in the hand (it creeps while turning)
    insert      lower the blade into the slot, re-aiming on the way
    release     open the gripper
    retreat     back off along the approach axis, then up; wait for the knife to settle
"""

from __future__ import annotations

from collections.abc import Generator
from typing import Any

import numpy as np

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
from keygen.geometry.rotations import (
    rot6d_to_matrix,
    yaw_matrix,
)

Z = np.array([0.0, 0.0, 1.0])

# Grasp: between the handle's grasp point and the blade base (less lever arm for the blade).
GRASP_TOWARD_BLADE = 0.4
PRE_GRASP_HEIGHT = 0.12  # metres above the table
APPROACH_HEIGHT = 0.04  # slow down from here to the handle
GRASP_BELOW_ANCHOR = 0.002  # the tcp goes this far below the grasp anchor ...
PAD_CLEARANCE_Z = 0.008  # ... but no lower: the pad tips stay clear of the table
LIFT_HEIGHT = 0.15
# Gripper opening (fraction of 80 mm) below which the fingers closed on nothing: a handle is
# several mm thick even at scale 0.5; 0.02 is 1.6 mm.
GRIP_MIN_OPENING = 0.02
# After the lift the grasp anchor must have risen by this share of the hand's rise.
LIFT_FOLLOW_SHARE = 0.5
GRASP_RETRIES = 1
PRE_INSERT_TIP_HEIGHT = 0.03  # metres above the slot's opening at the end of the transport
AIM_TIP_HEIGHT = 0.02
TRANSPORT_CLEARANCE = 0.05  # the transport's midpoint rises this much above both ends
FLOOR_CLEARANCE = 0.01  # the tip stops this far above the slot's floor
INSERT_SHARES = (0.35, 1.0)  # lowered in stages, re-aiming at each
# Insertion: prefer the approach pointing away from the robot, and against the blade on the table.
TIP_DIRECTION_WEIGHT = 0.5
RETREAT_BACK, RETREAT_UP = 0.08, 0.08
SETTLE_WAIT_STEPS = 12

# Control steps of each motion (10 Hz).
STEPS = {
    "pre_grasp": 15,
    "approach": 8,
    "descend": 8,
    "close": 6,
    "lift": 10,
    "reopen": 4,
    "transport": 12,
    "aim": 4,
    "insert": 12,
    "hold": 3,
    "release": 4,
    "back": 6,
    "up": 4,
}


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def horizontal(v: np.ndarray) -> np.ndarray:
    """The unit horizontal part of ``v``."""
    return unit(np.array([v[0], v[1], 0.0]))


def grasp_rotation(anchors: dict[str, np.ndarray]) -> np.ndarray:
    """tcp pointing down, fingers closing across the handle; of the two such hands the one whose
    x axis points away from the robot base (as at home), which keeps the wrist mid-range."""
    along = horizontal(anchors["handle_axis"])
    across = np.cross(Z, along)
    options = [np.column_stack([np.cross(s * across, -Z), s * across, -Z]) for s in (1.0, -1.0)]
    away = horizontal(anchors["handle_grasp"])
    return max(options, key=lambda R: R[:, 0] @ away)


def grasp_point(anchors: dict[str, np.ndarray]) -> np.ndarray:
    g = anchors["handle_grasp"] + GRASP_TOWARD_BLADE * (anchors["blade_base"] - anchors["handle_grasp"])
    g[2] = max(anchors["handle_grasp"][2] - GRASP_BELOW_ANCHOR, PAD_CLEARANCE_Z)
    return g


def insert_approach(anchors: dict[str, np.ndarray]) -> np.ndarray:
    """Horizontal tcp z at insertion: across the slot, away from the robot (reach), and against
    the blade's direction on the table: turning the blade down swings the fingers toward the
    butt, so the hand then turns less."""
    across = unit(np.cross(Z, anchors["slot_axis"]))
    outward = horizontal(anchors["slot_center_top"])
    tip_dir = horizontal(anchors["blade_axis"])
    return max((across, -across), key=lambda v: v @ outward - TIP_DIRECTION_WEIGHT * (v @ tip_dir))


def knife_in_hand(tcp_pos: np.ndarray, tcp_rot: np.ndarray, anchors: dict[str, np.ndarray]) -> dict:
    """The knife's anchors in the tcp frame (tip position; blade axis, edge, normal directions)."""
    axis = tcp_rot.T @ anchors["blade_axis"]
    edge = tcp_rot.T @ anchors["edge_direction"]
    edge = unit(edge - (edge @ axis) * axis)
    return {"tip": tcp_rot.T @ (anchors["blade_tip"] - tcp_pos), "frame": np.column_stack([axis, edge])}


def insert_pose(
    tcp_pos: np.ndarray,
    tcp_rot: np.ndarray,
    anchors: dict[str, np.ndarray],
    approach: np.ndarray,
    tip_depth: float,
    center_offset: float,
) -> tuple[np.ndarray, np.ndarray]:
    """tcp pose with the blade axis straight down, the blade plane along the slot, the blade's
    width centred on the slot and its tip ``tip_depth`` below the slot's opening (negative:
    above); of the two blade-down poses the one whose approach axis is nearer ``approach``."""
    h = knife_in_hand(tcp_pos, tcp_rot, anchors)
    axis_h, edge_h = h["frame"][:, 0], h["frame"][:, 1]
    in_hand = np.column_stack([axis_h, edge_h, np.cross(axis_h, edge_h)])
    slot = anchors["slot_axis"]
    options = [np.column_stack([-Z, s * slot, np.cross(-Z, s * slot)]) @ in_hand.T for s in (1.0, -1.0)]
    rot = max(options, key=lambda R: R[:, 2] @ approach)
    centre = center_offset * (rot @ edge_h)
    top = anchors["slot_center_top"]
    return top - tip_depth * Z - centre - rot @ h["tip"], rot


class KnifeExpert(Expert):
    """Grasp-turn-insert state machine of the knife task, parameterised by the anchors only."""

    task = "knife"

    def __init__(self) -> None:
        super().__init__()
        self.grasp_attempts = 0

    def reset(self, env, obs: dict, info: dict) -> None:
        self.grasp_attempts = 0
        super().reset(env, obs, info)

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

        # transport: over the slot while turning the blade down; the turn is half done at the
        # raised midpoint so that the blade never sweeps low over the block.
        self.phase = "transport"
        self.approach = insert_approach(a)
        tcp_pos, tcp_rot = self._tcp(obs)
        pre, blade_down = insert_pose(
            tcp_pos, tcp_rot, a, self.approach, -PRE_INSERT_TIP_HEIGHT, center_offset
        )
        mid = 0.5 * (self._pos + pre)
        mid[2] = max(self._pos[2], pre[2]) + TRANSPORT_CLEARANCE
        half_turned = interpolate_rotation(self._rot, blade_down, 0.5)
        obs, info = yield from self._move(mid, half_turned, CLOSED, STEPS["transport"])
        obs, info = yield from self._move(pre, blade_down, CLOSED, STEPS["transport"])

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
            grasp, down = grasp_point(a), grasp_rotation(a)

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
