import mujoco
import numpy as np
import pytest
import trimesh

from _assets import simple_bowl
from keygen.errors import InvalidParameterError
from keygen.geometry.clouds import nearest_distances
from keygen.perception import (
    FusionConfig,
    SimulatorSegmenter,
    make_clouds,
    make_object_cloud,
    make_scene_cloud,
)
from keygen.sim.cameras import CameraRig, MultiViewRenderer, add_cameras
from keygen.sim.object_bodies import add_object


@pytest.fixture(scope="module")
def bowl_scene():
    asset = simple_bowl()
    spec = mujoco.MjSpec()
    table = spec.worldbody.add_geom()
    table.name = "table"
    table.type = mujoco.mjtGeom.mjGEOM_BOX
    table.size = [0.6, 0.6, 0.02]
    table.pos = [0.5, 0, -0.02]
    light = spec.worldbody.add_light()
    light.pos = [0.5, 0, 2.0]
    pos = np.array([0.5, 0.05, 0.0])
    handles = add_object(spec, asset, "bowl", pos=pos, free=False)
    rig = CameraRig(width=96, height=96)
    names = add_cameras(spec, rig)
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    labels = np.zeros(model.ngeom, np.int32)
    labels[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, handles.visual_geom)] = 1
    with MultiViewRenderer(model, names, rig.width, rig.height) as renderer:
        views = renderer.render(data)
    world_mesh = asset.visual.copy().apply_translation(pos)
    return asset, world_mesh, views, SimulatorSegmenter(labels), rig


def test_rig_extrinsics_match_the_rendered_cameras(bowl_scene):
    _, _, views, _, rig = bowl_scene
    np.testing.assert_allclose(views.extrinsics, rig.extrinsics(), atol=1e-6)
    np.testing.assert_allclose(views.intrinsics, rig.intrinsics(), atol=1e-9)
    assert views.rgb.shape == (4, 96, 96, 3) and views.rgb.dtype == np.uint8
    assert views.depth.dtype == np.float32


def test_object_cloud_lies_on_the_object(bowl_scene):
    asset, mesh, views, segment, _ = bowl_scene
    labels = segment(views.rgb, views.depth, views.geom_ids)
    cloud, ids = make_object_cloud(views.depth, views.intrinsics, views.extrinsics, labels, FusionConfig(512))
    assert cloud.shape == (512, 3) and ids.shape == (512,)
    assert np.all(ids == 1)
    surface = mesh.sample(20000, seed=0)
    d = nearest_distances(cloud.astype(float), surface)
    assert np.mean(d < 0.005) >= 0.99


def test_scene_cloud_has_no_table(bowl_scene):
    _, mesh, views, _, _ = bowl_scene
    cloud = make_scene_cloud(views.depth, views.intrinsics, views.extrinsics, 0.0, FusionConfig(256))
    assert cloud.shape == (256, 3)
    assert cloud[:, 2].min() >= 0.006 - 1e-6
    # what is left is the bowl
    assert np.all(trimesh.proximity.ProximityQuery(mesh).signed_distance(cloud) > -0.006)


def test_bad_config():
    with pytest.raises(InvalidParameterError):
        FusionConfig(num_points=0)
    with pytest.raises(InvalidParameterError):
        CameraRig(fovy_deg=200)


def test_make_clouds_equals_the_two_separate_fusions(bowl_scene):
    _, _, views, segment, _ = bowl_scene
    labels = segment(views.rgb, views.depth, views.geom_ids)
    config = FusionConfig(256)
    K, T = views.intrinsics, views.extrinsics
    cloud, ids, scene = make_clouds(views.depth, K, T, labels, 0.0, config)
    ref_cloud, ref_ids = make_object_cloud(views.depth, K, T, labels, config)
    np.testing.assert_array_equal(cloud, ref_cloud)
    np.testing.assert_array_equal(ids, ref_ids)
    np.testing.assert_array_equal(scene, make_scene_cloud(views.depth, K, T, 0.0, config))
