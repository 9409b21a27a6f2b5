"""A Franka-Panda-like 7-DoF arm with a parallel-jaw gripper, built in code with ``mujoco.MjSpec``.

Kinematics follow the published Panda parameters in Craig's modified DH convention: link ``i``
sits in link ``i-1`` at ``RotX(alpha_i) TransX(a_i) TransZ(d_i)`` and turns about its own z axis.
The flange is ``d = 0.107`` beyond link 7; the hand is mounted turned by -45 deg about the flange
z axis, as on the real robot, so that ``q7 = pi/4`` aligns the fingers with link 0's y axis.

Frames (world z-up, metres):

- ``tcp`` site: on the hand, ``TCP_OFFSET`` beyond the flange, between the finger pads. Its z
  axis points out of the gripper (approach direction), its y axis along the finger closing axis.
- ``flange`` site: on link 7 at the flange, frame equal to the DH flange frame.

Collision geometry is primitive (capsules, cylinders, boxes) and a few mm larger than the real
links. Robot geoms use ``contype=2, conaffinity=1``: they collide with anything of the default
``contype=1`` (table, objects) but never with each other, which avoids spurious self-contacts
between the coarse capsules. Scene objects must therefore keep bit 0 set in ``contype``.

Gravity is compensated through the actuators (``gravcomp`` on the bodies, ``actgravcomp`` on the
joints), so the position servos do not sag and the compensation counts against torque limits.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from keygen.errors import InvalidParameterError

# Published Panda kinematics (Craig's modified DH), joints 1..7.
DH_A = (0.0, 0.0, 0.0, 0.0825, -0.0825, 0.0, 0.088)
DH_D = (0.333, 0.0, 0.316, 0.0, 0.384, 0.0, 0.0)
DH_ALPHA = (0.0, -np.pi / 2, np.pi / 2, np.pi / 2, -np.pi / 2, np.pi / 2, np.pi / 2)
FLANGE_D = 0.107

# Published limits: positions (rad), velocities (rad/s), torques (N m).
JOINT_LOWER = (-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973)
JOINT_UPPER = (2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973)
JOINT_VELOCITY_LIMITS = (2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61)
JOINT_TORQUE_LIMITS = (87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0)

# Position servo gains per joint. kv gives a damping ratio of about 1.2 for the joint-space
# inertia at HOME_QPOS (armature included): faster settling than heavily overdamped servos, whose
# slow pole kp / kv would make the arm lag its targets by a tenth of a second.
JOINT_KP = (4500.0, 4500.0, 3500.0, 3500.0, 2000.0, 2000.0, 2000.0)
JOINT_KV = (160.0, 200.0, 150.0, 150.0, 40.0, 40.0, 35.0)
JOINT_DAMPING = 1.0  # N m s / rad, viscous friction of the gearboxes
JOINT_ARMATURE = 0.1  # kg m^2, reflected rotor inertia; also steadies the integration

HAND_YAW = -np.pi / 4  # hand mounted on the flange turned about the flange z axis
FINGER_MAX = 0.04  # stroke of each finger; maximum opening 2 * FINGER_MAX = 80 mm
FINGER_BASE_Z = 0.0584  # where the fingers leave the hand, along the hand z axis
# Long fingers (the Panda's are ~50 mm): with one finger through a mug handle the hand must clear
# the mug's body, and with 50 mm fingers it hit every body wider than ~45 mm in radius.
FINGER_LENGTH = 0.09
TCP_OFFSET = FINGER_BASE_Z + FINGER_LENGTH - 0.005  # flange to tcp: 5 mm short of the fingertips
PAD_SIZE = (0.018, 0.008, 0.025)  # pad width (x), thickness (y), length (z), metres
GRIP_FORCE = 70.0  # N, squeeze force of each jaw at saturation (Panda hand: 70 N continuous)
# The gripper servo acts on the mean finger opening. Its stiffness is high so that even a thin
# handle (a few mm of remaining command error) is squeezed near GRIP_FORCE.
GRIPPER_KP = 20000.0  # N/m on the mean opening
# N s/m per finger: caps the closing speed near GRIP_FORCE / FINGER_DAMPING = 0.23 m/s so that
# fingers do not bat objects away; with the servo this is a first-order lag of ~30 ms.
FINGER_DAMPING = 300.0
# kg, reflected inertia of the geared finger drive (a lead-screw drive reflects far more). Besides
# being realistic it keeps the pads from sinking into objects: a soft contact's steady penetration
# grows with the acceleration the grip force would give the finger, so a bare 50 g finger under 70 N
# sinks ~2 mm, a 0.15 kg one ~0.4 mm. At 0.1 kg a pinched mug handle put the servo, the finger and
# the pad contact into a ~11 Hz limit cycle under a constant command: the squeeze swung between 0
# and 70 N, each zero let the handle slide ~1 mm along the pads, and the mug walked out of the
# pinch (test mug 1, pinch expert: 15 drops in 20). From 0.3 kg the squeeze holds steady (58 +- 1 N
# in the same hold); 0.5 leaves a margin (19 of those 20 episodes then pour).
FINGER_ARMATURE = 0.5

PAD_FRICTION = (1.5, 0.02, 0.002)
# Contact time constant 10 ms, critically damped: stiffer settings (4-6 ms, i.e. 2-3 physics steps)
# let the pinched finger-object pair fall into a limit cycle that walks the object out of the grasp;
# at 10 ms a 70 N pinch sinks the pads ~0.4 mm into the object and holds it without creep.
PAD_SOLREF = (0.01, 1.0)
PAD_SOLIMP = (0.95, 0.99, 0.001, 0.5, 2.0)

# Gripper pointing straight down, tcp 0.45 m in front of the base and 0.30 m above it,
# fingers closing along the base y axis.
HOME_QPOS = (0.0, -0.2594, 0.0, -2.4315, 0.0, 2.1721, np.pi / 4)
HOME_TCP_POS = (0.45, 0.0, 0.26)

ROBOT_CONTYPE = 2
ROBOT_CONAFFINITY = 1

ARM_JOINTS = tuple(f"joint{i}" for i in range(1, 8))
FINGER_JOINTS = ("finger_left", "finger_right")
ARM_ACTUATORS = tuple(f"actuator{i}" for i in range(1, 8))
GRIPPER_ACTUATOR = "gripper"
PAD_GEOMS = ("pad_left", "pad_right")
FINGER_GEOMS = ("finger_left_geom", "finger_right_geom", *PAD_GEOMS)

_GREY = (0.85, 0.85, 0.87, 1.0)
_DARK = (0.2, 0.2, 0.22, 1.0)


@dataclass(frozen=True)
class _Link:
    """Mass properties (published-identification-like values) and primitive collision shapes."""

    mass: float  # kg
    com: tuple[float, float, float]  # in the link frame
    inertia: tuple[float, float, float]  # principal moments about the com, kg m^2
    # (type, fromto or (pos, size), radius or box half sizes)
    capsules: tuple[tuple[tuple[float, ...], float], ...] = ()  # (fromto, radius)
    cylinders: tuple[tuple[tuple[float, ...], float], ...] = ()  # (fromto, radius)


# Masses and centres of mass are rounded from published Panda identification results; the
# inertias are those of solid boxes of roughly the link's size (simple and plausible).
_LINKS: tuple[_Link, ...] = (
    _Link(0.63, (-0.04, 0.0, 0.06), (0.006, 0.007, 0.007), cylinders=(((0, 0, 0, 0, 0, 0.15), 0.09),)),
    _Link(
        4.97,
        (0.004, 0.002, -0.048),
        (0.070, 0.070, 0.009),
        capsules=(((0, 0, -0.19, 0, 0, -0.03), 0.065),),
    ),
    _Link(
        0.65,
        (-0.003, -0.029, 0.003),
        (0.008, 0.003, 0.008),
        capsules=(((0, 0, 0, 0, -0.20, 0), 0.065),),
        cylinders=(((0, 0, -0.065, 0, 0, 0.065), 0.065),),
    ),
    _Link(
        3.23,
        (0.028, 0.039, -0.067),
        (0.037, 0.036, 0.011),
        capsules=(((0, 0, -0.13, 0, 0, -0.02), 0.06), ((0, 0, 0, 0.0825, 0, 0), 0.06)),
    ),
    _Link(
        3.59,
        (-0.053, 0.104, 0.027),
        (0.037, 0.011, 0.036),
        capsules=(((0, 0, 0, -0.0825, 0.11, 0), 0.06),),
        cylinders=(((0, 0, -0.06, 0, 0, 0.06), 0.065),),
    ),
    _Link(
        1.23,
        (-0.012, 0.041, -0.038),
        (0.036, 0.033, 0.004),
        capsules=(((0, 0, -0.27, 0, 0, -0.02), 0.06), ((0, 0.08, -0.24, 0, 0.08, -0.12), 0.04)),
    ),
    _Link(
        1.67,
        (0.060, -0.014, -0.011),
        (0.002, 0.004, 0.005),
        capsules=(((0, 0, 0, 0.088, 0, 0), 0.055),),
        cylinders=(((0, 0, -0.06, 0, 0, 0.02), 0.06),),
    ),
    _Link(
        0.74,
        (0.011, -0.004, 0.062),
        (0.001, 0.001, 0.001),
        cylinders=(((0, 0, -0.02, 0, 0, 0.095), 0.05),),
    ),
)
_HAND_MASS = 0.73
_FINGER_MASS = 0.05


@dataclass(frozen=True)
class RobotHandles:
    """Names (already prefixed) of the robot's elements inside a compiled scene, and its base pose."""

    prefix: str
    base_pos: tuple[float, float, float]
    base_yaw: float
    arm_joints: tuple[str, ...]
    finger_joints: tuple[str, str]
    arm_actuators: tuple[str, ...]
    gripper_actuator: str
    tcp_site: str
    flange_site: str
    hand_body: str
    finger_geoms: tuple[str, ...]
    pad_geoms: tuple[str, str]
    collision_geoms: tuple[str, ...]


