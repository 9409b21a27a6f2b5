"""Helpers for the pour expert: smooth tcp interpolation and a kinematic reach check.

The reach check solves a damped least-squares IK on a private, robot-only model (the same robot,
base pose and names as the scene's) so the expert can rank grasp variants before moving: a pose
that the arm reaches only at a joint limit, or only with the wrist near the table, is ranked low.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from keygen.expert.base import interpolate_rotation, smooth_fraction  # noqa: F401 (re-exported)
from keygen.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from keygen.sim.robot import HOME_QPOS, JOINT_LOWER, JOINT_UPPER, RobotHandles, add_robot

_LOWER, _UPPER = np.array(JOINT_LOWER), np.array(JOINT_UPPER)
WRIST_CLEARANCE = 0.06  # m: link 6/7 origins lower than this over the table count as a collision risk
LIMIT_MARGIN = 0.15  # rad: joints closer than this to a limit are penalised
COLLISION_COST = 1.0  # per planned pose (or segment) where the arm touches the scene
_DAMPING = 1e-3 * np.eye(6)  # damped least squares: J^T (J J^T + lambda I)^-1 e


def cosine_profile(steps: int) -> np.ndarray:
    """(steps,) interpolation fractions rising smoothly from ~0 to exactly 1 (zero speed at both ends)."""
    return np.array([smooth_fraction(k / steps) for k in range(1, steps + 1)])


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = np.asarray(axis, float)
    return axis_angle_to_matrix(axis / np.linalg.norm(axis) * angle)


@dataclass(frozen=True)
class ReachResult:
    """How well the arm reaches one tcp pose: residual errors, joint-limit margin, wrist height."""

    position_error: float  # m
    rotation_error: float  # rad
    limit_margin: float  # rad, smallest distance of any joint to its limit
    wrist_z: float  # m, lowest of the link 6, link 7 and hand origins
    qpos: np.ndarray

    def cost(self) -> float:
        """0 for a comfortable pose; grows with residual error, limit proximity and a low wrist."""
        return (
            10.0 * self.position_error
            + 1.0 * self.rotation_error
            + 2.0 * max(LIMIT_MARGIN - self.limit_margin, 0.0)
            + 10.0 * max(WRIST_CLEARANCE - self.wrist_z, 0.0)
        )


class ReachChecker:
    """Damped least-squares IK on a robot-only copy of the scene's robot."""

    def __init__(self, handles: RobotHandles) -> None:
        spec = mujoco.MjSpec()
        add_robot(spec, base_pos=handles.base_pos, base_yaw=handles.base_yaw, name_prefix=handles.prefix)
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self._site = self.model.site(handles.tcp_site).id
        self._qadr = np.array([self.model.joint(n).qposadr[0] for n in handles.arm_joints])
        self._dadr = np.array([self.model.joint(n).dofadr[0] for n in handles.arm_joints])
        p = handles.prefix
        self._wrist_bodies = [self.model.body(p + n).id for n in ("link6", "link7", "hand")]
        # Scratch arrays for the solve loop, allocated once (the expert runs ~130 solves per plan).
        self._jacp = np.zeros((3, self.model.nv))
        self._jacr = np.zeros((3, self.model.nv))
        self._jac = np.zeros((6, len(self._dadr)))

    def solve(
        self, position: np.ndarray, rotation: np.ndarray, q0: np.ndarray | None = None, iterations: int = 80
    ) -> ReachResult:
        """IK from ``q0`` (default the home posture); joints are clipped to their limits each step."""
        m, d = self.model, self.data
        q = np.array(HOME_QPOS if q0 is None else q0, float)
        jacp, jacr, jac = self._jacp, self._jacr, self._jac
        err = np.zeros(6)
        for _ in range(iterations):
            d.qpos[self._qadr] = q
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            err[:3] = position - d.site_xpos[self._site]
            err[3:] = _rotation_error(rotation, d.site_xmat[self._site].reshape(3, 3))
            if _norm3(err[:3]) < 1e-4 and _norm3(err[3:]) < 1e-3:
                break
            mujoco.mj_jacSite(m, d, jacp, jacr, self._site)
            jac[:3] = jacp[:, self._dadr]
            jac[3:] = jacr[:, self._dadr]
            step = jac.T @ np.linalg.solve(jac @ jac.T + _DAMPING, err)
            q = np.clip(q + np.clip(step, -0.3, 0.3), _LOWER, _UPPER)
        d.qpos[self._qadr] = q
        mujoco.mj_kinematics(m, d)
        err[:3] = position - d.site_xpos[self._site]
        err[3:] = matrix_to_axis_angle(rotation @ d.site_xmat[self._site].reshape(3, 3).T)
        return ReachResult(
            position_error=float(np.linalg.norm(err[:3])),
            rotation_error=float(np.linalg.norm(err[3:])),
            limit_margin=float(np.min(np.minimum(q - _LOWER, _UPPER - q))),
            wrist_z=float(min(d.xpos[b][2] for b in self._wrist_bodies)),
            qpos=q.copy(),
        )

    def path_cost(
        self,
        poses: list[tuple[np.ndarray, np.ndarray]],
        bound: float = np.inf,
        checker=None,
        q0: np.ndarray | None = None,
    ) -> float:
        """Summed cost of a chain of poses, each solved from the previous solution (as the arm moves).

        With a :class:`~keygen.expert.motion.CollisionChecker` (built on the scene, same robot
        names), each solution and the straight joint segment from the previous one (the path
        the arm takes between two nearby targets) is checked against the scene; each colliding
        pose or segment adds COLLISION_COST. Stops early (returning a partial sum >= ``bound``)
        once the sum reaches ``bound``. The first pose is solved from ``q0`` (default: home).
        """
        q, total = q0, 0.0
        for k, (position, rotation) in enumerate(poses):
            result = self.solve(position, rotation, q)
            total += result.cost()
            if checker is not None:
                free = checker.is_free(result.qpos)
                # The move to the first pose is planned on its own (from home, or from q0).
                if free and k > 0:
                    free = checker.segment_is_free(q, result.qpos, 0.05)
                total += 0.0 if free else COLLISION_COST
            q = result.qpos
            if total >= bound:
                break
        return total


def _rotation_error(goal: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Rotation vector-like error taking ``current`` toward ``goal`` (exact direction, sin-scaled size).

    Half the sum of column cross products: cheap, and a fine descent direction for the IK.
    Written out rather than three ``np.cross`` calls (whose argument handling cost ~10 % of a pour
    recording); the products, differences and sums are the same floating-point operations in the
    same order, so the result is bit-identical.
    """
    a, b = current, goal
    cross = np.empty((3, 3))  # row: component; column: which pair of columns
    cross[0] = a[1] * b[2] - a[2] * b[1]
    cross[1] = a[2] * b[0] - a[0] * b[2]
    cross[2] = a[0] * b[1] - a[1] * b[0]
    return 0.5 * (cross[:, 0] + cross[:, 1] + cross[:, 2])


def _norm3(v: np.ndarray) -> float:
    """Euclidean norm of a short vector (what np.linalg.norm computes for 1-D input, without its overhead)."""
    return math.sqrt(float(v @ v))
