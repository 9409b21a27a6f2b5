"""Outside pinch of a mug handle's outer bar: the pour expert's grasp for handles too small for a finger.

The expert's main grasp (:mod:`keygen.expert.pour`) puts one 18 mm finger through the handle
opening; on small mugs (scale 0.7: most handle gaps) and on a few narrow-necked handles at scale 1
no candidate gets the finger through without touching the mug, and a touch on the body fails the
episode. The task asks only that both jaws be on handle parts and no finger on the body, so the
bar can be pinched from outside instead::

    approach   from outside the handle toward the mug's axis (along -radial), pitched downward
    closing    along the tangential axis, i.e. across the handle's plane: the handle lies within
               +-half its width of that plane, so fingers outside it never meet the handle
               whatever its style, and the pads squeeze the bar's two flat sides
    depth      the fingertips (5 mm past the tcp) reach a little past the bar, never to the body
    pour       over a lip 90 degrees from the handle, ``opening_center +- rim_radius * tangential``,
               tipping about the radial axis. Measured (test/hard/0.7, pinch forced, seed 0):
               over the usual lip opposite the handle (tipping about the closing axis) the mug
               turned about the closing axis and left the pads in 4 of 6 episodes (2 successes);
               over the side lip 8 of 12 succeeded. The side pour loads the one axis a line
               contact cannot hold, the bar's own: the mug swung 3-38 degrees (median ~11) about
               it while tipping, but stayed gripped (failures: 2 spheres sinking through the box
               floor, 1 unreachable pour, 1 finger on the body after a 135 degree transport turn)

Everything is computed from the anchors (handle_grasp, bottom_center, opening_center, pour_point)
and the mug's collision parts (:func:`keygen.expert.pour.mug_clearance`), never per instance.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from keygen.expert._pour_util import ReachChecker
from keygen.expert.clearance import FingerClearance
from keygen.expert.pour import (
    FIT_COST,
    FIT_SWEEP,
    GOOD_ENOUGH,
    POUR_TURNS,
    UP,
    mug_clearance,
    pose_chain,
    radial_axis,
)

# Approach pitches below the horizontal, tried in order (ties go to the earlier). The gripper's
# long side lies along the closing axis (horizontal here), so even a shallow pitch keeps the hand
# over the table; steeper pitches bring the hand over a handle that points away from the robot. The
# side pour rolls the hand 130 degrees about the radial axis, which swings its back (up by
# sin(pitch) at the grasp) down by 0.64 sin(pitch): shallow pitches keep the wrist off the table.
PINCH_PITCHES = tuple(np.deg2rad(d) for d in (15.0, 25.0, 35.0, 55.0))
# The pour is not planned any higher than the finger-through one's: spheres falling from 3 cm
# higher (1.3 instead of 1.1 m/s) sank through the box's soft 6 mm floor (test/hard/0.7 object 8:
# all 12 ended inside the floor, at table height), failing 4 of 7 episodes planned that way.
# tcp past handle_grasp along the approach, deepest first: at 6 mm the fingertips reach 11 mm past
# the bar's centreline, past its inner face for bars up to ~16 mm deep (largest at scale 1.2: 15 mm),
# so the 25 mm pads cover the whole bar; shallower only where the body is near.
PINCH_DEPTHS = (0.006, 0.004, 0.002, 0.0, -0.002)
# Gripper openings (fraction of FINGER_MAX = 40 mm per finger), narrowest first: pads at 6-24 mm
# from the handle's plane (bars are 3-17 mm wide over scales 0.7-1.2).
PINCH_OPENINGS = np.arange(0.15, 0.601, 0.05)
# Wanted clearances on the way in: pads to handle (the arm tracks its target within a few mm while
# moving; a pad grazing the bar only nudges the mug) and fingers to body (a touch fails the task).
SIDE_WANTED = 0.004  # m
BODY_WANTED = 0.006  # m
# The pinch replaces the finger-through grasp only when the latter's best fit overlaps the mug by
# more than this (the finger then pushes the mug on its way in). Measured (hard, seed 0, about one
# episode per instance): finger-through with fits of -0.7 to 0 mm succeeded (train 4, 20, 22 at
# scale 1), below -1 mm it failed on 9 of 11 instances (train 8, 19 at scale 1, 7 of 8 at scale
# 0.7), where the pinch, forced, succeeded in 14 of 20 episodes (test at 0.7; six train at 1).
PINCH_SWITCH = -0.001  # m
# A pinched bar turns freely about its own (vertical) axis: a line contact has no lever against it.
# Turning the mug about world z during transport loads exactly that axis (a 135 degree turn let test
# object 10 at scale 0.7 swing 23 degrees in the grip, and a finger then met the body), so turns cost
# five times more than for the finger-through grasp.
PINCH_TURN_COST = 0.05  # per rad


@dataclass(frozen=True)
class PinchPlan:
    """The outside pinch, fixed for the episode: signs relative to the anchors' directions."""

    closing_sign: float  # +1: tcp y along tangential = UP x radial; -1: the jaws swapped
    lip_side: float  # +1: pour over the lip at +tangential; -1: at -tangential
    pour_turn: float  # rad about world z applied to the mug during transport
    cost: float
    pitch: float = PINCH_PITCHES[0]

    def lip(self, anchors: dict) -> tuple[np.ndarray, np.ndarray]:
        """The side lip and its horizontal direction from the mug's axis."""
        return side_lip(anchors, self.lip_side)