def _dh_link_pose(i: int) -> tuple[np.ndarray, np.ndarray]:
    """Position and quaternion (w, x, y, z) of link ``i + 1`` in link ``i`` (0-based joint index)."""
    alpha, a, d = DH_ALPHA[i], DH_A[i], DH_D[i]
    # RotX(alpha) TransX(a) TransZ(d): x is unchanged by RotX, z is rotated by it.
    pos = np.array([a, -d * np.sin(alpha), d * np.cos(alpha)])
    quat_wxyz = np.array([np.cos(alpha / 2), np.sin(alpha / 2), 0.0, 0.0])
    return pos, quat_wxyz


def _yaw_quat_wxyz(yaw: float) -> list[float]:
    return [float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))]


def _add_collision(body: mujoco.MjsBody, name: str, **kwargs) -> mujoco.MjsGeom:
    geom = body.add_geom(name=name, contype=ROBOT_CONTYPE, conaffinity=ROBOT_CONAFFINITY, **kwargs)
    geom.mass = 0.0  # mass properties are given explicitly on the body
    return geom


def _add_link_geometry(body: mujoco.MjsBody, link: _Link, stem: str) -> list[str]:
    names = []
    shapes = [(mujoco.mjtGeom.mjGEOM_CAPSULE, s) for s in link.capsules]
    shapes += [(mujoco.mjtGeom.mjGEOM_CYLINDER, s) for s in link.cylinders]
    for k, (gtype, (fromto, radius)) in enumerate(shapes):
        name = f"{stem}_col{k}"
        _add_collision(body, name, type=gtype, fromto=list(map(float, fromto)), size=[radius, 0, 0])
        body.geoms[-1].rgba = _GREY
        names.append(name)
    return names


