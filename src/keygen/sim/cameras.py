"""The RGB-D camera rig: placement in the scene and offscreen rendering of RGB, depth and masks.

Cameras are placed uniformly around the workspace (azimuths), all looking at one target point,
with configurable image size, vertical field of view, distance and elevation. Intrinsics and
extrinsics are reported in the OpenCV convention (see :mod:`keygen.geometry.cameras`):
``extrinsics[v]`` is the camera-to-world transform of view ``v``.

Rendering runs offscreen; on machines without a display set ``MUJOCO_GL=egl`` before importing
mujoco (this module sets it when unset). Shadows are off: with Mesa's software renderer a shadow
map costs ~30 ms a frame, without it an RGB frame costs ~1.5 ms at 128 x 128.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace

import numpy as np

from keygen.errors import InvalidParameterError
from keygen.geometry.cameras import intrinsics_from_fov, look_at, opencv_to_opengl, opengl_to_opencv
from keygen.geometry.rotations import matrix_to_quat_wxyz

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402


@dataclass(frozen=True)
class CameraRig:
    """Where the fixed cameras are and what they see."""

    width: int = 128
    height: int = 128
    fovy_deg: float = 50.0
    distance: float = 0.95  # metres from the target
    elevation_deg: float = 42.0  # above the horizontal
    azimuths_deg: tuple[float, ...] = (45.0, 135.0, 225.0, 315.0)
    target: tuple[float, float, float] = (0.5, 0.0, 0.05)
    near: float = 0.05
    far: float = 3.0
    # Per-camera offsets for domain randomisation (filled by `jittered`): metres and degrees.
    position_offsets: tuple[tuple[float, float, float], ...] = field(default_factory=tuple)
    fovy_offsets_deg: tuple[float, ...] = field(default_factory=tuple)
    # An optional camera on the robot's hand, looking along the approach axis past the fingers.
    wrist: bool = False
    wrist_fovy_deg: float = 75.0

    def __post_init__(self) -> None:
        if self.width < 8 or self.height < 8:
            raise InvalidParameterError(
                f"image size must be at least 8 x 8, got {self.width} x {self.height}"
            )
        if not 5.0 < self.fovy_deg < 150.0:
            raise InvalidParameterError(f"fovy_deg must be in (5, 150), got {self.fovy_deg}")
        if self.distance <= 0 or not self.azimuths_deg:
            raise InvalidParameterError("need a positive distance and at least one azimuth")
        for name in ("position_offsets", "fovy_offsets_deg"):
            value = getattr(self, name)
            if value and len(value) != len(self.azimuths_deg):
                raise InvalidParameterError(f"{name} needs one entry per camera ({len(self.azimuths_deg)})")

    @property
    def num_views(self) -> int:
        return len(self.azimuths_deg)

    @property
    def names(self) -> tuple[str, ...]:
        """Names of the fixed cameras (the wrist camera, when on, is ``WRIST_CAMERA``)."""
        return tuple(f"cam{i}" for i in range(self.num_views))

    @property
    def num_rendered(self) -> int:
        """Views in an observation: the fixed cameras, then the wrist camera if on."""
        return self.num_views + int(self.wrist)

    def fovy(self, view: int) -> float:
        return self.fovy_deg + (self.fovy_offsets_deg[view] if self.fovy_offsets_deg else 0.0)

    def eye(self, view: int) -> np.ndarray:
        az, el = np.deg2rad(self.azimuths_deg[view]), np.deg2rad(self.elevation_deg)
        offset = np.asarray(self.position_offsets[view]) if self.position_offsets else np.zeros(3)
        direction = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        return np.asarray(self.target) + self.distance * direction + offset

    def extrinsics(self) -> np.ndarray:
        """(V, 4, 4) camera-to-world transforms, OpenCV convention."""
        return np.stack(
            [look_at(self.eye(v), np.asarray(self.target, dtype=float)) for v in range(self.num_views)]
        )

    def intrinsics(self) -> np.ndarray:
        """(V, 3, 3) pinhole intrinsics."""
        return np.stack(
            [intrinsics_from_fov(self.width, self.height, self.fovy(v)) for v in range(self.num_views)]
        )

    def jittered(
        self, rng: np.random.Generator, position_std: float = 0.01, fovy_std_deg: float = 1.5
    ) -> CameraRig:
        """A copy with each camera's position and field of view perturbed (domain randomisation)."""
        offsets = tuple(tuple(rng.normal(0.0, position_std, 3).tolist()) for _ in range(self.num_views))
        fovs = tuple(rng.normal(0.0, fovy_std_deg, self.num_views).tolist())
        return replace(self, position_offsets=offsets, fovy_offsets_deg=fovs)


