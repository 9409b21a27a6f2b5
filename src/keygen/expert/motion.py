"""Motion utilities for the scripted experts: IK, collision checking, joint-space planning, retiming.

The experts drive the env through absolute tcp targets (the action format). For moves where a
straight tcp line would sweep the arm through the table or a prop, they can plan in joint space
instead and feed the result back as tcp targets::

    plan = plan_to_pose(env.model, env.data, env.scene.robot, pos, rot, OPEN, ignore_geoms=held)
    for action in plan.actions:          # (T, 10), one per 10 Hz control period
        obs, ... = env.step(action)

Pipeline of :func:`plan_to_pose`: :func:`solve_ik` (several seeds, collision-free goal) ->
straight joint interpolation if :meth:`CollisionChecker.path_is_free`, else
:func:`plan_rrt_connect` with shortcut smoothing -> :func:`retime` (trapezoidal velocity profiles,
synchronised across joints, stopping at each waypoint) -> :func:`joint_path_to_actions` (forward
kinematics of every sample).

Everything here works on private copies (a robot-only kinematic model for IK/FK, a private
``MjData`` for collision queries), so the live simulation is never touched. Angles in radians,
lengths in metres, time in seconds.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple

import mink
import mujoco
import numpy as np

from keygen.errors import InvalidParameterError, KeyGenError
from keygen.geometry.rotations import matrix_to_rot6d, rotation_angle_between
from keygen.sim.controller import CONTROL_DT, pick_solver
from keygen.sim.robot import (
    FINGER_MAX,
    HOME_QPOS,
    JOINT_LOWER,
    JOINT_UPPER,
    JOINT_VELOCITY_LIMITS,
    ROBOT_CONAFFINITY,
    ROBOT_CONTYPE,
    RobotHandles,
    add_robot,
    robot_handles,
)

N_ARM = 7
Q_LOWER = np.asarray(JOINT_LOWER, dtype=float)
Q_UPPER = np.asarray(JOINT_UPPER, dtype=float)
# Planned motions run well inside the hardware limits: the end-effector controller that replays
# them lags a little, and a held object should not be flung about.
DEFAULT_VEL_LIMITS = 0.5 * np.asarray(JOINT_VELOCITY_LIMITS, dtype=float)  # rad/s
DEFAULT_ACC_LIMITS = np.full(N_ARM, 2.0)  # rad/s^2
# Samples and RRT nodes stay this far inside the joint limits, where mink's limit constraint
# and the servos' range clipping never bind.
_LIMIT_MARGIN = 0.01  # rad
_POLISH_ITERS = 10  # final IK iterations without the posture pull


class PlanningError(KeyGenError):
    """No motion could be planned; ``reason`` is a short machine-readable tag."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(f"{reason}: {message}")
        self.reason = reason


class PoseError(NamedTuple):
    position: float  # metres
    rotation: float  # radians


class IKResult(NamedTuple):
    q: np.ndarray  # (7,) arm joints
    ok: bool
    error: PoseError


# -- kinematics on a robot-only model ---------------------------------------------------------


