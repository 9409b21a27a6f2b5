"""Partial scans of single objects: training and evaluation data of the keypoint detector.

A :class:`ScanGenerator` renders one object of a category split alone in an empty MuJoCo scene (no
table, no robot) at a random pose, from 1 to 4 cameras at random azimuths and elevations around it,
fuses the masked depth views into a world-frame cloud and down-samples it to exactly ``num_points``.
Each :class:`Scan` carries the ground truth a keypoint detector is trained and scored against: the
object's pose (canonical -> world), its anchors in the world frame and its size.

Poses: ``"table"`` reproduces the poses the tasks produce (mug and bowl upright with any yaw, the
knife lying flat with any yaw, face up or turned over about its x axis), with the object resting on
the plane z = 0 plus a horizontal offset; ``"any"`` draws a uniform random rotation.

One compiled model per instance is kept (an LRU cache): a scan moves the body and the single camera
through ``qpos`` / ``cam_pos`` and re-renders, which costs milliseconds instead of a recompile.
"""

from __future__ import annotations

import contextlib
import os
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

# keygen/__init__.py, imported before this module, sets MUJOCO_GL=egl before mujoco loads.
import mujoco
import numpy as np
import trimesh

from keygen.errors import InvalidParameterError, KeyGenError
from keygen.geometry.cameras import look_at, opencv_to_opengl
from keygen.geometry.clouds import farthest_point_sample, voxel_downsample
from keygen.geometry.rotations import axis_angle_to_matrix, matrix_to_quat_wxyz, random_rotation, yaw_matrix
from keygen.objects.asset import CATEGORIES, Asset
from keygen.objects.splits import DEFAULT_SEED, SPLIT_SIZES, SPLITS, make_instance
from keygen.perception.fusion import fuse_views
from keygen.sim.cameras import CameraRig, MultiViewRenderer, add_cameras
from keygen.sim.object_bodies import add_object

POSE_MODES = ("table", "any")
MAX_VIEWS = 8
OBJECT_BODY = "object"
_CAMERA = "scan_cam"
_SCAN_FORMAT_VERSION = 1


@dataclass
class Scan:
    """One fused partial scan with its ground truth.

    ``points`` (N, 3) float32 world frame; ``rotation`` (3, 3) and ``translation`` (3,) map the
    canonical frame to the world (x_world = R x + t); ``scale`` is the asset's scale; ``anchors_world``
    holds the asset's anchors in the world frame (points moved, directions rotated, scalars as they
    are); ``diameter`` is the diameter of the object's minimum bounding sphere (metres).
    """

    points: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    scale: float
    instance_id: str
    anchors_world: dict[str, np.ndarray] = field(default_factory=dict)
    diameter: float = 0.0
    num_views: int = 0

    @property
    def transform(self) -> np.ndarray:
        """(4, 4) canonical -> world transform."""
        T = np.eye(4)
        T[:3, :3] = self.rotation
        T[:3, 3] = self.translation
        return T


@dataclass
class _InstanceScene:
    """A compiled single-object scene and what a scan needs from it."""

    asset: Asset
    model: mujoco.MjModel
    data: mujoco.MjData
    renderer: MultiViewRenderer
    qpos_adr: int
    camera_id: int
    geom_ids: np.ndarray
    sphere_center: np.ndarray  # canonical frame
    sphere_radius: float

    def close(self) -> None:
        self.renderer.close()


def _bounding_sphere(mesh: trimesh.Trimesh) -> tuple[np.ndarray, float]:
    """Centre and radius of the minimum sphere enclosing the mesh (computed on its hull)."""
    hull = np.asarray(mesh.convex_hull.vertices, dtype=np.float64)
    center, radius = trimesh.nsphere.minimum_nsphere(hull)
    return np.asarray(center, dtype=np.float64), float(radius)