@dataclass(frozen=True)
class PinchFit:
    """Depth and opening of the pinch, fixed before the approach, with the clearances they leave."""

    depth: float  # m, tcp past handle_grasp along the approach
    opening: float  # gripper command while approaching
    side: float  # m, smallest finger-to-handle distance on the way in
    body: float  # m, smallest finger-to-body distance on the way in and with the jaws closed

    @property
    def margin(self) -> float:
        """m by which the wanted clearances are met (negative: missed by that much)."""
        return min(self.side - SIDE_WANTED, self.body - BODY_WANTED)


def tangential_axis(anchors: dict) -> np.ndarray:
    """Horizontal unit normal of the handle's plane: UP x radial."""
    return np.cross(UP, radial_axis(anchors))


def pinch_pose(
    anchors: dict, plan: PinchPlan, depth: float = PINCH_DEPTHS[0]
) -> tuple[np.ndarray, np.ndarray]:
    """tcp position and rotation of the pinch: approach toward the mug's axis, jaws across its plane."""
    radial = radial_axis(anchors)
    approach = -np.cos(plan.pitch) * radial - np.sin(plan.pitch) * UP
    closing = plan.closing_sign * tangential_axis(anchors)  # horizontal, so normal to the approach
    rotation = np.column_stack([np.cross(closing, approach), closing, approach])
    return anchors["handle_grasp"] + depth * approach, rotation


def side_lip(anchors: dict, side: float) -> tuple[np.ndarray, np.ndarray]:
    """The rim point 90 degrees from the handle on ``side`` and its horizontal direction.

    Built in the mug's own (possibly tilted) frame: rim radius from pour_point, the handle plane's
    normal from the mug axis and the pour_point's direction.
    """
    centre = anchors["opening_center"]
    axis = centre - anchors["bottom_center"]
    axis = axis / np.linalg.norm(axis)
    back = anchors["pour_point"] - centre  # toward the lip opposite the handle
    normal = np.cross(axis, -back)
    normal = side * normal / np.linalg.norm(normal)
    lip = centre + np.linalg.norm(back) * normal
    direction = np.array([normal[0], normal[1], 0.0])
    return lip, direction / np.linalg.norm(direction)


def fit_pinch(
    clearance: FingerClearance, is_handle: np.ndarray, grasp_point: np.ndarray, rotation: np.ndarray
) -> PinchFit:
    """The deepest depth, then narrowest opening, that meets the wanted clearances; else the best margin.

    ``is_handle`` (T,) marks the checker's handle targets. The body distance also counts the
    closed jaws at the grasp (opening 0: the pads at their innermost), where the tips stay put
    but sweep toward the handle's plane, near which the body bulges out most.
    """
    best = None
    for depth in PINCH_DEPTHS:
        at = grasp_point + depth * rotation[:, 2]
        poses = [(at - s * rotation[:, 2], rotation) for s in FIT_SWEEP]
        closed = clearance.distances(at, rotation, 0.0)  # (T,)
        closed_body = closed[~is_handle].min(initial=np.inf)
        for opening in PINCH_OPENINGS:
            dist = clearance.sweep(poses, float(opening))  # (T,)
            side = dist[is_handle].min(initial=np.inf)
            body = min(dist[~is_handle].min(initial=np.inf), closed_body)
            fit = PinchFit(float(depth), float(opening), float(side), float(body))
            if fit.margin >= 0.0:
                return fit
            if best is None or fit.margin > best.margin + 1e-9:
                best = fit
    return best