def _set_inertial(body: mujoco.MjsBody, mass: float, com, inertia) -> None:
    body.explicitinertial = True
    body.mass = mass
    body.ipos = list(map(float, com))
    body.inertia = list(map(float, inertia))
    body.gravcomp = 1.0


def _add_arm(spec: mujoco.MjSpec, p: str) -> tuple[mujoco.MjsBody, list[str]]:
    """The base and seven links; returns link 7 and the names of the collision geoms."""
    base = spec.worldbody.add_body(name=f"{p}link0")
    _set_inertial(base, _LINKS[0].mass, _LINKS[0].com, _LINKS[0].inertia)
    collision = _add_link_geometry(base, _LINKS[0], f"{p}link0")
    parent = base
    for i in range(7):
        pos, quat = _dh_link_pose(i)
        link = _LINKS[i + 1]
        body = parent.add_body(name=f"{p}link{i + 1}", pos=pos.tolist(), quat=quat.tolist())
        _set_inertial(body, link.mass, link.com, link.inertia)
        body.add_joint(
            name=f"{p}{ARM_JOINTS[i]}",
            type=mujoco.mjtJoint.mjJNT_HINGE,
            axis=[0, 0, 1],
            range=[JOINT_LOWER[i], JOINT_UPPER[i]],
            limited=mujoco.mjtLimited.mjLIMITED_TRUE,
            damping=JOINT_DAMPING,
            armature=JOINT_ARMATURE,
            actfrclimited=mujoco.mjtLimited.mjLIMITED_TRUE,
            actfrcrange=[-JOINT_TORQUE_LIMITS[i], JOINT_TORQUE_LIMITS[i]],
            actgravcomp=True,
        )
        collision += _add_link_geometry(body, link, f"{p}link{i + 1}")
        parent = body
    parent.add_site(name=f"{p}flange", pos=[0, 0, FLANGE_D], size=[0.005, 0, 0])
    return parent, collision


