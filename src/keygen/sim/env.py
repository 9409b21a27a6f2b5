"""The gymnasium environment shared by the three tasks.

``reset(seed)`` composes a fresh scene for the episode (table, robot, cameras, the task's objects,
randomisation drawn from the seed), so the same seed gives the same episode. ``step(action)``
tracks an absolute end-effector target (position 3 + 6D rotation 6 + gripper 1) for one 10 Hz
control period and returns the observation::

    rgb               (V, H, W, 3) uint8          per view (omitted with include_rgb=False); V = 4 fixed
                                                  views, + the wrist camera with wrist_camera=True
    depth             (V, H, W) float32 metres    0 where nothing was hit
    segmentation      (V, H, W) int32             task object label (1 = manipulated object), 0 else
    intrinsics        (V, 3, 3) float32           pinhole, OpenCV convention
    extrinsics        (V, 4, 4) float32           camera-to-world, OpenCV convention
    proprio           (10,) float32               the tcp pose (position, 6D) and gripper opening
    object_cloud      (N, 3) float32              task objects only, world frame
    object_cloud_ids  (N,) int32                  label of the object each point came from
    scene_cloud       (N, 3) float32              workspace crop, no masks

``info`` carries ``success``, ``failure`` (a reason once the episode is lost), the task's
``metrics``, the privileged ``anchors`` in the world frame and the ``objects`` of the episode.
A physics instability (NaN or exploding velocities) ends the episode as a failure with the reason
``physics_unstable``; it never raises out of ``step``.
"""

from __future__ import annotations

import importlib
import os
from functools import lru_cache
from typing import Any

import gymnasium as gym
import numpy as np

from keygen.errors import InvalidParameterError
from keygen.objects.asset import Asset
from keygen.objects.splits import SPLITS, make_instance
from keygen.perception.fusion import FusionConfig, make_clouds
from keygen.perception.segmenters import Segmenter, SimulatorSegmenter
from keygen.sim.cameras import CameraRig, MultiViewRenderer, tile_views
from keygen.sim.controller import ACTION_DIM, EndEffectorController, validate_target
from keygen.sim.randomization import Randomization
from keygen.sim.registration import ENV_IDS  # noqa: F401  (re-exported)
from keygen.sim.robot import set_home
from keygen.sim.scene import TABLE_TOP_Z, build_base_scene
from keygen.sim.tasks.base import SETTINGS, Task, TaskStatus

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402

TASKS = {
    "pour": "keygen.sim.tasks.pour:PourTask",
    "knife": "keygen.sim.tasks.knife:KnifeTask",
    "stack": "keygen.sim.tasks.stack:StackTask",
}
SETTLE_SECONDS = 0.3
MAX_QVEL = 200.0  # rad/s or m/s; anything beyond is a blown-up simulation


def task_class(name: str) -> type[Task]:
    if name not in TASKS:
        raise InvalidParameterError(f"task must be one of {sorted(TASKS)}, got {name!r}")
    module, cls = TASKS[name].split(":")
    return getattr(importlib.import_module(module), cls)


@lru_cache(maxsize=64)
def cached_instance(category: str, split: str, index: int, seed: int) -> Asset:
    """Procedural instances are pure functions of their ids: build each once per process."""
    return make_instance(category, split, index, seed)


