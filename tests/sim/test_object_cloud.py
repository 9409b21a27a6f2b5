"""The object-centric cloud lies on the task objects, and never on the table or the robot."""

import gymnasium as gym
import mujoco
import numpy as np
import pytest
import trimesh

import keygen
from keygen.geometry.clouds import nearest_distances
from keygen.geometry.rotations import matrix_to_rot6d


def geom_mesh(model: mujoco.MjModel, data: mujoco.MjData, g: int) -> trimesh.Trimesh | None:
    """A geom's surface in the world frame (meshes, boxes, capsules, cylinders, spheres)."""
    kind, size = model.geom_type[g], model.geom_size[g]
    if kind == mujoco.mjtGeom.mjGEOM_MESH:
        m = model.geom_dataid[g]
        v0, nv = model.mesh_vertadr[m], model.mesh_vertnum[m]
        f0, nf = model.mesh_faceadr[m], model.mesh_facenum[m]
        mesh = trimesh.Trimesh(model.mesh_vert[v0 : v0 + nv], model.mesh_face[f0 : f0 + nf], process=False)
    elif kind == mujoco.mjtGeom.mjGEOM_BOX:
        mesh = trimesh.creation.box(extents=2 * size)
    elif kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
        mesh = trimesh.creation.capsule(height=2 * size[1], radius=size[0])
    elif kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
        mesh = trimesh.creation.cylinder(radius=size[0], height=2 * size[1])
    elif kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        mesh = trimesh.creation.icosphere(radius=size[0])
    else:
        return None
    tf = np.eye(4)
    tf[:3, :3] = data.geom_xmat[g].reshape(3, 3)
    tf[:3, 3] = data.geom_xpos[g]
    return mesh.apply_transform(tf)


def surface_points(model, data, geoms, count=40000):
    meshes = [m for m in (geom_mesh(model, data, g) for g in geoms) if m is not None]
    return trimesh.util.concatenate(meshes).sample(count, seed=0)


@pytest.mark.parametrize("task", ["pour", "knife", "stack"])
def test_object_cloud_lies_on_task_objects(task):
    env = gym.make(
        keygen.ENV_IDS[task],
        object_split="test",
        object_id=2,
        setting="hard",
        include_rgb=False,
        image_size=128,
        num_points=1024,
    ).unwrapped
    obs, info = env.reset(seed=4)
    # Bring the open gripper down close to the object so the robot is in view next to it.
    target = obs["proprio"].copy()
    anchor = info["anchors"]["handle_grasp" if task != "stack" else "rim_grasp"]
    target[:3] = anchor + np.array([0.0, 0.0, 0.09])
    target[3:9] = matrix_to_rot6d(np.diag([1.0, -1.0, -1.0]))  # tcp z pointing down
    for _ in range(8):
        obs, *_ = env.step(target)
    model, data = env.model, env.data
    labels = env.task.geom_labels(model)
    visual = model.geom_group < 3  # what the cameras see
    task_geoms = np.flatnonzero((labels > 0) & visual)
    robot_geoms = np.flatnonzero(
        [model.body(model.geom_bodyid[g]).name.startswith("robot/") for g in range(model.ngeom)] & visual
    )
    seen = env._last_views.geom_ids
    assert np.isin(seen, robot_geoms).sum() > 100, "the robot is in view, so the check means something"
    cloud = obs["object_cloud"].astype(float)
    assert set(np.unique(obs["object_cloud_ids"])) <= {1, 2}
    d_obj = nearest_distances(cloud, surface_points(model, data, task_geoms))
    assert np.mean(d_obj < 0.005) >= 0.99, f"{np.mean(d_obj < 0.005):.3f} of points on the objects"
    strays = cloud[d_obj >= 0.005]
    if len(strays):
        assert np.all(strays[:, 2] > 0.002), "a point lies on the table"
        d_robot = nearest_distances(strays, surface_points(model, data, robot_geoms, 20000))
        assert np.all(d_robot > 0.003), "a point lies on the robot"
    env.close()