def _add_finger(hand: mujoco.MjsBody, p: str, side: int) -> list[str]:
    """One finger: a prismatic joint along +-y of the hand, a finger box and a friction pad."""
    label = "left" if side > 0 else "right"
    finger = hand.add_body(name=f"{p}finger_{label}", pos=[0, 0, FINGER_BASE_Z])
    _set_inertial(finger, _FINGER_MASS, (0, side * 0.012, FINGER_LENGTH / 2), (2e-5, 2e-5, 5e-6))
    finger.add_joint(
        name=f"{p}finger_{label}",
        type=mujoco.mjtJoint.mjJNT_SLIDE,
        axis=[0, side, 0],
        range=[0.0, FINGER_MAX],
        limited=mujoco.mjtLimited.mjLIMITED_TRUE,
        damping=FINGER_DAMPING,
        armature=FINGER_ARMATURE,
        actgravcomp=True,
    )
    width, thick, length = PAD_SIZE
    # The finger's inner face is flush with the pad's inner face, at y = side * q; at q = 0 the
    # pads touch in the middle. The finger box sits behind the pad over the whole length.
    _add_collision(
        finger,
        f"{p}finger_{label}_geom",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        pos=[0, side * (thick + 0.005), FINGER_LENGTH / 2],
        size=[width / 2, 0.005, FINGER_LENGTH / 2],
        rgba=_DARK,
    )
    pad = _add_collision(
        finger,
        f"{p}pad_{label}",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        pos=[0, side * thick / 2, FINGER_LENGTH - length / 2],
        size=[width / 2, thick / 2, length / 2],
        rgba=(0.1, 0.1, 0.1, 1.0),
    )
    # Priority makes the pad's contact parameters win over whatever the object declares, so grasp
    # quality does not depend on the object asset. condim 4 adds torsional friction, which keeps a
    # pinched object from spinning about the closing axis.
    pad.priority = 1
    pad.condim = 4
    pad.friction = list(PAD_FRICTION)
    pad.solref = list(PAD_SOLREF)
    pad.solimp = list(PAD_SOLIMP)
    return [f"{p}finger_{label}_geom", f"{p}pad_{label}"]


