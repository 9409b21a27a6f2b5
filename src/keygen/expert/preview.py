"""Preview of the env's end-effector controller: where the arm's joints go for a list of tcp targets.

The environment turns each absolute tcp target into joint commands by differential IK
(:class:`keygen.sim.controller.EndEffectorController`): the joints follow the tcp along whatever
branch the local solutions lead to, and for large turns of the hand that branch may run into a
joint limit even though the goal pose has a comfortable IK solution elsewhere. An expert that
commits to a route of tcp targets therefore first *previews* it: :class:`ControllerPreview`
runs the very same controller class on a private robot-only model, kinematically (the servos
track the reference within a few milliradians, so the reference is the prediction), and reports
the joint-limit margin, the tracking error and, with a scene :class:`CollisionChecker`, whether
the arm touches the scene anywhere along the route. Choosing among anchor-derived candidate
routes by this preview is how the knife expert keeps its blade-down turn inside the joint limits.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from keygen.errors import InvalidParameterError
from keygen.geometry.rotations import rot6d_to_matrix, rotation_angle_between
from keygen.sim.controller import ACTION_DIM, EndEffectorController
from keygen.sim.robot import JOINT_LOWER, JOINT_UPPER, RobotHandles, add_robot

_LOWER, _UPPER = np.asarray(JOINT_LOWER), np.asarray(JOINT_UPPER)


@dataclass(frozen=True)
class PreviewResult:
    """What the controller would do with a route of targets."""

    q: np.ndarray  # (T, 7) reference joints at the end of each control period
    limit_margin: float  # rad: smallest distance of any joint to its limit along the route
    final_position_error: float  # m, tcp vs the last target after the last period
    final_rotation_error: float  # rad
    collisions: int  # control periods whose configuration touches the scene (0 without a checker)

    def cost(self, margin_wanted: float = 0.15) -> float:
        """0 for a route ending on target with margin to spare; grows with each shortfall.

        A centimetre short of the target costs as much as the whole margin shortfall: a blade
        that stops 1 cm off a slot a few millimetres wide fails for sure, a joint grazing its
        limit only may."""
        return (
            100.0 * self.final_position_error
            + 5.0 * self.final_rotation_error
            + 2.0 * max(margin_wanted - self.limit_margin, 0.0)
            + 1.0 * self.collisions
        )


class ControllerPreview:
    """Runs :class:`EndEffectorController` on a robot-only copy of the scene's robot, without physics.

    Args:
        handles: the scene robot's handles (names and base pose).
        **controller_kwargs: as for the env's controller (defaults match the env's).
    """

    def __init__(self, handles: RobotHandles, **controller_kwargs) -> None:
        spec = mujoco.MjSpec()
        add_robot(spec, base_pos=handles.base_pos, base_yaw=handles.base_yaw, name_prefix=handles.prefix)
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self.handles = handles
        self.controller = EndEffectorController(self.model, handles, **controller_kwargs)
        self._qadr = np.array([self.model.joint(n).qposadr[0] for n in handles.arm_joints])
        self._site = self.model.site(handles.tcp_site).id
        self._solves = (
            max(1, round(self.controller.control_dt / self.model.opt.timestep)) // self.controller.ik_every
        )

    def rollout(self, q0: np.ndarray, targets: Sequence[np.ndarray], checker=None) -> PreviewResult:
        """Reference joints after each of ``targets`` (T, 10) starting from arm joints ``q0`` (7,).

        ``checker``: a :class:`~keygen.expert.motion.CollisionChecker` of the scene (with held
        objects ignored); each period's configuration is checked against it.
        """
        q0 = np.asarray(q0, float)
        targets = np.asarray(targets, float)
        if q0.shape != (7,) or targets.ndim != 2 or targets.shape[1] != ACTION_DIM or len(targets) == 0:
            raise InvalidParameterError(
                f"rollout expects q0 (7,) and targets (T, {ACTION_DIM}) with T >= 1, "
                f"got {q0.shape} and {targets.shape}"
            )
        m, d = self.model, self.data
        d.qpos[self._qadr] = q0
        self.controller.reset(m, d)
        qs = np.empty((len(targets), 7))
        collisions = 0
        for t, target in enumerate(targets):
            self.controller.set_target(target)
            for _ in range(self._solves):
                self.controller.update_ctrl(m, d)
            qs[t] = self.controller.q_ref
            if checker is not None and not checker.is_free(qs[t]):
                collisions += 1
        d.qpos[self._qadr] = qs[-1]
        mujoco.mj_kinematics(m, d)
        position = d.site_xpos[self._site]
        rotation = d.site_xmat[self._site].reshape(3, 3)
        margin = float(np.min(np.minimum(qs - _LOWER, _UPPER - qs)))
        return PreviewResult(
            q=qs,
            limit_margin=margin,
            final_position_error=float(np.linalg.norm(position - targets[-1, :3])),
            final_rotation_error=float(rotation_angle_between(rotation, rot6d_to_matrix(targets[-1, 3:9]))),
            collisions=collisions,
        )
