"""Anchor geometry and motion constants of the knife expert (see :mod:`keygen.expert.knife`).

Pure functions of the anchors: the top-down grasp, the insertion pose with the blade straight
down along the slot, and how the knife sits in the hand. Shared by the state machine and by the
planner that previews its routes (:mod:`keygen.expert.knife_plan`).
"""

from __future__ import annotations

import numpy as np

Z = np.array([0.0, 0.0, 1.0])

# Grasp: between the handle's grasp point and the blade base (less lever arm for the blade).
GRASP_TOWARD_BLADE = 0.4
PRE_GRASP_HEIGHT = 0.12  # metres above the table
APPROACH_HEIGHT = 0.04  # slow down from here to the handle
GRASP_BELOW_ANCHOR = 0.002  # the tcp goes this far below the grasp anchor ...
PAD_CLEARANCE_Z = 0.008  # ... but no lower (unpitched hand): the pad tips stay clear of the table
# The fingertips reach this far past the tcp along the hand z; the pads are this wide (half, along
# the hand x): a hand pitched about its closing axis lowers one tip corner by the sum of both.
PAD_TIP_BEYOND_TCP = 0.005
PAD_HALF_WIDTH = 0.009
# A pitched hand's lower pad corner may come this much nearer the table than the upright tips (3 mm
# above it): every millimetre the hand stays higher is a millimetre less of a thin handle pinched.
CORNER_SLACK = 0.0015
# Pitches of the grasp about the closing axis (radians), tried when the upright grasp's insertion
# is out of comfortable reach: the hand then holds the knife at that angle, so with the blade
# straight down its approach axis points that much below the horizontal. A horizontal approach
# with the blade hanging below the hand folds the Panda's elbow and wrist against their limits
# (margins of 0-0.2 rad measured for long blades); 30 degrees down leaves 0.25-0.6 rad. A pitched
# hand stays higher over the table and pinches less of a thin handle: the smaller pitch first.
GRASP_PITCHES = (np.radians(20.0), np.radians(30.0))
LIFT_HEIGHT = 0.15
# Gripper opening (fraction of 80 mm) below which the fingers closed on nothing: a handle is
# several mm thick even at scale 0.5; 0.02 is 1.6 mm.
GRIP_MIN_OPENING = 0.02
# After the lift the grasp anchor must have risen by this share of the hand's rise.
LIFT_FOLLOW_SHARE = 0.5
GRASP_RETRIES = 1
PRE_INSERT_TIP_HEIGHT = 0.03  # metres above the slot's opening before the insertion
# The turn ends with the tip this high over the slot, then the blade comes straight down: a wide
# blade turning close to the block sweeps its heel over the block's top.
HOVER_TIP_HEIGHT = 0.08
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


def grasp_rotations(anchors: dict[str, np.ndarray]) -> list[np.ndarray]:
    """The two top-down hands closing across the handle (turned pi about the vertical from each
    other); the first has its x axis pointing away from the robot base, as at home."""
    along = horizontal(anchors["handle_axis"])
    across = np.cross(Z, along)
    options = [np.column_stack([np.cross(s * across, -Z), s * across, -Z]) for s in (1.0, -1.0)]
    away = horizontal(anchors["handle_grasp"])
    return sorted(options, key=lambda R: -(R[:, 0] @ away))


def grasp_rotation(anchors: dict[str, np.ndarray], hand: int = 0, pitch: float = 0.0) -> np.ndarray:
    """tcp pointing down, fingers closing across the handle; ``hand`` 0 is the one whose x axis
    points away from the robot base (as at home, the wrist mid-range), 1 the other. ``pitch``
    (radians) turns the hand about its closing axis (its y): the pads' planes stay the handle's
    sides, only the fingers come in at a slant along the handle."""
    c, s = np.cos(pitch), np.sin(pitch)
    about_y = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return grasp_rotations(anchors)[hand] @ about_y


def grasp_point(anchors: dict[str, np.ndarray], pitch: float = 0.0) -> np.ndarray:
    """Where the tcp closes on the handle; a pitched hand stays higher so that its lower pad
    corner keeps the unpitched hand's clearance above the table, less CORNER_SLACK."""
    g = anchors["handle_grasp"] + GRASP_TOWARD_BLADE * (anchors["blade_base"] - anchors["handle_grasp"])
    tilt_drop = PAD_TIP_BEYOND_TCP * (np.cos(pitch) - 1.0) + PAD_HALF_WIDTH * abs(np.sin(pitch))
    floor = PAD_CLEARANCE_Z + max(tilt_drop - CORNER_SLACK, 0.0)
    g[2] = max(anchors["handle_grasp"][2] - GRASP_BELOW_ANCHOR, floor)
    return g


def insertion_pitch(
    anchors: dict[str, np.ndarray], hand: int, approach: np.ndarray, center_offset: float, size: float
) -> float:
    """The grasp pitch of magnitude ``size`` whose blade-down insertion has the approach axis
    pointing below the horizontal (the hand above the blade, reaching forward and down)."""
    best, lowest = size, np.inf
    for pitch in (size, -size):
        grasp, rot = grasp_point(anchors, pitch), grasp_rotation(anchors, hand, pitch)
        _, insert_rot = insert_pose(grasp, rot, anchors, approach, 0.0, center_offset)
        if insert_rot[2, 2] < lowest:
            best, lowest = pitch, insert_rot[2, 2]
    return best


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
    above); of the two blade-down poses the one whose approach axis is nearer ``approach``.

    ``tcp_pos``, ``tcp_rot`` and ``anchors`` only fix how the knife sits in the hand: a planned
    grasp pose with the anchors before the grasp predicts the insertion as well as the measured
    pose in the hand does after it."""
    h = knife_in_hand(tcp_pos, tcp_rot, anchors)
    axis_h, edge_h = h["frame"][:, 0], h["frame"][:, 1]
    in_hand = np.column_stack([axis_h, edge_h, np.cross(axis_h, edge_h)])
    slot = anchors["slot_axis"]
    options = [np.column_stack([-Z, s * slot, np.cross(-Z, s * slot)]) @ in_hand.T for s in (1.0, -1.0)]
    rot = max(options, key=lambda R: R[:, 2] @ approach)
    centre = center_offset * (rot @ edge_h)
    top = anchors["slot_center_top"]
    return top - tip_depth * Z - centre - rot @ h["tip"], rot