def _add_gripper(spec: mujoco.MjSpec, link7: mujoco.MjsBody, p: str) -> list[str]:
    """Hand, two coupled fingers and the gripper actuator; returns the collision geom names."""
    hand = link7.add_body(name=f"{p}hand", pos=[0, 0, FLANGE_D], quat=_yaw_quat_wxyz(HAND_YAW))
    _set_inertial(hand, _HAND_MASS, (0, 0, 0.035), (0.0025, 0.0003, 0.0025))
    _add_collision(
        hand,
        f"{p}hand_col0",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        pos=[0, 0, 0.032],
        size=[0.033, 0.104, 0.027],
        rgba=_GREY,
    )
    _add_collision(
        hand,
        f"{p}hand_col1",
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        fromto=[0, 0, -0.002, 0, 0, 0.01],
        size=[0.045, 0, 0],
        rgba=_DARK,
    )
    hand.add_site(name=f"{p}tcp", pos=[0, 0, TCP_OFFSET], size=[0.004, 0, 0], rgba=(1, 0, 0, 1))
    geoms = [f"{p}hand_col0", f"{p}hand_col1"]
    geoms += _add_finger(hand, p, +1)
    geoms += _add_finger(hand, p, -1)

    # Fingers move together: the right one copies the left one; the actuator drives their mean.
    spec.add_equality(
        name=f"{p}finger_coupling",
        type=mujoco.mjtEq.mjEQ_JOINT,
        name1=f"{p}finger_right",
        name2=f"{p}finger_left",
        solref=[0.005, 1.0],
        solimp=[0.95, 0.99, 0.001, 0.5, 2.0],
    )
    tendon = spec.add_tendon(name=f"{p}finger_mean")
    tendon.wrap_joint(f"{p}finger_left", 0.5)
    tendon.wrap_joint(f"{p}finger_right", 0.5)
    act = spec.add_actuator(name=f"{p}{GRIPPER_ACTUATOR}", target=f"{p}finger_mean")
    act.trntype = mujoco.mjtTrn.mjTRN_TENDON
    act.set_to_position(kp=GRIPPER_KP)
    act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
    act.ctrlrange = [0.0, FINGER_MAX]
    # A tendon force f pushes each finger with f / 2, so the jaw squeeze force is f / 2.
    act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
    act.forcerange = [-2 * GRIP_FORCE, 2 * GRIP_FORCE]
    return geoms


def _add_arm_actuators(spec: mujoco.MjSpec, p: str) -> None:
    for i in range(7):
        act = spec.add_actuator(name=f"{p}{ARM_ACTUATORS[i]}", target=f"{p}{ARM_JOINTS[i]}")
        act.trntype = mujoco.mjtTrn.mjTRN_JOINT
        act.set_to_position(kp=JOINT_KP[i], kv=JOINT_KV[i])
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.ctrlrange = [JOINT_LOWER[i], JOINT_UPPER[i]]
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcerange = [-JOINT_TORQUE_LIMITS[i], JOINT_TORQUE_LIMITS[i]]


def build_robot_spec(name_prefix: str = "robot/") -> mujoco.MjSpec:
    """The arm and gripper as a standalone spec, base at the world origin, every name prefixed.

    The spec compiles on its own (with MuJoCo's default options; see :func:`recommended_options`).
    """
    spec = mujoco.MjSpec()
    spec.modelname = "keygen_panda"
    # Joint ranges are in radians; the spec's default (inherited from MJCF) is degrees.
    spec.compiler.degree = False
    link7, _ = _add_arm(spec, name_prefix)
    _add_arm_actuators(spec, name_prefix)
    _add_gripper(spec, link7, name_prefix)
    return spec


def robot_collision_geom_names(name_prefix: str = "robot/") -> tuple[str, ...]:
    """Names of every collision geom of the robot (arm links, hand, fingers and pads)."""
    spec = build_robot_spec(name_prefix)
    return tuple(g.name for g in spec.geoms)