class ScanGenerator:
    """Random single-object scans of the instances of one category split.

    ``seed`` is the seed of the object split (:func:`keygen.objects.splits.make_instance`), so instance
    ``i`` here is the same object as everywhere else; the randomness of each scan comes from the
    generator or seed passed to :meth:`scan`, :meth:`pair`, :meth:`dataset` or :meth:`iterate_pairs`.
    ``depth_noise`` is the standard deviation (metres) of Gaussian noise added to each depth pixel;
    ``dropout`` the fraction of object pixels removed before back-projection.
    """

    def __init__(
        self,
        category: str,
        split: str = "train",
        num_points: int = 1024,
        image_size: int = 96,
        views: tuple[int, int] = (1, 4),
        pose_mode: str = "table",
        depth_noise: float = 0.0,
        dropout: float = 0.0,
        seed: int = DEFAULT_SEED,
        num_instances: int | None = None,
        voxel_size: float = 0.002,
        position_offset: float = 0.05,
        fovy_deg: float = 50.0,
        cache_size: int = 8,
    ) -> None:
        if category not in CATEGORIES:
            raise InvalidParameterError(f"category must be one of {CATEGORIES}, got {category!r}")
        if split not in SPLITS:
            raise InvalidParameterError(f"split must be one of {SPLITS}, got {split!r}")
        if pose_mode not in POSE_MODES:
            raise InvalidParameterError(f"pose_mode must be one of {POSE_MODES}, got {pose_mode!r}")
        _check_int("num_points", num_points, 1, 1 << 20)
        _check_int("image_size", image_size, 16, 1024)
        _check_int("cache_size", cache_size, 1, 1024)
        self.views = _check_views(views)
        for name, value in (("depth_noise", depth_noise), ("position_offset", position_offset)):
            if not np.isfinite(value) or value < 0:
                raise InvalidParameterError(f"{name} must be a finite length >= 0 (metres), got {value}")
        if not 0.0 <= dropout < 1.0:
            raise InvalidParameterError(f"dropout must be a fraction in [0, 1), got {dropout}")
        if not np.isfinite(voxel_size) or voxel_size <= 0:
            raise InvalidParameterError(f"voxel_size must be a positive length (metres), got {voxel_size}")
        if not 10.0 <= fovy_deg <= 120.0:
            raise InvalidParameterError(f"fovy_deg must be in [10, 120], got {fovy_deg}")
        self.num_instances = SPLIT_SIZES[split] if num_instances is None else num_instances
        _check_int("num_instances", self.num_instances, 1, 1 << 20)
        self.category, self.split, self.seed = category, split, int(seed)
        self.num_points, self.image_size, self.pose_mode = int(num_points), int(image_size), pose_mode
        self.depth_noise, self.dropout = float(depth_noise), float(dropout)
        self.voxel_size, self.position_offset, self.fovy_deg = (
            float(voxel_size),
            float(position_offset),
            fovy_deg,
        )
        self.cache_size = int(cache_size)
        self._scenes: OrderedDict[int, _InstanceScene] = OrderedDict()

    # -- lifecycle ------------------------------------------------------------------------------
    def close(self) -> None:
        """Free the renderers (GL contexts) of the cached scenes."""
        while self._scenes:
            self._scenes.popitem(last=False)[1].close()

    def __enter__(self) -> ScanGenerator:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):  # interpreter shutdown: GL may already be gone
            self.close()

    def asset(self, instance_index: int) -> Asset:
        return self._scene(instance_index).asset

    # -- scans ----------------------------------------------------------------------------------
    def scan(self, instance_index: int, rng: np.random.Generator | int) -> Scan:
        """One scan of instance ``instance_index`` at a random pose from random views."""
        gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        scene = self._scene(instance_index)
        rotation, translation = self._sample_pose(scene, gen)
        scene.data.qpos[scene.qpos_adr : scene.qpos_adr + 3] = translation
        scene.data.qpos[scene.qpos_adr + 3 : scene.qpos_adr + 7] = matrix_to_quat_wxyz(rotation)
        mujoco.mj_kinematics(scene.model, scene.data)
        center = rotation @ scene.sphere_center + translation
        num_views = int(gen.integers(self.views[0], self.views[1] + 1))
        depth, labels, Ks, Ts = self._render_views(scene, center, num_views, gen)
        depth = self._corrupt(depth, labels, gen)
        points, _ = fuse_views(depth, Ks, Ts, labels, max_depth=np.inf)
        return Scan(
            points=self._downsample(points),
            rotation=rotation,
            translation=translation,
            scale=float(scene.asset.scale),
            instance_id=scene.asset.instance_id,
            anchors_world=_anchors_in_world(scene.asset, rotation, translation),
            diameter=2.0 * scene.sphere_radius,
            num_views=num_views,
        )

    def pair(self, instance_index: int, rng: np.random.Generator | int) -> tuple[Scan, Scan]:
        """Two independent scans (pose, views, noise) of the same object."""
        gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        return self.scan(instance_index, gen), self.scan(instance_index, gen)

    def dataset(self, count: int, seed: int) -> list[Scan]:
        """``count`` scans of instances drawn uniformly from the split; the same for the same seed."""
        _check_int("count", count, 0, 1 << 30)
        gen = np.random.default_rng(seed)
        return [self.scan(int(gen.integers(self.num_instances)), gen) for _ in range(count)]

    def iterate_pairs(
        self, batch_size: int, seed: int, num_batches: int | None = None
    ) -> Iterator[list[tuple[Scan, Scan]]]:
        """Batches of scan pairs of random instances (endless unless ``num_batches`` is given)."""
        _check_int("batch_size", batch_size, 1, 1 << 20)
        if num_batches is not None:
            _check_int("num_batches", num_batches, 0, 1 << 40)
        gen = np.random.default_rng(seed)
        done = 0
        while num_batches is None or done < num_batches:
            yield [self.pair(int(gen.integers(self.num_instances)), gen) for _ in range(batch_size)]
            done += 1

    # -- internals ------------------------------------------------------------------------------
    def _scene(self, instance_index: int) -> _InstanceScene:
        index = int(instance_index)
        if not 0 <= index < self.num_instances:
            raise InvalidParameterError(
                f"instance_index must be in [0, {self.num_instances}) for the {self.split} split of "
                f"{self.category}, got {instance_index}"
            )
        if index in self._scenes:
            self._scenes.move_to_end(index)
            return self._scenes[index]
        scene = self._build_scene(make_instance(self.category, self.split, index, self.seed))
        self._scenes[index] = scene
        if len(self._scenes) > self.cache_size:  # evict the least recently used, freeing its GL context
            self._scenes.popitem(last=False)[1].close()
        return scene

    def _build_scene(self, asset: Asset) -> _InstanceScene:
        spec = mujoco.MjSpec()
        add_object(spec, asset, OBJECT_BODY, free=True)
        # One camera, moved for every view: rendering only the views a scan needs.
        rig = CameraRig(
            width=self.image_size,
            height=self.image_size,
            fovy_deg=self.fovy_deg,
            distance=1.0,
            azimuths_deg=(0.0,),
            target=(0.0, 0.0, 0.0),
        )
        add_cameras(spec, rig)
        spec.cameras[-1].name = _CAMERA
        model = spec.compile()
        data = mujoco.MjData(model)
        body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, OBJECT_BODY)
        joint_id = int(model.body_jntadr[body_id])
        center, radius = _bounding_sphere(asset.visual)
        return _InstanceScene(
            asset=asset,
            model=model,
            data=data,
            renderer=MultiViewRenderer(model, (_CAMERA,), self.image_size, self.image_size),
            qpos_adr=int(model.jnt_qposadr[joint_id]),
            camera_id=mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, _CAMERA),
            geom_ids=np.flatnonzero(model.geom_bodyid == body_id),
            sphere_center=center,
            sphere_radius=radius,
        )

    def _sample_pose(self, scene: _InstanceScene, gen: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        offset = np.zeros(3)
        if self.pose_mode == "any":
            rotation = random_rotation(gen)
            offset = gen.uniform(-self.position_offset, self.position_offset, 3)
            # Centre the bounding sphere on the offset so every object sits around the origin.
            return rotation, offset - rotation @ scene.sphere_center
        rotation = yaw_matrix(gen.uniform(0.0, 2.0 * np.pi))
        if self.category == "knife" and gen.random() < 0.5:
            # Face down: the flat canonical pose turned over about the knife's own x axis.
            rotation = rotation @ axis_angle_to_matrix(np.array([1.0, 0.0, 0.0]), np.pi)
        offset[:2] = gen.uniform(-self.position_offset, self.position_offset, 2)
        # Rest on the plane z = 0 as on the table: lift by the lowest vertex after rotation.
        lowest = float(np.min(np.asarray(scene.asset.visual.vertices) @ rotation[2]))
        offset[2] = -lowest
        return rotation, offset

    def _sample_camera(
        self, scene: _InstanceScene, target: np.ndarray, gen: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray]:
        """(eye, target) of one random view that frames the object's bounding sphere."""
        lo, hi = (10.0, 75.0) if self.pose_mode == "table" else (-75.0, 75.0)
        azimuth = gen.uniform(0.0, 2.0 * np.pi)
        elevation = np.deg2rad(gen.uniform(lo, hi))
        # The sphere fills 70-90 % of the vertical field of view.
        fill = gen.uniform(0.7, 0.9)
        distance = scene.sphere_radius / np.sin(np.deg2rad(self.fovy_deg) / 2.0) / fill
        aim = target + gen.normal(0.0, 0.05 * scene.sphere_radius, 3)
        direction = np.array(
            [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)]
        )
        return aim + distance * direction, aim

    def _render_views(
        self, scene: _InstanceScene, target: np.ndarray, num_views: int, gen: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Depth (V, H, W), object labels (V, H, W), intrinsics and OpenCV extrinsics of each view."""
        depths, labels, Ks, Ts = [], [], [], []
        for _ in range(num_views):
            eye, aim = self._sample_camera(scene, target, gen)
            T_gl = opencv_to_opengl(look_at(eye, aim))
            scene.model.cam_pos[scene.camera_id] = T_gl[:3, 3]
            scene.model.cam_quat[scene.camera_id] = matrix_to_quat_wxyz(T_gl[:3, :3])
            mujoco.mj_camlight(scene.model, scene.data)
            views = scene.renderer.render(scene.data, rgb=False)
            depths.append(views.depth[0])
            labels.append(np.isin(views.geom_ids[0], scene.geom_ids).astype(np.int32))
            Ks.append(views.intrinsics[0])
            Ts.append(views.extrinsics[0])
        return np.stack(depths), np.stack(labels), np.stack(Ks), np.stack(Ts)

    def _corrupt(self, depth: np.ndarray, labels: np.ndarray, gen: np.random.Generator) -> np.ndarray:
        """Sensor imperfections on the object's pixels: Gaussian depth noise and pixel dropout."""
        depth = depth.copy()
        on_object = labels > 0
        if self.depth_noise > 0:
            noise = gen.normal(0.0, self.depth_noise, depth.shape).astype(np.float32)
            depth[on_object] += noise[on_object]
        if self.dropout > 0:
            depth[on_object & (gen.random(depth.shape) < self.dropout)] = 0.0
        return depth

    def _downsample(self, points: np.ndarray) -> np.ndarray:
        if len(points) == 0:
            raise ScanError(
                f"a scan of {self.category} saw no object pixel; expected the cameras to frame it "
                "(check image_size, fovy_deg and dropout)"
            )
        # Voxels even out the density of near and far views before FPS spreads the points.
        points = voxel_downsample(points, self.voxel_size)
        return farthest_point_sample(points, self.num_points, method="fast").astype(np.float32)


class ScanError(KeyGenError):
    """A scan could not be made (e.g. the object was outside every view)."""


def _check_int(name: str, value: int, lo: int, hi: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= value <= hi:
        raise InvalidParameterError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")


def _check_views(views: int | Sequence[int]) -> tuple[int, int]:
    pair = (views, views) if isinstance(views, (int, np.integer)) else tuple(views)
    if (
        len(pair) != 2
        or not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in pair)
        or not 1 <= pair[0] <= pair[1] <= MAX_VIEWS
    ):
        raise InvalidParameterError(
            f"views must be an int or a (min, max) pair with 1 <= min <= max <= {MAX_VIEWS}, got {views!r}"
        )
    return int(pair[0]), int(pair[1])


def _anchors_in_world(asset: Asset, rotation: np.ndarray, translation: np.ndarray) -> dict[str, np.ndarray]:
    if asset.anchors is None:
        return {}
    return {
        name: anchor.transformed(rotation, translation).value.copy() for name, anchor in asset.anchors.items()
    }


# -- storage --------------------------------------------------------------------------------------
def save_scans(path: str | os.PathLike, scans: Sequence[Scan]) -> Path:
    """Write scans to a compressed .npz (plain arrays, no pickle); returns the path written."""
    path = Path(path)
    if path.suffix != ".npz":
        raise InvalidParameterError(f"scan files end in .npz, got {path.name!r}")
    scans = list(scans)
    counts = np.array([len(s.points) for s in scans], dtype=np.int64)
    names = sorted({name for s in scans for name in s.anchors_world})
    arrays: dict[str, np.ndarray] = {
        "version": np.array(_SCAN_FORMAT_VERSION),
        "points": np.concatenate([s.points for s in scans]).astype(np.float32)
        if scans
        else np.zeros((0, 3), np.float32),
        "counts": counts,
        "rotation": np.array([s.rotation for s in scans], dtype=np.float64).reshape(-1, 3, 3),
        "translation": np.array([s.translation for s in scans], dtype=np.float64).reshape(-1, 3),
        "scale": np.array([s.scale for s in scans], dtype=np.float64),
        "diameter": np.array([s.diameter for s in scans], dtype=np.float64),
        "num_views": np.array([s.num_views for s in scans], dtype=np.int64),
        "instance_id": np.array([s.instance_id for s in scans], dtype=np.str_).reshape(-1),
        "anchor_names": np.array(names, dtype=np.str_).reshape(-1),
    }
    for k, name in enumerate(names):
        # Anchors a scan lacks are stored as NaN rows (scans of several categories may share a file).
        size = max(len(s.anchors_world[name]) for s in scans if name in s.anchors_world)
        table = np.full((len(scans), size), np.nan)
        for i, s in enumerate(scans):
            if name in s.anchors_world:
                table[i] = s.anchors_world[name]
        arrays[f"anchor_{k}"] = table
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)
    return path


