"""One differential-IK step, the same QP as ``mink.solve_ik`` with its constant parts built once.

The controller solves this QP every 5 physics steps, and the knife expert's route preview
(:mod:`keygen.expert.preview`) tens of thousands of times per episode. ``mink.solve_ik`` rebuilds
everything on each call: the limit matrices (constant for hinge joints), a ``qpsolvers.Problem``,
the solver dispatch and a ``Solution``; that bookkeeping is about 40% of a solve. Here
the constant constraint matrix and the velocity bounds are built once and DAQP is called directly
with the arrays qpsolvers would pass it. The objective comes from mink's own task residuals,
summed in the order ``mink.solve_ik`` sums them, and the position bounds use the same
``mj_differentiatePos`` calls, so the step is the same floating-point computation, not an
approximation of it (tests/sim/test_ik_step.py compares the two on random configurations).
"""

from __future__ import annotations

from collections.abc import Sequence
from ctypes import c_int

import daqp
import mink
import mujoco
import numpy as np

from keygen.errors import InvalidParameterError

_NO_LOWER_BOUND = -1e30  # what qpsolvers passes DAQP for one-sided rows
_HINGE_OR_SLIDE = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))


class DifferentialIKStep:
    """Solves ``min_dq sum_i ||W_i (J_i dq + gain_i e_i)||^2 + mu ||dq||^2`` under the joint
    position limits (``mink.ConfigurationLimit``) and velocity limits (``mink.VelocityLimit``).

    Args:
        configuration: the mink configuration the tasks are evaluated at (updated by the caller).
        tasks: mink tasks with a weighted residual (``FrameTask``, ``PostureTask``, ...).
        position_limit: the ``mink.ConfigurationLimit`` of the model.
        velocity_limit: the ``mink.VelocityLimit`` of the model.
        dt: seconds per step (the velocity bounds are ``dt * v_max``).
        damping: the global Levenberg-Marquardt damping (``mink.solve_ik``'s default).
    """

    def __init__(
        self,
        configuration: mink.Configuration,
        tasks: Sequence[mink.Task],
        position_limit: mink.ConfigurationLimit,
        velocity_limit: mink.VelocityLimit,
        dt: float,
        damping: float = 1e-12,
    ) -> None:
        model = configuration.model
        if any(int(t) not in _HINGE_OR_SLIDE for t in model.jnt_type):
            # Ball and free joints make the position bounds configuration-dependent rows.
            raise InvalidParameterError("DifferentialIKStep supports hinge and slide joints only")
        if not dt > 0:
            raise InvalidParameterError(f"dt must be positive seconds, got {dt}")
        self.configuration = configuration
        self.tasks = list(tasks)
        self.dt = float(dt)
        self.damping = float(damping)
        self._model = model
        self._nv = model.nv
        self._position = position_limit
        # The rows mink stacks: position upper, position lower, velocity upper, velocity lower.
        position_rows = position_limit.compute_qp_inequalities(configuration, dt)
        velocity_rows = velocity_limit.compute_qp_inequalities(configuration, dt)
        self._G = np.vstack([position_rows.G, velocity_rows.G])
        self._h_velocity = velocity_rows.h
        self._blower = np.full(len(self._G), _NO_LOWER_BOUND)
        self._sense = np.zeros(len(self._G), dtype=c_int)
        self._delta_upper = np.empty(model.nv)
        self._delta_lower = np.empty(model.nv)

    def solve(self) -> np.ndarray:
        """The joint velocity (nv,) of one step from the configuration's current state."""
        jacobians, errors, mu = [], [], 0.0
        for task in self.tasks:
            weighted_jacobian, weighted_error, task_mu = task.compute_qp_residual(self.configuration)
            jacobians.append(weighted_jacobian)
            errors.append(weighted_error)
            mu += task_mu
        W = np.vstack(jacobians)
        H = W.T @ W
        c = -(np.concatenate(errors) @ W)
        H.flat[:: self._nv + 1] += self.damping + mu

        limit, q = self._position, self.configuration.q
        mujoco.mj_differentiatePos(self._model, self._delta_upper, 1.0, q, limit.upper)
        mujoco.mj_differentiatePos(self._model, self._delta_lower, 1.0, limit.lower, q)
        h = np.concatenate(
            [
                limit.gain * self._delta_upper[limit.indices],
                limit.gain * self._delta_lower[limit.indices],
                self._h_velocity,
            ]
        )
        x, _, exitflag, _ = daqp.solve(H, c, self._G, h, self._blower, self._sense)
        if exitflag <= 0:
            raise mink.NoSolutionFound("daqp")
        return x / self.dt
