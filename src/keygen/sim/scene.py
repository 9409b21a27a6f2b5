"""The shared scene: table, floor, lights, robot and camera rig, composed with ``mujoco.MjSpec``.

World frame: z up, the table top at z = 0, the robot base at the origin on the table's back
edge, the workspace in front of it (+x). Tasks add their objects on top of this.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from keygen.sim.cameras import CameraRig, add_cameras, add_wrist_camera
from keygen.sim.randomization import Randomization, object_color
from keygen.sim.robot import RobotHandles, add_robot, recommended_options

TABLE_TOP_Z = 0.0
TABLE_HALF = (0.6, 0.65, 0.02)  # half extents of the table top slab, metres
TABLE_CENTER_XY = (0.45, 0.0)
WORKSPACE_CENTER = (0.5, 0.0)


@dataclass
class SceneHandles:
    robot: RobotHandles
    camera_names: tuple[str, ...]
    rig: CameraRig
    table_geom: str = "table"


def _add_lights(spec: mujoco.MjSpec, rng: np.random.Generator, randomize: bool) -> None:
    if randomize:
        spec.visual.headlight.ambient = [float(rng.uniform(0.15, 0.4))] * 3
        spec.visual.headlight.diffuse = [float(rng.uniform(0.2, 0.5))] * 3
    else:
        spec.visual.headlight.ambient = [0.3, 0.3, 0.3]
        spec.visual.headlight.diffuse = [0.35, 0.35, 0.35]
    for k in range(2):
        light = spec.worldbody.add_light()
        light.name = f"light{k}"
        light.castshadow = False
        if randomize:
            az, el = rng.uniform(-np.pi, np.pi), rng.uniform(np.deg2rad(35), np.deg2rad(85))
            level = float(rng.uniform(0.25, 0.7))
        else:
            az, el, level = (0.6 if k == 0 else -2.2), np.deg2rad(60), 0.5
        direction = -np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        light.pos = (np.array([*WORKSPACE_CENTER, 0.0]) - 2.0 * direction).tolist()
        light.dir = direction.tolist()
        light.diffuse = [level] * 3
        light.specular = [0.1, 0.1, 0.1]


def _add_table(spec: mujoco.MjSpec, rng: np.random.Generator, randomize: bool) -> None:
    rgba = object_color(rng, randomize, (0.62, 0.52, 0.42))
    if randomize and rng.uniform() < 0.5:
        tex = spec.add_texture()
        tex.name = "table_tex"
        tex.type = mujoco.mjtTexture.mjTEXTURE_2D
        tex.builtin = mujoco.mjtBuiltin.mjBUILTIN_CHECKER
        tex.rgb1 = rgba[:3]
        tex.rgb2 = [float(c * rng.uniform(0.6, 0.9)) for c in rgba[:3]]
        tex.width = tex.height = 64
        mat = spec.add_material()
        mat.name = "table_mat"
        mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "table_tex"
        mat.texrepeat = [float(rng.integers(2, 8))] * 2
        material = "table_mat"
    else:
        material = ""
    table = spec.worldbody.add_geom()
    table.name = "table"
    table.type = mujoco.mjtGeom.mjGEOM_BOX
    table.size = list(TABLE_HALF)
    table.pos = [TABLE_CENTER_XY[0], TABLE_CENTER_XY[1], TABLE_TOP_Z - TABLE_HALF[2]]
    table.rgba = rgba
    table.friction = [0.8, 0.01, 0.001]
    table.condim = 4
    if material:
        table.material = material
    floor = spec.worldbody.add_geom()
    floor.name = "floor"
    floor.type = mujoco.mjtGeom.mjGEOM_PLANE
    floor.size = [3, 3, 0.1]
    floor.pos = [0, 0, -0.75]
    floor.rgba = [0.35, 0.35, 0.38, 1.0]


def build_base_scene(
    rng: np.random.Generator, randomization: Randomization, rig: CameraRig
) -> tuple[mujoco.MjSpec, SceneHandles]:
    """A spec with physics options, lights, table, floor, robot and cameras; tasks add the rest."""
    spec = mujoco.MjSpec()
    spec.modelname = "keygen_scene"
    recommended_options(spec)
    spec.visual.quality.shadowsize = 0
    spec.stat.extent = 1.5
    spec.stat.center = [0.45, 0.0, 0.2]
    _add_lights(spec, rng, randomization.lighting)
    _add_table(spec, rng, randomization.colors)
    robot = add_robot(spec, base_pos=(0.0, 0.0, TABLE_TOP_Z))
    if randomization.camera:
        rig = rig.jittered(rng, randomization.camera_position_std, randomization.camera_fovy_std_deg)
    names = add_cameras(spec, rig)
    if rig.wrist:
        names = (*names, add_wrist_camera(spec.body(robot.hand_body), rig.wrist_fovy_deg))
    return spec, SceneHandles(robot=robot, camera_names=names, rig=rig)