WRIST_CAMERA = "robot/wrist_cam"


def tile_views(rgb: np.ndarray) -> np.ndarray:
    """(V, H, W, 3) views -> one image: a grid ceil(sqrt(V)) views wide, black where it runs short."""
    v, h, w = rgb.shape[:3]
    cols = int(np.ceil(np.sqrt(v)))
    rows = int(np.ceil(v / cols))
    padded = np.concatenate([rgb, np.zeros((rows * cols - v, h, w, 3), rgb.dtype)])
    return padded.reshape(rows, cols, h, w, 3).transpose(0, 2, 1, 3, 4).reshape(rows * h, cols * w, 3)


def add_wrist_camera(hand: mujoco.MjsBody, fovy_deg: float) -> str:
    """A camera on the hand, 6 cm beside the finger plane, looking along the approach (+z) axis."""
    cam = hand.add_camera()
    cam.name = WRIST_CAMERA
    cam.pos = [0.06, 0.0, 0.02]
    # MuJoCo cameras look along their -z: turn 180 degrees about x so they look along the hand's +z,
    # then tilt 12 degrees toward the fingers.
    tilt = np.deg2rad(12.0)
    R = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
    R = np.array([[np.cos(tilt), 0, -np.sin(tilt)], [0, 1, 0], [np.sin(tilt), 0, np.cos(tilt)]]) @ R
    cam.quat = matrix_to_quat_wxyz(R)
    cam.fovy = fovy_deg
    return cam.name


def add_cameras(spec: mujoco.MjSpec, rig: CameraRig) -> tuple[str, ...]:
    """Add the rig's fixed cameras to the world body; returns their names."""
    spec.visual.global_.offwidth = max(spec.visual.global_.offwidth, rig.width)
    spec.visual.global_.offheight = max(spec.visual.global_.offheight, rig.height)
    spec.visual.quality.shadowsize = 0
    # No multisampling: 4x MSAA triples the cost of a frame in software rendering.
    spec.visual.quality.offsamples = 0
    # Coarser tessellation of primitives (the robot's capsules): a third of the vertex work.
    spec.visual.quality.numslices = 16
    spec.visual.quality.numstacks = 8
    T_cv = rig.extrinsics()
    for view, name in enumerate(rig.names):
        T_gl = opencv_to_opengl(T_cv[view])
        cam = spec.worldbody.add_camera()
        cam.name = name
        cam.pos = T_gl[:3, 3]
        cam.quat = matrix_to_quat_wxyz(T_gl[:3, :3])
        cam.fovy = rig.fovy(view)
    return rig.names


@dataclass
class RenderedViews:
    """Images of every view, stacked: ``rgb`` (V, H, W, 3) uint8, ``depth`` (V, H, W) float32 metres
    (0 where nothing was hit), ``geom_ids`` (V, H, W) int32 MuJoCo geom id per pixel (-1: none),
    ``intrinsics`` (V, 3, 3), ``extrinsics`` (V, 4, 4) camera-to-world, OpenCV convention."""

    rgb: np.ndarray | None
    depth: np.ndarray
    geom_ids: np.ndarray
    intrinsics: np.ndarray
    extrinsics: np.ndarray