def load_scans(path: str | os.PathLike) -> list[Scan]:
    """Read scans written by :func:`save_scans`."""
    path = Path(path)
    if not path.is_file():
        raise ScanError(f"no scan file at {path}; write one with save_scans")
    with np.load(path, allow_pickle=False) as f:
        if int(f["version"]) != _SCAN_FORMAT_VERSION:
            raise ScanError(
                f"{path} has scan format {int(f['version'])}, this keygen reads {_SCAN_FORMAT_VERSION}; "
                "regenerate the scans"
            )
        d = {k: f[k] for k in f.files}
    offsets = np.concatenate([[0], np.cumsum(d["counts"])])
    names = [str(n) for n in d["anchor_names"]]
    scans = []
    for i in range(len(d["counts"])):
        anchors = {}
        for k, name in enumerate(names):
            row = d[f"anchor_{k}"][i]
            if not np.all(np.isnan(row)):
                anchors[name] = row.copy()
        scans.append(
            Scan(
                points=d["points"][offsets[i] : offsets[i + 1]].copy(),
                rotation=d["rotation"][i].copy(),
                translation=d["translation"][i].copy(),
                scale=float(d["scale"][i]),
                instance_id=str(d["instance_id"][i]),
                anchors_world=anchors,
                diameter=float(d["diameter"][i]),
                num_views=int(d["num_views"][i]),
            )
        )
    return scans