def robot_handles(
    name_prefix: str = "robot/", base_pos=(0.0, 0.0, 0.0), base_yaw: float = 0.0
) -> RobotHandles:
    """The handles of a robot whose names carry ``name_prefix`` (no spec is touched)."""
    p = name_prefix
    return RobotHandles(
        prefix=p,
        base_pos=tuple(float(v) for v in base_pos),
        base_yaw=float(base_yaw),
        arm_joints=tuple(p + n for n in ARM_JOINTS),
        finger_joints=(p + FINGER_JOINTS[0], p + FINGER_JOINTS[1]),
        arm_actuators=tuple(p + n for n in ARM_ACTUATORS),
        gripper_actuator=p + GRIPPER_ACTUATOR,
        tcp_site=p + "tcp",
        flange_site=p + "flange",
        hand_body=p + "hand",
        finger_geoms=tuple(p + n for n in FINGER_GEOMS),
        pad_geoms=(p + PAD_GEOMS[0], p + PAD_GEOMS[1]),
        collision_geoms=robot_collision_geom_names(p),
    )


def add_robot(
    scene_spec: mujoco.MjSpec,
    base_pos=(0.0, 0.0, 0.0),
    base_yaw: float = 0.0,
    name_prefix: str = "robot/",
) -> RobotHandles:
    """Attach a robot into ``scene_spec`` with its base at ``base_pos``, turned ``base_yaw`` about z."""
    pos = np.asarray(base_pos, dtype=float)
    if pos.shape != (3,) or not np.all(np.isfinite(pos)) or not np.isfinite(base_yaw):
        raise InvalidParameterError(
            f"add_robot expected a finite base_pos (x, y, z) and base_yaw, got {base_pos!r}, {base_yaw!r}; "
            "pass three metres and an angle in radians."
        )
    if any(b.name == f"{name_prefix}link0" for b in scene_spec.bodies):
        raise InvalidParameterError(
            f"the scene already has a robot named with prefix {name_prefix!r}; "
            "pass a different name_prefix for a second robot."
        )
    frame = scene_spec.worldbody.add_frame(pos=pos.tolist(), quat=_yaw_quat_wxyz(base_yaw))
    scene_spec.attach(build_robot_spec(name_prefix=""), prefix=name_prefix, frame=frame)
    return robot_handles(name_prefix, pos, base_yaw)


def recommended_options(spec: mujoco.MjSpec, noslip_iterations: int = 2) -> mujoco.MjSpec:
    """Set the physics options the robot is tuned for on ``spec`` (in place; also returned).

    ``implicitfast`` treats the servo and joint damping implicitly (stable with stiff gains),
    a 2 ms step, elliptic friction cones with ``impratio = 10`` so that pinch grasps do not
    creep. Soft contacts still let a pinched object creep by about 1 mm/s in some grasps;
    ``noslip_iterations`` (default 2, 0 to turn off) removes that residual slip for a small cost.
    """
    if noslip_iterations < 0:
        raise InvalidParameterError(f"noslip_iterations must be >= 0, got {noslip_iterations}")
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.timestep = 0.002
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = 10.0
    spec.option.noslip_iterations = int(noslip_iterations)
    return spec


def set_home(model: mujoco.MjModel, data: mujoco.MjData, handles: RobotHandles, gripper: float = 1.0) -> None:
    """Put the robot at :data:`HOME_QPOS` at rest, servos holding it there; runs ``mj_forward``."""
    for joint_name, actuator_name, q in zip(
        handles.arm_joints, handles.arm_actuators, HOME_QPOS, strict=True
    ):
        joint = model.joint(joint_name)
        data.qpos[joint.qposadr[0]] = q
        data.qvel[joint.dofadr[0]] = 0.0
        data.ctrl[model.actuator(actuator_name).id] = q
    opening = float(np.clip(gripper, 0.0, 1.0)) * FINGER_MAX
    for name in handles.finger_joints:
        joint = model.joint(name)
        data.qpos[joint.qposadr[0]] = opening
        data.qvel[joint.dofadr[0]] = 0.0
    data.ctrl[model.actuator(handles.gripper_actuator).id] = opening
    mujoco.mj_forward(model, data)