def fit_pinch_for(env, anchors: dict, plan: PinchPlan) -> tuple[np.ndarray, np.ndarray, PinchFit]:
    """The pinch pose (depth applied) and its fit for the mug where it stands now."""
    checker, is_handle = mug_clearance(env)
    _, rotation = pinch_pose(anchors, plan, 0.0)
    fit = fit_pinch(checker, is_handle, anchors["handle_grasp"], rotation)
    return anchors["handle_grasp"] + fit.depth * rotation[:, 2], rotation, fit


def planned_pinch_poses(anchors: dict, plan: PinchPlan, depth: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """The chain of tcp poses the script will command for the pinch ``plan`` (rigid grasp assumed)."""
    grasp, rotation = pinch_pose(anchors, plan, depth)
    return pose_chain(anchors, grasp, rotation, plan.pour_turn, plan.lip(anchors))


def _pitch_fits(env, anchors: dict) -> dict[float, PinchFit]:
    """The pinch fit at each pitch (the fit does not depend on the jaw order, lip or turn)."""
    return {
        pitch: fit_pinch_for(env, anchors, PinchPlan(1.0, 1.0, 0.0, 0.0, pitch))[2] for pitch in PINCH_PITCHES
    }


def _variant_cost(
    anchors: dict, probe: PinchPlan, fit: PinchFit, reach: ReachChecker, checker, bound: float
) -> float:
    """Planned cost of one variant; a partial sum >= ``bound`` once it is sure to exceed it."""
    extra = PINCH_TURN_COST * abs(probe.pour_turn) + FIT_COST * max(-fit.margin, 0.0)
    poses = planned_pinch_poses(anchors, probe, fit.depth)
    return reach.path_cost(poses, bound - extra, checker) + extra


def _probes(fits: dict[float, PinchFit], turn: float):
    """The variants of one transport turn, each with its pitch's fit, in the search order."""
    for pitch, fit in fits.items():
        for closing_sign in (1.0, -1.0):
            for lip_side in (1.0, -1.0):
                yield PinchPlan(closing_sign, lip_side, turn, 0.0, pitch), fit


def choose_pinch(env, anchors: dict, reach: ReachChecker, checker) -> PinchPlan:
    """The pinch variant (pitch, jaw order, lip side, turn) the arm reaches at the lowest cost.

    Cost: the reach and arm-versus-scene cost of the planned pose chain, a small cost per radian
    of turn, and FIT_COST per m by which the pitch's fit misses the wanted clearances.
    """
    fits = _pitch_fits(env, anchors)
    best = None
    for turn in POUR_TURNS:
        for probe, fit in _probes(fits, turn):
            bound = np.inf if best is None else best.cost
            cost = _variant_cost(anchors, probe, fit, reach, checker, bound)
            if best is None or cost < best.cost - 1e-9:  # ties go to the earlier variant
                best = replace(probe, cost=cost)
        if best.cost < GOOD_ENOUGH:
            break
    return best


def pinch_variants(env, anchors: dict, reach: ReachChecker, checker) -> list[PinchPlan]:
    """Every pinch variant with its full planned cost, in :func:`choose_pinch`'s search order.

    For analysis (``benchmarks/pour_expert_plans.py``): the expert itself stops at the first turn
    that offers a variant under GOOD_ENOUGH, and stops summing a variant once it is out-costed.
    """
    fits = _pitch_fits(env, anchors)
    return [
        replace(probe, cost=_variant_cost(anchors, probe, fit, reach, checker, np.inf))
        for turn in POUR_TURNS
        for probe, fit in _probes(fits, turn)
    ]
