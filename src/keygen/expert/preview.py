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
    # The worst tcp error at the checkpoints (periods where a move ends and the hand must be on
    # its target: the grasp, the hover over the slot), m and rad; 0 without checkpoints.
    checkpoint_position_error: float = 0.0
    checkpoint_rotation_error: float = 0.0
    # Smallest singular value of the tcp Jacobian (6 x 7) at the checkpoints and the end: near 0
    # the arm is stretched to the edge of its reach, where a few millimetres of creep of the held
    # object put the next target out of reach (the differential IK then stalls centimetres off).
    manipulability: float = np.inf
    # The worst tcp position error over all periods (m): the reference lags a moving target by
    # a few centimetres at most; far more means the arm left its branch and swung through space.
    max_position_error: float = 0.0

    def cost(
        self, margin_wanted: float = 0.15, manipulability_wanted: float = 0.05, lag_allowed: float = 0.05
    ) -> float:
        """0 for a route ending on target with margin to spare; grows with each shortfall.

        A centimetre short of the target costs as much as the whole margin shortfall: a blade
        that stops 1 cm off a slot a few millimetres wide fails for sure, a joint grazing its
        limit only may. A checkpoint missed on the way counts like a missed end: a route that
        passes its hover 5 cm off (the arm stretched to its reach) and only then comes down onto
        the target does not do so with a knife that has meanwhile struck the block. A route
        passing near a singularity costs up to 0.5: there the joints the differential IK picks
        depend on millimetres of the target, and the held knife's creep in the fingers (measured
        up to 3 cm) sends the real arm down another branch than the previewed one. So does a
        route on which the tcp falls more than ``lag_allowed`` behind its target somewhere (the
        arm swinging through space to another branch: 17 cm measured, flinging the knife)."""
        return (
            100.0 * (self.final_position_error + self.checkpoint_position_error)
            + 5.0 * (self.final_rotation_error + self.checkpoint_rotation_error)
            + 2.0 * max(margin_wanted - self.limit_margin, 0.0)
            + 1.0 * self.collisions
            + 10.0 * max(manipulability_wanted - self.manipulability, 0.0)
            + 10.0 * max(self.max_position_error - lag_allowed, 0.0)
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
        self._dofs = np.array([self.model.joint(n).dofadr[0] for n in handles.arm_joints])
        self._jac_pos = np.zeros((3, self.model.nv))
        self._jac_rot = np.zeros((3, self.model.nv))
        self._solves = (
            max(1, round(self.controller.control_dt / self.model.opt.timestep)) // self.controller.ik_every
        )

    def rollout(
        self, q0: np.ndarray, targets: Sequence[np.ndarray], checker=None, checkpoints: Sequence[int] = ()
    ) -> PreviewResult:
        """Reference joints after each of ``targets`` (T, 10) starting from arm joints ``q0`` (7,).

        ``checker``: a :class:`~keygen.expert.motion.CollisionChecker` of the scene (with held
        objects ignored); each period's configuration is checked against it. ``checkpoints``:
        indices into ``targets`` after which the tcp must be on that target (their worst error
        is reported).
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
        checkpoints = {int(i) % len(targets) for i in checkpoints}
        qs = np.empty((len(targets), 7))
        collisions = 0
        check_pos = check_rot = worst = 0.0
        manipulability = np.inf
        for t, target in enumerate(targets):
            self.controller.set_target(target)
            for _ in range(self._solves):
                self.controller.update_ctrl(m, d)
            qs[t] = self.controller.q_ref
            if checker is not None and not checker.is_free(qs[t]):
                collisions += 1
            pos_err, rot_err = self._error(qs[t], target)
            worst = max(worst, pos_err)
            manipulability = min(manipulability, self._smallest_singular_value())
            if t in checkpoints:
                check_pos, check_rot = max(check_pos, pos_err), max(check_rot, rot_err)
        final_pos, final_rot = self._error(qs[-1], targets[-1])
        manipulability = min(manipulability, self._smallest_singular_value())
        margin = float(np.min(np.minimum(qs - _LOWER, _UPPER - qs)))
        return PreviewResult(
            q=qs,
            limit_margin=margin,
            final_position_error=final_pos,
            final_rotation_error=final_rot,
            collisions=collisions,
            checkpoint_position_error=check_pos,
            checkpoint_rotation_error=check_rot,
            manipulability=manipulability,
            max_position_error=worst,
        )

    def _smallest_singular_value(self) -> float:
        """Of the tcp Jacobian at the configuration last set by :meth:`_error`."""
        mujoco.mj_comPos(self.model, self.data)  # the Jacobian reads the dof axes it computes
        mujoco.mj_jacSite(self.model, self.data, self._jac_pos, self._jac_rot, self._site)
        jac = np.vstack([self._jac_pos, self._jac_rot])[:, self._dofs]  # (6, 7)
        return float(np.linalg.svd(jac, compute_uv=False)[-1])

    def _error(self, q: np.ndarray, target: np.ndarray) -> tuple[float, float]:
        """tcp position (m) and rotation (rad) error of arm joints ``q`` (7,) vs a (10,) target."""
        m, d = self.model, self.data
        d.qpos[self._qadr] = q
        mujoco.mj_kinematics(m, d)
        position = d.site_xpos[self._site]
        rotation = d.site_xmat[self._site].reshape(3, 3)
        return (
            float(np.linalg.norm(position - target[:3])),
            float(rotation_angle_between(rotation, rot6d_to_matrix(target[3:9]))),
        )
