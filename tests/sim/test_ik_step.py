"""DifferentialIKStep solves the QP of mink.solve_ik, to the last bit, without its per-call overhead."""

from __future__ import annotations

import mink
import mujoco
import numpy as np
import pytest

from keygen.errors import InvalidParameterError
from keygen.geometry.rotations import matrix_to_rot6d
from keygen.sim import robot
from keygen.sim.controller import EndEffectorController
from keygen.sim.ik_step import DifferentialIKStep


@pytest.fixture(scope="module")
def controller():
    spec = robot.recommended_options(mujoco.MjSpec())
    handles = robot.add_robot(spec)
    model = spec.compile()
    return EndEffectorController(model, handles)


def test_step_equals_mink_solve_ik_with_and_without_active_limits(controller):
    ctrl = controller
    assert ctrl._ik_step is not None  # daqp is installed with the project
    config, tasks = ctrl._configuration, [ctrl._tcp_task, ctrl._posture_task]
    lower, upper = np.array(robot.JOINT_LOWER), np.array(robot.JOINT_UPPER)
    rng = np.random.default_rng(0)
    at_velocity_limit = at_position_limit = unconstrained = 0
    for k in range(200):
        q = ctrl._ik_model.qpos0.copy()
        q[ctrl._ik_arm_qadr] = rng.uniform(lower, upper)
        if k % 4 == 0:  # one joint on its upper limit: the position rows bind
            q[ctrl._ik_arm_qadr[k % 7]] = upper[k % 7]
        elif k % 4 == 2:  # near home, where the posture task is nearly satisfied
            q[ctrl._ik_arm_qadr] = np.array(robot.HOME_QPOS) + rng.normal(0, 0.01, 7)
        config.update(q)
        if k % 2:  # a far target: the velocity bounds cap the step
            rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0]
            position = rng.uniform([0.2, -0.5, 0.0], [0.7, 0.5, 0.6])
        else:  # a target a few millimetres off: usually no bound is active
            site = ctrl._tcp_task.frame_name
            position = config.data.site(site).xpos + rng.normal(0, 0.002, 3)
            rotation = config.data.site(site).xmat.reshape(3, 3)
        target = np.concatenate([position, matrix_to_rot6d(rotation), [1]])
        ctrl.set_target(target)
        fast = ctrl._ik_step.solve()
        reference = mink.solve_ik(config, tasks, ctrl._ik_step.dt, "daqp", limits=ctrl._limits)
        np.testing.assert_allclose(fast, reference, rtol=0, atol=1e-12)
        dq = fast[ctrl._ik_arm_qadr] * ctrl._ik_step.dt
        at_velocity_limit += np.any(
            np.isclose(np.abs(dq), np.array(robot.JOINT_VELOCITY_LIMITS) * ctrl._ik_step.dt)
        )
        at_upper = np.isclose(q[ctrl._ik_arm_qadr] + dq, upper, atol=1e-9)
        at_position_limit += np.any(at_upper)
        unconstrained += not np.any(at_upper) and np.all(
            np.abs(dq) < 0.99 * np.array(robot.JOINT_VELOCITY_LIMITS) * ctrl._ik_step.dt
        )
    # The comparison covered steps where each kind of bound was active, not only the unconstrained case.
    assert at_velocity_limit > 20 and at_position_limit > 5 and unconstrained > 20


def test_ball_and_free_joints_are_refused():
    spec = mujoco.MjSpec()
    body = spec.worldbody.add_body(name="b")
    body.add_freejoint()
    body.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.1, 0, 0])
    model = spec.compile()
    config = mink.Configuration(model)
    with pytest.raises(InvalidParameterError, match="hinge and slide"):
        DifferentialIKStep(config, [], mink.ConfigurationLimit(model), mink.VelocityLimit(model, {}), 0.01)