class KeyGenEnv(gym.Env):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        task: str = "pour",
        object_split: str = "test",
        object_id: int = 0,
        setting: str = "easy",
        scale: float = 1.0,
        randomize: bool | str | dict | Randomization = False,
        image_size: int = 128,
        num_points: int = 1024,
        include_rgb: bool = True,
        camera_rig: CameraRig | None = None,
        wrist_camera: bool = False,
        asset: Asset | None = None,
        object_seed: int = 0,
        segmenter: Segmenter | None = None,
        render_mode: str | None = None,
    ) -> None:
        super().__init__()
        self.task_name = task
        self._task_cls = task_class(task)
        if object_split not in SPLITS:
            raise InvalidParameterError(f"object_split must be one of {SPLITS}, got {object_split!r}")
        if setting not in SETTINGS:
            raise InvalidParameterError(f"setting must be one of {SETTINGS}, got {setting!r}")
        if not (np.isfinite(scale) and 0.2 <= scale <= 3.0):
            raise InvalidParameterError(f"scale must be in [0.2, 3.0], got {scale}")
        if render_mode not in (None, "rgb_array"):
            raise InvalidParameterError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.object_split, self.object_id, self.setting, self.scale = (
            object_split,
            int(object_id),
            setting,
            scale,
        )
        self.object_seed = int(object_seed)
        self.randomization = Randomization.parse(randomize)
        self.rig = camera_rig or CameraRig(width=int(image_size), height=int(image_size), wrist=wrist_camera)
        self.fusion = FusionConfig(num_points=int(num_points))
        self.include_rgb = include_rgb
        self.render_mode = render_mode
        self._custom_asset = asset
        self._custom_segmenter = segmenter
        self.max_steps = self._task_cls.max_steps

        v, h, w, n = self.rig.num_rendered, self.rig.height, self.rig.width, self.fusion.num_points
        spaces: dict[str, gym.Space] = {}
        if include_rgb:
            spaces["rgb"] = gym.spaces.Box(0, 255, (v, h, w, 3), np.uint8)
        spaces.update(
            # Bounds are physical: the scene lies within a few metres of the origin.
            depth=gym.spaces.Box(0.0, 10.0, (v, h, w), np.float32),
            segmentation=gym.spaces.Box(0, 255, (v, h, w), np.int32),
            intrinsics=gym.spaces.Box(-1e5, 1e5, (v, 3, 3), np.float32),
            extrinsics=gym.spaces.Box(-10.0, 10.0, (v, 4, 4), np.float32),
            proprio=gym.spaces.Box(-5.0, 5.0, (ACTION_DIM,), np.float32),
            object_cloud=gym.spaces.Box(-5.0, 5.0, (n, 3), np.float32),
            object_cloud_ids=gym.spaces.Box(0, 255, (n,), np.int32),
            scene_cloud=gym.spaces.Box(-5.0, 5.0, (n, 3), np.float32),
        )
        self.observation_space = gym.spaces.Dict(spaces)
        low = np.array([-1.5, -1.5, -0.5] + [-1.0] * 6 + [0.0], np.float32)
        high = np.array([1.5, 1.5, 1.5] + [1.0] * 6 + [1.0], np.float32)
        self.action_space = gym.spaces.Box(low, high, dtype=np.float32)

        self.model: mujoco.MjModel | None = None
        self.data: mujoco.MjData | None = None
        self.task: Task | None = None
        self._renderer: MultiViewRenderer | None = None
        self._last_views = None
        self._steps = 0
        self._done_reason: str | None = None

    # -- episode set-up ----------------------------------------------------------------------
    def manipulated_asset(self) -> Asset:
        if self._custom_asset is not None:
            asset = self._custom_asset
        else:
            asset = cached_instance(
                self._task_cls.category, self.object_split, self.object_id, self.object_seed
            )
        return asset if self.scale == 1.0 else asset.scaled(self.scale)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        # One generator drives every draw of the episode: scene, randomisation and task layout.
        rng = np.random.default_rng(self.np_random.integers(2**63))
        spec, scene = build_base_scene(rng, self.randomization, self.rig)
        self.scene = scene
        self.task = self._task_cls(self.manipulated_asset(), self.setting, rng, self.randomization)
        self.task.populate(spec)
        sleep_flag = getattr(mujoco.mjtEnableBit, "mjENBL_SLEEP", None)  # MuJoCo >= 3.4
        if self.task.sleep_at_rest and sleep_flag is not None:
            spec.option.enableflags |= int(sleep_flag)
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self.task.bind(self.model, self.data)
        if self.randomization.physics:
            self._randomize_physics(rng)
        set_home(self.model, self.data, scene.robot, gripper=1.0)
        self.controller = EndEffectorController(self.model, scene.robot)
        self.controller.reset(self.model, self.data)
        for _ in range(int(SETTLE_SECONDS / self.model.opt.timestep)):
            mujoco.mj_step(self.model, self.data)
        self.task.settle(self.model, self.data)
        self.controller.reset(self.model, self.data)
        if self._renderer is not None:
            self._renderer.close()
        self._renderer = MultiViewRenderer(self.model, scene.camera_names, self.rig.width, self.rig.height)
        self._segmenter = self._custom_segmenter or SimulatorSegmenter(self.task.geom_labels(self.model))
        self._steps = 0
        self._done_reason = None
        obs = self._observe()
        return obs, self._info(self.task.status(self.model, self.data))

    def _randomize_physics(self, rng: np.random.Generator) -> None:
        r = self.randomization
        for obj in self.task.objects:
            if obj.asset is None:
                continue
            factor = float(rng.uniform(*r.mass_range))
            self.model.body_mass[obj.body_id] *= factor
            self.model.body_inertia[obj.body_id] *= factor
            geoms = np.flatnonzero((self.model.geom_bodyid == obj.body_id) & (self.model.geom_contype > 0))
            self.model.geom_friction[geoms, 0] *= float(rng.uniform(*r.friction_range))

    # -- stepping ------------------------------------------------------------------------------
    def step(self, action):
        if self.model is None:
            raise InvalidParameterError("call reset() before step()")
        target = validate_target(np.asarray(action, dtype=np.float64))
        if self._done_reason is None:
            try:
                self.controller.step(self.model, self.data, target)
            except Exception as exc:  # noqa: BLE001 - the IK or the physics failed: end the episode
                self._done_reason = f"controller_error: {type(exc).__name__}"
            if self._done_reason is None and self._unstable():
                self._done_reason = "physics_unstable"
            if self._done_reason is None:
                self.task.update(self.model, self.data)
        self._steps += 1
        if self._done_reason is not None:
            status = (
                self.task.status(self.model, self.data) if self._done_reason != "physics_unstable" else None
            )
            status = status or TaskStatus(success=False, failure=self._done_reason)
            status.success, status.failure = False, self._done_reason
            obs = self._observe() if self._done_reason != "physics_unstable" else self._blank_observation()
            return obs, 0.0, True, False, self._info(status)
        status = self.task.status(self.model, self.data)
        terminated = bool(status.success or status.failure is not None)
        truncated = bool(not terminated and self._steps >= self.max_steps)
        if truncated and status.failure is None:
            status.failure = "timeout"
        return self._observe(), float(status.success), terminated, truncated, self._info(status)

    def _unstable(self) -> bool:
        d = self.data
        warn = d.warning[mujoco.mjtWarning.mjWARN_BADQACC].number > 0
        return bool(warn or not np.all(np.isfinite(d.qpos)) or np.max(np.abs(d.qvel)) > MAX_QVEL)

    # -- observation ---------------------------------------------------------------------------
    def _observe(self) -> dict[str, np.ndarray]:
        views = self._renderer.render(self.data, rgb=self.include_rgb or self.render_mode == "rgb_array")
        self._last_views = views
        labels = self._segmenter(views.rgb, views.depth, views.geom_ids).astype(np.int32)
        cloud, ids, scene = make_clouds(
            views.depth, views.intrinsics, views.extrinsics, labels, TABLE_TOP_Z, self.fusion
        )
        obs = {}
        if self.include_rgb:
            obs["rgb"] = views.rgb
        obs.update(
            depth=views.depth.astype(np.float32),
            segmentation=labels,
            intrinsics=views.intrinsics.astype(np.float32),
            extrinsics=views.extrinsics.astype(np.float32),
            proprio=self.controller.proprioception(self.model, self.data).astype(np.float32),
            object_cloud=cloud,
            object_cloud_ids=ids,
            scene_cloud=scene,
        )
        return obs

    def _blank_observation(self) -> dict[str, np.ndarray]:
        return {k: np.zeros(s.shape, s.dtype) for k, s in self.observation_space.spaces.items()}

    def _info(self, status) -> dict[str, Any]:
        anchors = {}
        if self._done_reason != "physics_unstable":
            anchors = self.task.anchors_world(self.model, self.data)
        return {
            "success": bool(status.success),
            "failure": status.failure,
            "metrics": dict(status.metrics),
            "anchors": anchors,
            "objects": self.task.object_ids(),
            "step": self._steps,
            "task": self.task_name,
            "setting": self.setting,
            "scale": self.scale,
        }

    def render(self):
        if self.render_mode != "rgb_array" or self._last_views is None or self._last_views.rgb is None:
            return None
        return tile_views(self._last_views.rgb)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
