"""Object assets as MuJoCo bodies inside an ``mujoco.MjSpec`` scene.

Each asset becomes one body: convex collision geoms (primitives as MuJoCo primitives, hull parts as
meshes, which MuJoCo treats as their convex hull), one visual mesh geom that does not collide, and
the asset's own mass properties as an explicit inertial, so the physics sees exactly the mass and
inertia the asset records (at any scale).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from keygen.objects.asset import Asset
from keygen.sim.render_mesh import render_mesh

# Geom groups: MuJoCo renders groups 0-2 by default. Visual meshes go in group 2, collision parts in
# group 3 so that cameras (and segmentation) see the real shape, not its convex approximation.
VISUAL_GROUP = 2
COLLISION_GROUP = 3


@dataclass(frozen=True)
class ContactParams:
    """Contact settings of an object's collision geoms."""

    friction: tuple[float, float, float] = (1.0, 0.01, 0.001)
    condim: int = 4
    solref: tuple[float, float] = (0.004, 1.0)
    solimp: tuple[float, float, float, float, float] = (0.95, 0.99, 0.001, 0.5, 2.0)
    margin: float = 0.0


@dataclass
class ObjectHandles:
    """Names of what :func:`add_object` created, for lookups after compiling."""

    body: str
    joint: str | None
    collision_geoms: list[str] = field(default_factory=list)
    visual_geom: str = ""
    part_labels: list[str | None] = field(default_factory=list)  # label of each collision geom


def _full_inertia(inertia: np.ndarray) -> list[float]:
    """MuJoCo's fullinertia order: Ixx, Iyy, Izz, Ixy, Ixz, Iyz."""
    i = np.asarray(inertia)
    return [i[0, 0], i[1, 1], i[2, 2], i[0, 1], i[0, 2], i[1, 2]]


def add_object(
    spec: mujoco.MjSpec,
    asset: Asset,
    name: str,
    pos: np.ndarray | tuple = (0.0, 0.0, 0.0),
    quat_wxyz: np.ndarray | tuple = (1.0, 0.0, 0.0, 0.0),
    free: bool = True,
    rgba: tuple[float, float, float, float] = (0.8, 0.8, 0.8, 1.0),
    contact: ContactParams | None = None,
    parent: mujoco.MjsBody | None = None,
    render_max_faces: int | None = None,
) -> ObjectHandles:
    """Add ``asset`` as a body called ``name`` (a free body unless ``free`` is False).

    ``render_max_faces``: draw a simplified copy of the visual mesh when it has more faces
    (:func:`keygen.sim.render_mesh.render_mesh`); physics and the asset are unaffected."""
    contact = contact or ContactParams()
    body = (parent or spec.worldbody).add_body()
    body.name = name
    body.pos = np.asarray(pos, dtype=float)
    body.quat = np.asarray(quat_wxyz, dtype=float)
    mp = asset.mass_properties
    body.explicitinertial = True
    body.mass = float(mp.mass)
    body.ipos = np.asarray(mp.com, dtype=float)
    body.fullinertia = _full_inertia(mp.inertia)
    handles = ObjectHandles(body=name, joint=None)
    if free:
        joint = body.add_freejoint()
        joint.name = f"{name}/free"
        handles.joint = joint.name

    visual_mesh = spec.add_mesh()
    visual_mesh.name = f"{name}/visual"
    vertices, faces = np.asarray(asset.visual.vertices, dtype=float), np.asarray(asset.visual.faces)
    if render_max_faces is not None:
        vertices, faces = render_mesh(vertices, faces, render_max_faces)
    visual_mesh.uservert = vertices.ravel()
    visual_mesh.userface = faces.astype(np.int32).ravel()
    # The visual mesh never collides and the body has explicit inertia, so a shell inertia avoids
    # MuJoCo's volume checks on imported (possibly open) scans.
    visual_mesh.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL
    geom = body.add_geom()
    geom.name = f"{name}/visual"
    geom.type = mujoco.mjtGeom.mjGEOM_MESH
    geom.meshname = visual_mesh.name
    geom.contype = geom.conaffinity = 0
    geom.group = VISUAL_GROUP
    geom.rgba = list(rgba)
    geom.mass = 0.0
    handles.visual_geom = geom.name

    for i, part in enumerate(asset.collision):
        g = body.add_geom()
        g.name = f"{name}/col{i:03d}"
        g.group = COLLISION_GROUP
        g.rgba = [0.2, 0.6, 0.9, 0.5]
        g.friction = list(contact.friction)
        g.condim = contact.condim
        g.solref = list(contact.solref)
        g.solimp = list(contact.solimp)
        g.margin = contact.margin
        g.mass = 0.0
        if part.kind == "box":
            g.type = mujoco.mjtGeom.mjGEOM_BOX
            g.size = np.asarray(part.half_extents, dtype=float)
            g.pos = np.asarray(part.center, dtype=float)
            quat = np.zeros(4)
            mujoco.mju_mat2Quat(quat, np.asarray(part.rotation, dtype=float).ravel())
            g.quat = quat
        elif part.kind == "capsule":
            g.type = mujoco.mjtGeom.mjGEOM_CAPSULE
            g.fromto = np.concatenate([part.p0, part.p1]).astype(float)
            g.size = [float(part.radius), 0, 0]
        elif part.kind == "sphere":
            g.type = mujoco.mjtGeom.mjGEOM_SPHERE
            g.pos = np.asarray(part.center, dtype=float)
            g.size = [float(part.radius), 0, 0]
        else:
            mesh = spec.add_mesh()
            mesh.name = f"{name}/col{i:03d}"
            mesh.uservert = np.asarray(part.vertices, dtype=float).ravel()
            mesh.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_CONVEX
            g.type = mujoco.mjtGeom.mjGEOM_MESH
            g.meshname = mesh.name
        handles.collision_geoms.append(g.name)
        handles.part_labels.append(part.label)
    return handles