class _Kinematics:
    """A robot-only model (same names and base pose as in the scene) with its own data."""

    def __init__(self, handles: RobotHandles) -> None:
        spec = mujoco.MjSpec()
        add_robot(spec, base_pos=handles.base_pos, base_yaw=handles.base_yaw, name_prefix=handles.prefix)
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self.arm_qadr = np.array([self.model.joint(n).qposadr[0] for n in handles.arm_joints])
        self.site = self.model.site(handles.tcp_site).id

    def fk(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """tcp position (3,) and rotation (3, 3) in the world for arm joints ``q``."""
        self.data.qpos[self.arm_qadr] = q
        mujoco.mj_kinematics(self.model, self.data)
        return self.data.site_xpos[self.site].copy(), self.data.site_xmat[self.site].reshape(3, 3).copy()


@lru_cache(maxsize=8)
def _kinematics(handles: RobotHandles) -> _Kinematics:
    return _Kinematics(handles)


def _check_model_has_robot(model: mujoco.MjModel, handles: RobotHandles) -> np.ndarray:
    """Arm qpos addresses of ``handles`` in ``model``, or InvalidParameterError."""
    try:
        model.site(handles.tcp_site)
        return np.array([model.joint(n).qposadr[0] for n in handles.arm_joints])
    except KeyError as err:
        raise InvalidParameterError(
            f"the model lacks a robot element named with prefix {handles.prefix!r} ({err}); "
            "pass the handles returned by add_robot for this model."
        ) from err


def _as_q(q, name: str) -> np.ndarray:
    arr = np.asarray(q, dtype=float)
    if arr.shape != (N_ARM,) or not np.all(np.isfinite(arr)):
        raise InvalidParameterError(f"{name} must be 7 finite arm joint angles (rad), got {q!r}")
    return arr


def _as_path(q_path, name: str, min_len: int = 1) -> np.ndarray:
    arr = np.asarray(q_path, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != N_ARM or arr.shape[0] < min_len or not np.all(np.isfinite(arr)):
        raise InvalidParameterError(
            f"{name} must be a finite (K, 7) array of arm configurations with K >= {min_len}, "
            f"got shape {arr.shape}"
        )
    return arr


def forward_kinematics(handles: RobotHandles, q) -> tuple[np.ndarray, np.ndarray]:
    """tcp position (3,) and rotation matrix (3, 3) in the world frame for arm joints ``q`` (7,)."""
    return _kinematics(handles).fk(_as_q(q, "q"))


# -- inverse kinematics -----------------------------------------------------------------------


def _pose_error(kin: _Kinematics, q: np.ndarray, pos: np.ndarray, rot: np.ndarray) -> PoseError:
    p, r = kin.fk(q)
    return PoseError(float(np.linalg.norm(p - pos)), float(rotation_angle_between(r, rot)))


def _ik_from_seed(
    kin: _Kinematics,
    config: mink.Configuration,
    task: mink.FrameTask,
    posture: mink.PostureTask,
    limits: list,
    solver: str,
    q0: np.ndarray,
    max_iters: int,
) -> np.ndarray:
    """Damped Gauss-Newton steps (mink QP with joint limits) from ``q0``; returns the last q."""
    q_full = kin.model.qpos0.copy()
    q_full[kin.arm_qadr] = q0
    config.update(q_full)
    posture.set_target(q_full)  # pulls the redundant direction toward the seed
    # The posture pull biases the solution by a fraction of a mm; the last iterations drop it
    # and polish the tcp error alone, from wherever the redundant direction has settled.
    tasks = [task, posture]
    for k in range(max_iters):
        if k >= max_iters - _POLISH_ITERS:
            tasks = [task]
        velocity = mink.solve_ik(config, tasks, 1.0, solver, damping=1e-6, limits=limits)
        # A step larger than ~0.3 rad leaves the linearisation far behind; shorten it instead.
        scale = min(1.0, 0.3 / max(float(np.max(np.abs(velocity))), 1e-12))
        config.integrate_inplace(velocity * scale, 1.0)
        if float(np.max(np.abs(velocity * scale))) < 1e-6:
            if len(tasks) == 1:
                break
            tasks = [task]  # converged with the posture pull: polish without it
    return np.clip(config.q[kin.arm_qadr], Q_LOWER, Q_UPPER)


def solve_ik(
    model: mujoco.MjModel,
    handles: RobotHandles,
    target_pos,
    target_rot,
    q_seed,
    *,
    n_random_seeds: int = 6,
    seed: int = 0,
    max_iters: int = 60,
    pos_tol: float = 1e-3,
    rot_tol: float = np.deg2rad(0.5),
    accept: Callable[[np.ndarray], bool] | None = None,
    solver: str | None = None,
) -> IKResult:
    """Arm joints placing the tcp at ``target_pos`` (3,) with rotation ``target_rot`` (3, 3).

    Tries the seeds ``q_seed``, HOME_QPOS, then ``n_random_seeds`` perturbations of both
    (normal, 0.5 rad, drawn from ``seed``), iterating mink's joint-limited IK to convergence
    from each, and stops at the first solution within ``pos_tol`` / ``rot_tol`` that ``accept``
    (e.g. :meth:`CollisionChecker.is_free`) accepts. Otherwise returns the solution with the
    smallest error and ``ok = False``. The result always lies within the joint limits.
    """
    _check_model_has_robot(model, handles)
    pos = np.asarray(target_pos, dtype=float)
    rot = np.asarray(target_rot, dtype=float)
    if (
        pos.shape != (3,)
        or rot.shape != (3, 3)
        or not (np.all(np.isfinite(pos)) and np.all(np.isfinite(rot)))
    ):
        raise InvalidParameterError(
            f"solve_ik expected a finite position (3,) and rotation matrix (3, 3), got shapes "
            f"{pos.shape} and {rot.shape}"
        )
    q_seed = np.clip(_as_q(q_seed, "q_seed"), Q_LOWER, Q_UPPER)
    kin = _kinematics(handles)
    config = mink.Configuration(kin.model)
    task = mink.FrameTask(
        handles.tcp_site, "site", position_cost=1.0, orientation_cost=1.0, gain=1.0, lm_damping=1e-2
    )
    task.set_target(mink.SE3.from_rotation_and_translation(mink.SO3.from_matrix(rot), pos))
    posture = mink.PostureTask(kin.model, cost=1e-2)
    limits = [mink.ConfigurationLimit(kin.model, gain=0.95)]
    chosen_solver = pick_solver(solver)

    rng = np.random.default_rng(seed)
    home = np.asarray(HOME_QPOS, dtype=float)
    seeds = [q_seed, home]
    for k in range(n_random_seeds):
        centre = q_seed if k % 2 == 0 else home
        seeds.append(np.clip(centre + rng.normal(0.0, 0.5, N_ARM), Q_LOWER + 0.05, Q_UPPER - 0.05))

    best: IKResult | None = None
    for q0 in seeds:
        q = _ik_from_seed(kin, config, task, posture, limits, chosen_solver, q0, max_iters)
        err = _pose_error(kin, q, pos, rot)
        ok = err.position <= pos_tol and err.rotation <= rot_tol
        if ok and (accept is None or accept(q)):
            return IKResult(q, True, err)
        if (
            best is None
            or err.position + 0.1 * err.rotation < best.error.position + 0.1 * best.error.rotation
        ):
            best = IKResult(q, False, err)
    return best


# -- collision checking -----------------------------------------------------------------------


class Contact(NamedTuple):
    robot_geom: str
    other_geom: str
    distance: float  # metres, negative when penetrating


class CollisionChecker:
    """Robot-versus-scene contacts for arm configurations, on private copies of model and data.

    Only the robot's *moving* geoms (links 1-7, hand, fingers) are tested against the scene
    geoms that collide with the robot in the simulation (table, props, objects); the base, which
    never moves, and robot-robot pairs (the simulation does not collide them either) are left
    out, as are ``ignore_geoms`` (names, e.g. an object being held). Contacts closer than
    ``clearance`` metres count (0: touching or penetrating; > 0 keeps a safety distance). Link 1
    only turns about the vertical and stays 78 mm above the table top, so a clearance beyond that
    flags every configuration.

    Args:
        model: the compiled scene.
        handles: the robot's handles; default the robot named with prefix ``"robot/"``.
        data: scene state to copy (object poses, finger opening); default ``model.qpos0``.
        gripper: finger opening as a fraction of FINGER_MAX held fixed during checks; None
            keeps the opening of ``data``.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        handles: RobotHandles | None = None,
        *,
        data: mujoco.MjData | None = None,
        gripper: float | None = None,
        ignore_geoms: Iterable[str] = (),
        clearance: float = 0.0,
    ) -> None:
        self.handles = handles if handles is not None else robot_handles()
        self._arm_qadr = _check_model_has_robot(model, self.handles)
        if not np.isfinite(clearance) or clearance < 0:
            raise InvalidParameterError(f"clearance must be >= 0 metres, got {clearance}")
        self.clearance = float(clearance)
        self.model = copy.copy(model)  # private: we rewrite collision filters and margins
        self.data = mujoco.MjData(self.model)
        self._finger_qadr = np.array([model.joint(n).qposadr[0] for n in self.handles.finger_joints])
        self._original_contype = model.geom_contype.copy()
        self._original_conaffinity = model.geom_conaffinity.copy()
        robot_ids = {model.geom(n).id for n in self.handles.collision_geoms}
        # Geoms on bodies welded to the world (the base link) keep the same contacts in every
        # configuration; a base resting on the table would otherwise make every check fail.
        self._moving = np.array(
            sorted(g for g in robot_ids if model.body_weldid[model.geom_bodyid[g]] != 0), dtype=int
        )
        self._robot = np.array(sorted(robot_ids), dtype=int)
        self._moving_set, self._robot_set = frozenset(self._moving.tolist()), frozenset(robot_ids)
        self._gripper: float | None = None
        self.sync(data)
        self.set_gripper(gripper)
        self.set_ignored(ignore_geoms)

    # configuration of the checker

    def sync(self, data: mujoco.MjData | None) -> None:
        """Copy the scene state (object poses, finger opening) from live ``data``."""
        self.data.qpos[:] = self.model.qpos0 if data is None else data.qpos
        if self._gripper is not None:
            self.set_gripper(self._gripper)

    def set_gripper(self, gripper: float | None) -> None:
        """Fix the finger opening (fraction of FINGER_MAX) for later checks; None keeps data's."""
        self._gripper = None if gripper is None else float(np.clip(gripper, 0.0, 1.0))
        if self._gripper is not None:
            self.data.qpos[self._finger_qadr] = self._gripper * FINGER_MAX

    def set_ignored(self, ignore_geoms: Iterable[str]) -> None:
        """Replace the set of scene geoms (names) whose contacts with the robot do not count."""
        m = self.model
        ignored = set()
        for name in ignore_geoms:
            try:
                ignored.add(m.geom(name).id)
            except KeyError as err:
                raise InvalidParameterError(
                    f"ignore_geoms names a geom {name!r} that the model lacks; pass geom names of this scene"
                ) from err
        self.ignored = frozenset(ignored)
        # Collision filter of the private model: moving robot geoms (contype 2, conaffinity 1)
        # meet only scene geoms given (contype 0, conaffinity 2), so MuJoCo skips scene-scene
        # and robot-robot pairs entirely, which keeps each query cheap.
        ct, ca = self._original_contype, self._original_conaffinity
        meets_robot = ((ct & ROBOT_CONAFFINITY) != 0) | ((ca & ROBOT_CONTYPE) != 0)
        m.geom_contype[:] = 0
        m.geom_conaffinity[:] = np.where(meets_robot, 2, 0)
        m.geom_conaffinity[self._robot] = 0
        m.geom_conaffinity[list(self.ignored)] = 0
        m.geom_contype[self._moving] = 2
        # MuJoCo reports a contact once the distance falls below the larger of the two margins.
        m.geom_margin[self._moving] = self.clearance
        if self.clearance > 0:
            # The midphase's bounding-volume trees were built at compile time without this margin
            # and would drop the near (not yet touching) pairs.
            m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_MIDPHASE)
        m.geom_gap[self._moving] = 0.0

    # queries

    def _collide(self, q: np.ndarray) -> None:
        self.data.qpos[self._arm_qadr] = q
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_collision(self.model, self.data)

    def _counts(self, g1: int, g2: int, dist: float) -> bool:
        if (g1 in self._moving_set) == (g2 in self._moving_set):
            return False
        other = g2 if g1 in self._moving_set else g1
        return other not in self._robot_set and other not in self.ignored and dist < self.clearance

    def contacts(self, q) -> list[Contact]:
        """Every counted contact at arm configuration ``q`` (7,), for diagnostics."""
        self._collide(_as_q(q, "q"))
        found = []
        for k in range(self.data.ncon):
            c = self.data.contact[k]
            if self._counts(int(c.geom1), int(c.geom2), float(c.dist)):
                robot_first = int(c.geom1) in self._moving_set
                r, o = (c.geom1, c.geom2) if robot_first else (c.geom2, c.geom1)
                found.append(
                    Contact(self.model.geom(int(r)).name, self.model.geom(int(o)).name, float(c.dist))
                )
        return found

    def is_free(self, q) -> bool:
        """True when no robot geom is within ``clearance`` of the scene at ``q`` (7,)."""
        self._collide(np.asarray(q, dtype=float))
        # The filter above already limits contacts to robot-vs-scene; explicit <pair>s of the
        # model bypass it, so check each contact once more.
        return not any(
            self._counts(int(c.geom1), int(c.geom2), float(c.dist))
            for c in (self.data.contact[k] for k in range(self.data.ncon))
        )

    def segment_is_free(self, q_a, q_b, step: float = 0.02) -> bool:
        """Straight joint motion from ``q_a`` to ``q_b``, checked every ``step`` rad (max joint)."""
        q_a, q_b = np.asarray(q_a, dtype=float), np.asarray(q_b, dtype=float)
        n = max(1, int(np.ceil(np.max(np.abs(q_b - q_a)) / step)))
        # Endpoints first, then a bisection order: collisions tend to show up mid-segment, so
        # this finds them sooner than a sweep from one end.
        order = [n, 0, *_bisection_order(n)]
        return all(self.is_free(q_a + (i / n) * (q_b - q_a)) for i in order)

    def path_is_free(self, q_path, step: float = 0.02) -> bool:
        """True when the piecewise-linear joint path (K, 7) is free at every ``step`` rad."""
        path = _as_path(q_path, "q_path")
        if not step > 0:
            raise InvalidParameterError(f"step must be a positive angle in rad, got {step}")
        if len(path) == 1:
            return self.is_free(path[0])
        return all(self.segment_is_free(a, b, step) for a, b in zip(path[:-1], path[1:], strict=True))


def _bisection_order(n: int) -> list[int]:
    """Interior indices 1..n-1 ordered coarse to fine (midpoint first)."""
    order, seen, spans = [], {0, n}, [(0, n)]
    while spans:
        nxt = []
        for lo, hi in spans:
            mid = (lo + hi) // 2
            if mid not in seen:
                seen.add(mid)
                order.append(mid)
            if mid - lo > 1:
                nxt.append((lo, mid))
            if hi - mid > 1:
                nxt.append((mid, hi))
        spans = nxt
    return order


# -- retiming ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class JointTrajectory:
    """Joint positions and velocities sampled every ``dt`` seconds (``t[0] = 0``)."""

    t: np.ndarray  # (T,) seconds
    q: np.ndarray  # (T, 7) rad
    qd: np.ndarray  # (T, 7) rad/s
    waypoint_index: np.ndarray  # (K,) sample index at which each waypoint is reached

    @property
    def duration(self) -> float:
        return float(self.t[-1])


def _trapezoid_time(vmax: float, amax: float) -> float:
    """Shortest time to travel a unit distance from rest to rest."""
    if vmax * vmax / amax <= 1.0:
        return 1.0 / vmax + vmax / amax
    return 2.0 * np.sqrt(1.0 / amax)


def _trapezoid_sample(t: np.ndarray, duration: float, amax: float) -> tuple[np.ndarray, np.ndarray]:
    """Progress s(t) in [0, 1] and its rate of a rest-to-rest trapezoid lasting ``duration``.

    With the acceleration fixed at ``amax``, the cruise speed v solves 1 = v T - v^2 / amax;
    stretching a time-optimal profile this way lowers both speed and acceleration.
    """
    disc = max(amax * amax * duration * duration - 4.0 * amax, 0.0)
    v = (amax * duration - np.sqrt(disc)) / 2.0
    ta = v / amax
    s = np.where(
        t < ta,
        0.5 * amax * t**2,
        np.where(
            t <= duration - ta, 0.5 * amax * ta**2 + v * (t - ta), 1.0 - 0.5 * amax * (duration - t) ** 2
        ),
    )
    sd = np.where(t < ta, amax * t, np.where(t <= duration - ta, v, amax * (duration - t)))
    return np.clip(s, 0.0, 1.0), np.maximum(sd, 0.0)


def retime(
    q_waypoints, vel_limits=DEFAULT_VEL_LIMITS, acc_limits=DEFAULT_ACC_LIMITS, dt: float = CONTROL_DT
) -> JointTrajectory:
    """Time-parameterise a piecewise-linear joint path (K, 7), sampled every ``dt`` seconds.

    Each segment follows its straight line with a trapezoidal speed profile, all joints
    synchronised (they start and stop together), from rest to rest at every waypoint: the
    motion stays on the path that the collision checker validated, and every waypoint is a
    sample. Each segment lasts a whole number of periods, the shortest that keeps every joint
    within ``vel_limits`` and ``acc_limits`` (7,) (so the limits also hold for the sampled
    finite differences). Repeated waypoints are skipped.
    """
    path = _as_path(q_waypoints, "q_waypoints")
    vmax = np.broadcast_to(np.asarray(vel_limits, dtype=float), (N_ARM,))
    amax = np.broadcast_to(np.asarray(acc_limits, dtype=float), (N_ARM,))
    if not (
        np.all(vmax > 0) and np.all(amax > 0) and np.all(np.isfinite(vmax)) and np.all(np.isfinite(amax))
    ):
        raise InvalidParameterError(
            f"vel_limits and acc_limits must be positive and finite per joint, got {vel_limits}, {acc_limits}"
        )
    if not (np.isfinite(dt) and dt > 0):
        raise InvalidParameterError(f"dt must be a positive period in seconds, got {dt}")

    qs, qds, index = [path[:1]], [np.zeros((1, N_ARM))], [0]
    for q_a, q_b in zip(path[:-1], path[1:], strict=True):
        delta = q_b - q_a
        moving = np.abs(delta) > 1e-12
        if not np.any(moving):
            index.append(index[-1])
            continue
        # Limits on the progress s in [0, 1]: joint j moves delta_j * s.
        s_vmax = float(np.min(vmax[moving] / np.abs(delta[moving])))
        s_amax = float(np.min(amax[moving] / np.abs(delta[moving])))
        n = int(np.ceil(_trapezoid_time(s_vmax, s_amax) / dt - 1e-9))
        t = np.arange(1, n + 1) * dt
        s, sd = _trapezoid_sample(t, n * dt, s_amax)
        s[-1], sd[-1] = 1.0, 0.0  # exact arrival at the waypoint
        qs.append(q_a + s[:, None] * delta)
        qds.append(sd[:, None] * delta)
        index.append(index[-1] + n)
    q = np.concatenate(qs)
    return JointTrajectory(
        t=np.arange(len(q)) * dt, q=q, qd=np.concatenate(qds), waypoint_index=np.asarray(index, dtype=int)
    )


# -- RRT-Connect ------------------------------------------------------------------------------


class _Tree:
    def __init__(self, root: np.ndarray, capacity: int) -> None:
        self.nodes = np.empty((capacity, N_ARM))
        self.parent = np.empty(capacity, dtype=int)
        self.nodes[0], self.parent[0], self.size = root, -1, 1

    def add(self, q: np.ndarray, parent: int) -> int:
        if self.size == len(self.nodes):  # grow geometrically
            self.nodes = np.concatenate([self.nodes, np.empty_like(self.nodes)])
            self.parent = np.concatenate([self.parent, np.empty_like(self.parent)])
        self.nodes[self.size], self.parent[self.size] = q, parent
        self.size += 1
        return self.size - 1

    def nearest(self, q: np.ndarray) -> int:
        return int(np.argmin(np.sum((self.nodes[: self.size] - q) ** 2, axis=1)))

    def path_to_root(self, i: int) -> list[np.ndarray]:
        out = []
        while i >= 0:
            out.append(self.nodes[i].copy())
            i = int(self.parent[i])
        return out


def _extend(tree: _Tree, checker: CollisionChecker, q_target: np.ndarray, step: float, check_step: float):
    """One step from the nearest node toward ``q_target``: ('reached'|'advanced'|'trapped', index)."""
    i = tree.nearest(q_target)
    q_near = tree.nodes[i]
    delta = q_target - q_near
    dist = float(np.linalg.norm(delta))
    reached = dist <= step
    q_new = q_target.copy() if reached else q_near + delta * (step / dist)
    if not checker.segment_is_free(q_near, q_new, check_step):
        return "trapped", i
    return ("reached" if reached else "advanced"), tree.add(q_new, i)


def _connect(tree: _Tree, checker: CollisionChecker, q_target: np.ndarray, step: float, check_step: float):
    while True:
        status, i = _extend(tree, checker, q_target, step, check_step)
        if status != "advanced":
            return status, i


def _shortcut(path: list[np.ndarray], checker, rng, iterations: int, check_step: float) -> list[np.ndarray]:
    """Random shortcuts (drop the waypoints between two that see each other), then a greedy pass."""
    path = list(path)
    for _ in range(iterations):
        if len(path) <= 2:
            break
        i, j = sorted(rng.choice(len(path), size=2, replace=False))
        if j - i > 1 and checker.segment_is_free(path[i], path[j], check_step):
            path = path[: i + 1] + path[j:]
    # Greedy: from each kept waypoint jump to the farthest one it sees.
    out, i = [path[0]], 0
    while i < len(path) - 1:
        j = len(path) - 1
        while j > i + 1 and not checker.segment_is_free(path[i], path[j], check_step):
            j -= 1
        out.append(path[j])
        i = j
    return out


def plan_rrt_connect(
    checker: CollisionChecker,
    q_start,
    q_goal,
    seed: int = 0,
    max_iters: int = 2000,
    step: float = 0.3,
    *,
    check_step: float = 0.02,
    shortcut_iters: int = 100,
) -> np.ndarray:
    """A collision-free joint path (K, 7) from ``q_start`` to ``q_goal`` by RRT-Connect.

    Two trees grow toward uniform samples of the joint box (seeded by ``seed``, so the same
    inputs give the same path) in steps of at most ``step`` rad (Euclidean); edges are checked
    every ``check_step`` rad. The raw path is shortened by random shortcuts and a greedy pass.
    Raises PlanningError when an end is in collision or no path is found in ``max_iters``.
    """
    q_start, q_goal = _as_q(q_start, "q_start"), _as_q(q_goal, "q_goal")
    if not (step > 0 and check_step > 0 and max_iters >= 1):
        raise InvalidParameterError(
            "step and check_step must be positive (rad) and max_iters >= 1, "
            f"got {step}, {check_step}, {max_iters}"
        )
    for name, q in (("start", q_start), ("goal", q_goal)):
        if not checker.is_free(q):
            raise PlanningError(
                f"{name}_in_collision",
                f"the {name} configuration touches the scene: {checker.contacts(q)[:3]}; "
                "move it or pass the touching geoms (e.g. a held object) as ignored.",
            )
    rng = np.random.default_rng(seed)
    if checker.segment_is_free(q_start, q_goal, check_step):
        return np.stack([q_start, q_goal])
    low, high = Q_LOWER + _LIMIT_MARGIN, Q_UPPER - _LIMIT_MARGIN
    tree_a, tree_b = _Tree(q_start, 1024), _Tree(q_goal, 1024)
    a_is_start = True
    for _ in range(int(max_iters)):
        sample = rng.uniform(low, high)
        status, i_a = _extend(tree_a, checker, sample, step, check_step)
        if status != "trapped":
            status_b, i_b = _connect(tree_b, checker, tree_a.nodes[i_a], step, check_step)
            if status_b == "reached":
                half_a = tree_a.path_to_root(i_a)[::-1]  # root_a .. meeting node
                half_b = tree_b.path_to_root(i_b)[1:]  # after the meeting node .. root_b
                path = half_a + half_b if a_is_start else (half_a + half_b)[::-1]
                return np.stack(_shortcut(path, checker, rng, shortcut_iters, check_step))
        # Grow the smaller tree next: balanced trees meet sooner.
        if tree_a.size > tree_b.size:
            tree_a, tree_b, a_is_start = tree_b, tree_a, not a_is_start
    raise PlanningError(
        "no_path",
        f"RRT-Connect found no collision-free path in {max_iters} iterations "
        f"({tree_a.size + tree_b.size} nodes); raise max_iters or check that the goal is reachable.",
    )


# -- joint path to env actions ----------------------------------------------------------------


def joint_path_to_actions(model: mujoco.MjModel, handles: RobotHandles, q_traj, gripper) -> np.ndarray:
    """(T, 10) env actions: the tcp pose (FK) of each sample of ``q_traj`` (T, 7) and ``gripper``.

    ``gripper`` is one command in [0, 1] or one per sample (T,). Replayed through the env's
    end-effector controller, the tcp follows the planned path; the controller's own IK picks the
    arm's redundant (elbow) direction, which stays close to the plan for small steps from the
    planned start but is not enforced.
    """
    _check_model_has_robot(model, handles)
    path = _as_path(q_traj, "q_traj")
    grip = np.broadcast_to(np.asarray(gripper, dtype=float), (len(path),))
    kin = _kinematics(handles)
    actions = np.empty((len(path), 10))
    for k, q in enumerate(path):
        pos, rot = kin.fk(q)
        actions[k, :3], actions[k, 3:9] = pos, matrix_to_rot6d(rot)
    actions[:, 9] = grip
    return actions


# -- top level --------------------------------------------------------------------------------


@dataclass(frozen=True)
class MotionPlan:
    actions: np.ndarray  # (T, 10) env actions, one per control period
    trajectory: JointTrajectory
    waypoints: np.ndarray  # (K, 7) collision-checked joint path
    q_goal: np.ndarray  # (7,)
    used_rrt: bool
    planning_time: float  # seconds of wall time


def plan_to_pose(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    handles: RobotHandles,
    target_pos,
    target_rot,
    gripper: float,
    ignore_geoms: Sequence[str] = (),
    seed: int = 0,
    *,
    clearance: float = 0.0,
    vel_limits=DEFAULT_VEL_LIMITS,
    acc_limits=DEFAULT_ACC_LIMITS,
    dt: float = CONTROL_DT,
    max_iters: int = 2000,
    checker: CollisionChecker | None = None,
) -> MotionPlan:
    """Plan a collision-free move of the tcp to a pose, as env actions from the current state.

    IK (seeded by the current arm joints, collision-free goal) -> straight joint interpolation
    when free, else RRT-Connect -> :func:`retime` -> :func:`joint_path_to_actions`. The finger
    opening stays as in ``data`` during the checks; ``gripper`` is only the command written in
    the actions. Pass a ``checker`` to reuse one (it is re-synced to ``data`` and given
    ``ignore_geoms``). Raises PlanningError (``reason``: ``start_in_collision``,
    ``goal_unreachable``, ``goal_in_collision``, ``no_path``) when no plan exists.
    """
    started = time.perf_counter()
    arm_qadr = _check_model_has_robot(model, handles)
    q_start = np.clip(data.qpos[arm_qadr].copy(), Q_LOWER, Q_UPPER)
    if checker is None:
        checker = CollisionChecker(model, handles, data=data, ignore_geoms=ignore_geoms, clearance=clearance)
    else:
        checker.sync(data)
        checker.set_ignored(ignore_geoms)
    if not checker.is_free(q_start):
        raise PlanningError(
            "start_in_collision",
            f"the robot touches the scene at the start: {checker.contacts(q_start)[:3]}; "
            "pass the touching geoms (e.g. a held object) in ignore_geoms or move away first.",
        )
    ik = solve_ik(model, handles, target_pos, target_rot, q_start, seed=seed, accept=checker.is_free)
    if not ik.ok:
        # Tell an unreachable pose from a reachable one whose every IK solution collides.
        free_ik = solve_ik(model, handles, target_pos, target_rot, q_start, seed=seed, n_random_seeds=0)
        if free_ik.ok:
            raise PlanningError(
                "goal_in_collision",
                f"every IK solution found for the target touches the scene, e.g. "
                f"{checker.contacts(free_ik.q)[:3]}; choose another pose or ignore the touched geoms.",
            )
        raise PlanningError(
            "goal_unreachable",
            f"IK missed the target by {ik.error.position * 1e3:.1f} mm / "
            f"{np.degrees(ik.error.rotation):.1f} deg "
            "(tolerance 1 mm / 0.5 deg); choose a pose inside the workspace.",
        )
    used_rrt = not checker.segment_is_free(q_start, ik.q)
    if used_rrt:
        waypoints = plan_rrt_connect(checker, q_start, ik.q, seed=seed, max_iters=max_iters)
    else:
        waypoints = np.stack([q_start, ik.q])
    trajectory = retime(waypoints, vel_limits, acc_limits, dt)
    # Sample 0 is the start itself; a plan that does not move still gets its goal as one action.
    samples = trajectory.q[1:] if len(trajectory.q) > 1 else trajectory.q
    actions = joint_path_to_actions(model, handles, samples, gripper)
    return MotionPlan(
        actions=actions,
        trajectory=trajectory,
        waypoints=waypoints,
        q_goal=ik.q,
        used_rrt=used_rrt,
        planning_time=time.perf_counter() - started,
    )
