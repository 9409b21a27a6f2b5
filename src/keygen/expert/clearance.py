"""Finger clearance: how far the gripper's fingers stay from an object for a free-floating tcp pose.

The grasp of a thin part (a mug's handle, a knife's handle) is decided by millimetres between
the fingers and the rest of the object, and by nothing else of the arm. :class:`FingerClearance`
answers "at this tcp pose and finger opening, how close does any finger geom come to these
object geoms?" with MuJoCo's exact signed distance (``mj_geomDistance``) on a private copy of
the scene, without solving IK: the finger geoms' poses are rigid in the tcp frame up to their
slide along the closing axis, so they are placed directly and the rest of the robot is ignored.
The experts use it to choose, among anchor-derived candidates, the grasp opening and offset
that keep the fingers farthest from the object while they move in along the approach.

The live simulation is never touched; objects keep the pose they had in ``data`` when the
checker was built (or last :meth:`FingerClearance.sync`-ed).
"""

from __future__ import annotations

import copy
from collections.abc import Iterable, Sequence

import mujoco
import numpy as np

from keygen.errors import InvalidParameterError
from keygen.sim.robot import FINGER_MAX, RobotHandles

DISTMAX = 0.05  # m: distances beyond this are reported as DISTMAX (nothing nearby)


def collision_geoms_of_body(model: mujoco.MjModel, body_id: int) -> np.ndarray:
    """Ids of the geoms of a body that take part in collisions (visual-only geoms left out).

    A visual mesh's convex hull would close a mug handle's opening: only the collision parts
    describe the shape the fingers meet.
    """
    ids = np.flatnonzero(model.geom_bodyid == body_id)
    return ids[(model.geom_contype[ids] != 0) | (model.geom_conaffinity[ids] != 0)]


class FingerClearance:
    """Smallest signed distance (m) from the finger and pad geoms to ``target_geoms``.

    Args:
        model: the compiled scene (with the robot of ``handles``).
        data: the live state to copy (object poses); only read.
        handles: the robot's handles (finger joints, geoms, tcp site).
        target_geoms: geom ids of the object(s) the fingers must clear.
    """

    def __init__(
        self, model: mujoco.MjModel, data: mujoco.MjData, handles: RobotHandles, target_geoms: Iterable[int]
    ) -> None:
        self.model = copy.copy(model)
        self.data = mujoco.MjData(self.model)
        self.targets = np.array(sorted({int(g) for g in target_geoms}), dtype=int)
        if len(self.targets) == 0 or np.any(self.targets < 0) or np.any(self.targets >= model.ngeom):
            raise InvalidParameterError(
                f"target_geoms must be geom ids of the scene (0..{model.ngeom - 1}), "
                f"got {self.targets.tolist()}; pass the collision geoms of the object the fingers must clear"
            )
        try:
            self._fingers = np.array([model.geom(n).id for n in handles.finger_geoms], dtype=int)
            finger_joints = [model.joint(n) for n in handles.finger_joints]
            site = model.site(handles.tcp_site).id
        except KeyError as err:
            raise InvalidParameterError(
                f"the model lacks the robot's fingers or tcp ({err}); pass the handles of this scene's robot"
            ) from err
        # Finger geom poses in the tcp frame with the fingers closed, and each geom's slide axis.
        d = self.data
        d.qpos[:] = data.qpos
        for j in finger_joints:
            d.qpos[j.qposadr[0]] = 0.0
        mujoco.mj_kinematics(self.model, d)
        tcp_pos, tcp_rot = d.site_xpos[site].copy(), d.site_xmat[site].reshape(3, 3).copy()
        joint_of_body = {int(self.model.jnt_bodyid[j.id]): j.id for j in finger_joints}
        self._local_pos = np.empty((len(self._fingers), 3))  # (F, 3) tcp frame, closed
        self._local_rot = np.empty((len(self._fingers), 3, 3))  # (F, 3, 3)
        self._slide = np.empty((len(self._fingers), 3))  # (F, 3) unit slide direction, tcp frame
        for i, g in enumerate(self._fingers):
            body = int(self.model.geom_bodyid[g])
            if body not in joint_of_body:
                raise InvalidParameterError(
                    f"finger geom {model.geom(int(g)).name!r} is not on a finger body"
                )
            self._local_pos[i] = tcp_rot.T @ (d.geom_xpos[g] - tcp_pos)
            self._local_rot[i] = tcp_rot.T @ d.geom_xmat[g].reshape(3, 3)
            self._slide[i] = tcp_rot.T @ d.xaxis[joint_of_body[body]]
        self._fromto = np.zeros(6)
        self.sync(data)

    def sync(self, data: mujoco.MjData) -> None:
        """Copy the objects' current poses from live ``data``."""
        self.data.qpos[:] = data.qpos
        mujoco.mj_kinematics(self.model, self.data)

    def distances(self, tcp_pos: np.ndarray, tcp_rot: np.ndarray, opening: float) -> np.ndarray:
        """(T,) smallest signed distance (m, negative: penetration) of any finger geom to each target.

        ``opening`` is the gripper command as a fraction of the full stroke (each finger slides
        ``opening * FINGER_MAX`` from the middle). Capped at DISTMAX.
        """
        pos, rot = np.asarray(tcp_pos, float), np.asarray(tcp_rot, float)
        if pos.shape != (3,) or rot.shape != (3, 3):
            raise InvalidParameterError(
                f"tcp pose must be a position (3,) and rotation (3, 3), got {pos.shape} and {rot.shape}"
            )
        stroke = float(np.clip(opening, 0.0, 1.0)) * FINGER_MAX
        d = self.data
        out = np.full(len(self.targets), DISTMAX)
        for i, g in enumerate(self._fingers):
            d.geom_xpos[g] = pos + rot @ (self._local_pos[i] + stroke * self._slide[i])
            d.geom_xmat[g] = (rot @ self._local_rot[i]).ravel()
            for j, t in enumerate(self.targets):
                dist = mujoco.mj_geomDistance(self.model, d, int(g), int(t), DISTMAX, self._fromto)
                out[j] = min(out[j], dist)
        return out

    def distance(self, tcp_pos: np.ndarray, tcp_rot: np.ndarray, opening: float) -> float:
        """The smallest of :meth:`distances`: how close the fingers come to any target (m)."""
        return float(self.distances(tcp_pos, tcp_rot, opening).min())

    def sweep(self, poses: Sequence[tuple[np.ndarray, np.ndarray]], opening: float) -> np.ndarray:
        """(T,) per-target minimum of :meth:`distances` over a sequence of tcp poses at one opening."""
        if len(poses) == 0:
            raise InvalidParameterError("sweep needs at least one tcp pose")
        return np.min([self.distances(p, r, opening) for p, r in poses], axis=0)
