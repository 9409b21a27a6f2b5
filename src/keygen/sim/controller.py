"""End-effector control: 10-number absolute targets to joint position commands by differential IK.

Action and proprioception share one layout (see the design notes), ``ACTION_DIM = 10``::

    [0:3]  tcp position in the world frame, metres
    [3:9]  tcp orientation as 6D: the first two COLUMNS of the rotation matrix (x axis, y axis)
    [9]    gripper: command in [0, 1] (0 = closed, 1 = open; values outside are clipped), the
           target of each finger's travel as a fraction of FINGER_MAX, squeezing with up to
           GRIP_FORCE; in proprioception the opening fraction (mean finger travel / FINGER_MAX)

Timeline of one control period (``control_dt = 0.1`` s, 10 Hz)::

    step(target) | IK  phys phys phys phys phys | IK  phys ... | ... 50 physics steps (2 ms)
                   ^ every ``ik_every`` physics steps: one QP from the reference configuration

The IK runs on a private, kinematics-only copy of the robot (same names, same base pose), so
the scene's free objects never enter the QP. It integrates a *reference* configuration
``q_ref``; the servos track ``q_ref`` (``data.ctrl``). Integrating the reference rather than the
measured joints keeps the servo's small tracking error from feeding back into the IK target.
The reference approaches the target exponentially (``time_constant``, 50 ms) within the joint
velocity limits, and the servos get (part of) its velocity as feedforward, so the arm follows it
with less lag than a plain position servo and without overshoot.
Call :meth:`EndEffectorController.reset` after any change to ``data.qpos`` outside the loop.
"""

from __future__ import annotations

import mink
import mujoco
import numpy as np
import qpsolvers

from keygen.errors import InvalidParameterError
from keygen.geometry.rotations import matrix_to_rot6d, rot6d_to_matrix
from keygen.sim.ik_step import DifferentialIKStep
from keygen.sim.robot import (
    FINGER_MAX,
    HOME_QPOS,
    JOINT_LOWER,
    JOINT_UPPER,
    JOINT_VELOCITY_LIMITS,
    RobotHandles,
    add_robot,
)

ACTION_DIM = 10
CONTROL_DT = 0.1  # seconds per action (10 Hz)
_SOLVER_PREFERENCE = ("daqp", "quadprog", "proxqp", "osqp")


def pick_solver(requested: str | None) -> str:
    available = qpsolvers.available_solvers
    if requested is not None:
        if requested not in available:
            raise InvalidParameterError(
                f"QP solver {requested!r} is not installed; available: {available}. "
                "Pass one of those or install the solver."
            )
        return requested
    for name in _SOLVER_PREFERENCE:
        if name in available:
            return name
    raise InvalidParameterError(
        f"no supported QP solver installed (looked for {_SOLVER_PREFERENCE}, found {available}); "
        "install daqp (pip install daqp)."
    )


def _build_ik_model(handles: RobotHandles) -> mujoco.MjModel:
    """A scene holding only this robot at the same base pose, with the same names."""
    spec = mujoco.MjSpec()
    add_robot(spec, base_pos=handles.base_pos, base_yaw=handles.base_yaw, name_prefix=handles.prefix)
    return spec.compile()


def validate_target(target10) -> np.ndarray:
    """``target10`` as a float (10,) array, or InvalidParameterError saying what is wrong."""
    target = np.asarray(target10, dtype=float)
    if target.shape != (ACTION_DIM,):
        raise InvalidParameterError(
            f"end-effector target must have shape ({ACTION_DIM},) = position (3) + 6D rotation (6) "
            f"+ gripper (1), got shape {target.shape}; pass one action at a time."
        )
    if not np.all(np.isfinite(target)):
        raise InvalidParameterError(
            f"end-effector target contains NaN or inf: {target.tolist()}; check the policy output."
        )
    return target


def proprioception(model: mujoco.MjModel, data: mujoco.MjData, handles: RobotHandles) -> np.ndarray:
    """(10,) current tcp position, 6D orientation and gripper opening fraction.

    Reads the site pose computed by the last ``mj_forward``/``mj_step`` (positions of the state
    before the step's integration, as MuJoCo stores them); call ``mj_kinematics`` first when the
    pose must match the very latest ``qpos``.
    """
    site = model.site(handles.tcp_site).id
    position = data.site_xpos[site].copy()  # (3,)
    rotation = data.site_xmat[site].reshape(3, 3)  # (3, 3)
    fingers = [data.qpos[model.joint(name).qposadr[0]] for name in handles.finger_joints]
    opening = float(np.clip(np.mean(fingers) / FINGER_MAX, 0.0, 1.0))
    return np.concatenate([position, matrix_to_rot6d(rotation), [opening]])