class MultiViewRenderer:
    """Renders RGB, depth and geom-id masks of named cameras of a compiled model."""

    def __init__(self, model: mujoco.MjModel, camera_names: tuple[str, ...], width: int, height: int) -> None:
        self.model = model
        self.width, self.height = width, height
        self.camera_ids = []
        for name in camera_names:
            cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, name)
            if cam_id < 0:
                raise InvalidParameterError(f"camera {name!r} is not in the model")
            self.camera_ids.append(cam_id)
        self._renderer = mujoco.Renderer(model, height, width)
        self._rgb_buf = np.empty((height, width, 3), np.uint8)
        self._depth_buf = np.empty((height, width), np.float32)
        # Only the visual groups 0-2 are seen; collision parts (group 3) stay invisible.
        self._option = mujoco.MjvOption()
        self._option.geomgroup[:] = [1, 1, 1, 0, 0, 0]
        self._option.sitegroup[:] = 0  # sites (the tcp marker) are for debugging, not for cameras

    def close(self) -> None:
        self._renderer.close()

    def __enter__(self) -> MultiViewRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def camera_parameters(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """(V, 3, 3) intrinsics and (V, 4, 4) OpenCV camera-to-world extrinsics of the current state."""
        Ks, Ts = [], []
        for cam_id in self.camera_ids:
            Ks.append(intrinsics_from_fov(self.width, self.height, float(self.model.cam_fovy[cam_id])))
            T_gl = np.eye(4)
            T_gl[:3, :3] = data.cam_xmat[cam_id].reshape(3, 3)
            T_gl[:3, 3] = data.cam_xpos[cam_id]
            Ts.append(opengl_to_opencv(T_gl))
        return np.stack(Ks), np.stack(Ts)

    def _depth_and_ids(self, data: mujoco.MjData, cam_id: int) -> tuple[np.ndarray, np.ndarray]:
        """Depth (metres, 0 = nothing) and geom ids (-1 = none) of one view from a single pass.

        mujoco.Renderer reads depth and segmentation in two separate renders; both buffers come
        from the same segmentation frame, so we render once and read both (halves the cost).
        """
        r = self._renderer
        r.update_scene(data, cam_id, scene_option=self._option)
        scene = r.scene
        flags = scene.flags.copy()
        scene.flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = True
        scene.flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = True
        try:
            if r._gl_context:
                r._gl_context.make_current()
            mujoco.mjr_render(r._rect, scene, r._mjr_context)
            mujoco.mjr_readPixels(self._rgb_buf, self._depth_buf, r._rect, r._mjr_context)
        finally:
            np.copyto(scene.flags, flags)
        # Depth: undo the reversed-z perspective projection (as mujoco.Renderer does).
        extent = self.model.stat.extent
        near, far = self.model.vis.map.znear * extent, self.model.vis.map.zfar * extent
        c = -0.5 * (-(far + near) / (far - near)) - 0.5
        d = -0.5 * (-(2.0 * far * near) / (far - near))
        depth = (d / (self._depth_buf.astype(np.float64) + c)).astype(np.float32)
        # Segmentation colours encode scene-geom index + 1; map them to model geom ids.
        seg = self._rgb_buf.astype(np.int64)
        segid = seg[..., 0] + (seg[..., 1] << 8) + (seg[..., 2] << 16)
        lookup = np.full(scene.ngeom + 1, -1, np.int32)
        for g in scene.geoms[: scene.ngeom]:
            if g.segid != -1 and g.objtype == int(mujoco.mjtObj.mjOBJ_GEOM):
                lookup[g.segid + 1] = g.objid
        ids = lookup[np.clip(segid, 0, scene.ngeom)]
        depth = np.where(ids >= 0, depth, 0.0).astype(np.float32)
        return np.flipud(depth), np.flipud(ids)

    def render(self, data: mujoco.MjData, rgb: bool = True) -> RenderedViews:
        r = self._renderer
        v, h, w = len(self.camera_ids), self.height, self.width
        rgbs = np.zeros((v, h, w, 3), np.uint8) if rgb else None
        depth = np.zeros((v, h, w), np.float32)
        ids = np.zeros((v, h, w), np.int32)
        r.disable_depth_rendering()
        r.disable_segmentation_rendering()
        for i, cam_id in enumerate(self.camera_ids):
            if rgb:
                r.update_scene(data, cam_id, scene_option=self._option)
                rgbs[i] = r.render()
            depth[i], ids[i] = self._depth_and_ids(data, cam_id)
        K, T = self.camera_parameters(data)
        return RenderedViews(rgbs, depth, ids, K, T)