class EndEffectorController:
    """Turns absolute tcp targets into arm and gripper servo commands by differential IK (mink).

    Args:
        model: the compiled scene containing the robot described by ``handles``.
        handles: from :func:`keygen.sim.robot.add_robot`.
        ik_every: physics steps between IK solves (5 at dt = 2 ms is 100 Hz).
        solver: QP solver for ``mink.solve_ik``; default the first installed of daqp, quadprog,
            proxqp, osqp.
        posture_cost: weight of the pull toward HOME_QPOS in the arm's null space, relative to
            the tcp task (cost 1 per metre and per radian).
        lm_damping: Levenberg-Marquardt damping of the tcp task; keeps steps bounded near
            singularities and for unreachable targets.
        control_dt: seconds per action; ``step`` runs ``control_dt / timestep`` physics steps.
        velocity_feedforward: fraction (0..1) of the reference velocity fed to the servos. 1
            tracks fastest but its 100 Hz steps shake the hand, and a pinched object creeps by a
            few mm during long moves; 0.5 halves that creep and still settles within 3 mm in
            0.2 s; 0 creeps least and lags most.
        time_constant: seconds in which the reference closes 63% of the tcp error (the joint
            velocity limits cap it further for large errors).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        handles: RobotHandles,
        *,
        ik_every: int = 5,
        solver: str | None = None,
        posture_cost: float = 1e-3,
        lm_damping: float = 1e-3,
        control_dt: float = CONTROL_DT,
        velocity_feedforward: float = 0.5,
        time_constant: float = 0.05,
    ) -> None:
        if ik_every < 1:
            raise InvalidParameterError(f"ik_every must be >= 1 physics step, got {ik_every}")
        if not control_dt > 0:
            raise InvalidParameterError(f"control_dt must be positive seconds, got {control_dt}")
        if not time_constant > 0:
            raise InvalidParameterError(f"time_constant must be positive seconds, got {time_constant}")
        if not 0.0 <= velocity_feedforward <= 1.0:
            raise InvalidParameterError(f"velocity_feedforward must be in [0, 1], got {velocity_feedforward}")
        self.handles = handles
        self.ik_every = int(ik_every)
        self.control_dt = float(control_dt)
        self.velocity_feedforward = float(velocity_feedforward)
        self.solver = pick_solver(solver)
        self._bind_scene(model, handles)
        # The IK closes this fraction of the tcp error per solve: an exponential approach with
        # ``time_constant`` instead of a jump at full joint speed followed by an abrupt stop,
        # which the servos (and anything held) would overshoot.
        self._task_gain = min(1.0, self.ik_every * model.opt.timestep / time_constant)

        self._ik_model = _build_ik_model(handles)
        self._configuration = mink.Configuration(self._ik_model)
        self._ik_arm_qadr = np.array([self._ik_model.joint(n).qposadr[0] for n in handles.arm_joints])
        self._tcp_task = mink.FrameTask(
            handles.tcp_site,
            "site",
            position_cost=1.0,
            orientation_cost=1.0,
            lm_damping=lm_damping,
            gain=self._task_gain,
        )
        self._posture_task = mink.PostureTask(self._ik_model, cost=posture_cost)
        home = self._ik_model.qpos0.copy()
        home[self._ik_arm_qadr] = HOME_QPOS
        self._posture_task.set_target(home)
        self._limits = [
            mink.ConfigurationLimit(self._ik_model),
            mink.VelocityLimit(
                self._ik_model, dict(zip(handles.arm_joints, JOINT_VELOCITY_LIMITS, strict=True))
            ),
        ]
        # DAQP (the default) gets the same QP without mink's per-call bookkeeping (0.6 of the time);
        # other solvers go through mink.solve_ik.
        self._ik_step = (
            DifferentialIKStep(
                self._configuration,
                [self._tcp_task, self._posture_task],
                *self._limits,
                dt=self.ik_every * model.opt.timestep,
            )
            if self.solver == "daqp"
            else None
        )
        self._q_ik = self._ik_model.qpos0.copy()
        self._q_ref: np.ndarray | None = None
        self._target: np.ndarray | None = None

    def _bind_scene(self, model: mujoco.MjModel, handles: RobotHandles) -> None:
        """Resolve the robot's addresses in the scene model (fails early on a foreign model)."""
        try:
            self._arm_qadr = np.array([model.joint(n).qposadr[0] for n in handles.arm_joints])
            self._arm_act = np.array([model.actuator(n).id for n in handles.arm_actuators])
            self._gripper_act = model.actuator(handles.gripper_actuator).id
            model.site(handles.tcp_site)
        except KeyError as err:
            raise InvalidParameterError(
                f"the model lacks a robot element named with prefix {handles.prefix!r} ({err}); "
                "pass the handles returned by add_robot for this model."
            ) from err
        self._n_substeps = max(1, round(self.control_dt / model.opt.timestep))
        kp = model.actuator_gainprm[self._arm_act, 0]
        kv = -model.actuator_biasprm[self._arm_act, 2]
        self._lead_s = kv / kp  # (7,) seconds

    @property
    def q_ref(self) -> np.ndarray | None:
        """(7,) the reference arm configuration sent to the servos (None before the first reset)."""
        return None if self._q_ref is None else self._q_ref.copy()

    def reset(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Start the reference from the measured arm joints and drop any target."""
        # Clipped: contact can push a joint a hair past its limit, and mink warns on every solve
        # that starts outside the limits.
        self._q_ref = np.clip(data.qpos[self._arm_qadr], JOINT_LOWER, JOINT_UPPER)
        self._target = None
        data.ctrl[self._arm_act] = self._q_ref

    def set_target(self, target10) -> None:
        """Validate and store a (10,) target; the next IK solves track it."""
        target = validate_target(target10)
        rotation = rot6d_to_matrix(target[3:9])  # (3, 3), Gram-Schmidt of the two columns
        pose = mink.SE3.from_rotation_and_translation(mink.SO3.from_matrix(rotation), target[:3])
        self._tcp_task.set_target(pose)
        self._target = target

    def update_ctrl(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """One IK solve over ``ik_every`` physics steps; writes the arm and gripper commands."""
        if self._q_ref is None:
            self.reset(model, data)
        if self._target is None:
            data.ctrl[self._arm_act] = self._q_ref
            return
        dt = self.ik_every * model.opt.timestep
        self._q_ik[self._ik_arm_qadr] = self._q_ref
        self._configuration.update(self._q_ik)
        if self._ik_step is not None:
            velocity = self._ik_step.solve()
        else:
            velocity = mink.solve_ik(
                self._configuration,
                [self._tcp_task, self._posture_task],
                dt,
                self.solver,
                limits=self._limits,
            )
        self._configuration.integrate_inplace(velocity, dt)
        q_new = np.clip(self._configuration.q[self._ik_arm_qadr], JOINT_LOWER, JOINT_UPPER)
        velocity_ref = (q_new - self._q_ref) / dt  # (7,) rad/s over the coming IK interval
        self._q_ref = q_new
        # A position servo computes kp (ctrl - q) - kv qdot: it brakes any motion. Leading the
        # command by kv/kp * velocity_ref turns that into kp (q_ref - q) + kv (qdot_ref - qdot), a
        # PD that tracks the reference's velocity too, removing most of the servo lag.
        data.ctrl[self._arm_act] = self._q_ref + self.velocity_feedforward * self._lead_s * velocity_ref
        data.ctrl[self._gripper_act] = float(np.clip(self._target[9], 0.0, 1.0)) * FINGER_MAX

    def step(
        self, model: mujoco.MjModel, data: mujoco.MjData, target10, n_substeps: int | None = None
    ) -> None:
        """Track ``target10`` for one control period: ``n_substeps`` physics steps (default
        ``control_dt / timestep``), re-solving IK every ``ik_every`` of them."""
        self.set_target(target10)
        n = self._n_substeps if n_substeps is None else int(n_substeps)
        for i in range(n):
            if i % self.ik_every == 0:
                self.update_ctrl(model, data)
            mujoco.mj_step(model, data)

    def proprioception(self, model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
        """(10,) proprioception of this controller's robot; see :func:`proprioception`."""
        return proprioception(model, data, self.handles)
