"""Typed policy configurations, validated on construction, and the registry of named policies.

Four policies share one diffusion framework (``keygen.policies.diffusion``):

=============== ============== ========= ===================== ======================
name            cloud          keypoints encoder               noise network
=============== ============== ========= ===================== ======================
keygen          object-centric yes       PointNet (3 layers)   DiT (in-context tokens)
keygen_no_kp    object-centric no        PointNet              DiT
keygen_scene    scene crop     yes       PointNet              DiT
dp3             scene crop     no        DP3 (LayerNorm MLP)   1-D UNet with FiLM
=============== ============== ========= ===================== ======================

The two ablations need no new component: they switch the cloud source or drop the keypoint tokens.
Sizes are CPU-sized (the paper's are GPU-sized): a query of 10 DDIM steps stays under ~25 ms on one core.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from keygen.errors import InvalidParameterError

POLICY_NAMES = ("keygen", "keygen_no_kp", "keygen_scene", "keygen_yaw", "dp3")
CLOUD_SOURCES = ("object", "scene")
BACKBONES = ("dit", "unet")
ENCODERS = ("pointnet", "dp3")
SCHEDULERS = ("ddim", "ddpm")
FRAMES = ("world", "object")
YAW_ORIGINS = ("centroid", "grasp")  # where a yaw frame is centred (keygen.policies.yaw_frame)
# What a yaw frame is measured on: the manipulated object's keypoints (keygen.policies.yaw_frame) or
# the placement target's top face (keygen.policies.target_frame; the knife block).
YAW_SOURCES = ("keypoints", "target")
# Tasks whose manipulated object has a heading the keypoints can measure. A bowl is round: a yaw
# frame fitted to its keypoints would only turn the scene at random, so training refuses it.
HEADING_TASKS = ("pour", "knife")
ACTION_DIM = 10  # position 3 + 6D rotation 6 + gripper 1
PROPRIO_DIM = 10

# Which objects of a task get keypoints: (category of the keypoint model, object label in
# ``object_cloud_ids``). Labels are the task's PlacedObject labels (1 = manipulated object).
TASK_KEYPOINT_OBJECTS: dict[str, tuple[tuple[str, int], ...]] = {
    "pour": (("mug", 1),),
    "knife": (("knife", 1),),
    "stack": (("bowl", 1), ("bowl", 2)),
}


def keypoint_categories(task: str) -> tuple[str, ...]:
    """The keypoint-model categories a task needs, in order and without repeats."""
    if task not in TASK_KEYPOINT_OBJECTS:
        raise InvalidParameterError(
            f"task must be one of {sorted(TASK_KEYPOINT_OBJECTS)}, got {task!r}; the dataset's episode "
            f"metadata names its task"
        )
    return tuple(dict.fromkeys(cat for cat, _ in TASK_KEYPOINT_OBJECTS[task]))


def _positive(obj: Any, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise InvalidParameterError(f"{name} must be a positive int, got {value!r}")


@dataclass(frozen=True)
class PolicyConfig:
    """Everything that fixes a policy's architecture, inputs and sampling.

    ``execute_steps`` (n of the ``horizon`` predicted actions run before predicting again) is a
    runtime default; ``PolicyRunner.execute_steps`` can change it without retraining.
    """

    name: str = "keygen"
    cloud_source: str = "object"  # "object" (object-centric) or "scene" (workspace crop)
    use_keypoints: bool = True
    encoder: str = "pointnet"  # "pointnet" (KeyGen) or "dp3"
    backbone: str = "dit"  # "dit" or "unet"
    # Frame of the positions the network sees and predicts. "world": as observed. "object": every
    # position (cloud, keypoints, proprioception, action) relative to the centroid of the latest
    # cloud, with that centroid given as one extra conditioning input; a grasp then sits at nearly
    # the same place whatever the object's position, which the network no longer has to learn.
    frame: str = "world"
    # Turn each episode into the manipulated object's planar frame, measured from its keypoints at
    # the episode's first step (keygen.policies.yaw_frame); for objects whose yaw matters (mug, knife).
    yaw_frame: bool = False
    # Where that frame is centred: the keypoint centroid, or the keypoint nearest the demonstrated
    # grasp ("grasp"; keygen.policies.yaw_frame), so an approach learnt on one instance follows the
    # grasped part on a wider or narrower one.
    yaw_origin: str = "centroid"
    # What the yaw frame is measured on: the manipulated object's keypoints, or the top face of the
    # object it is placed into ("target": keygen.policies.target_frame, the knife block's slot axis),
    # which makes the insertion the same motion in every episode.
    yaw_source: str = "keypoints"
    # One more conditioning token: where the placement target (the box, the knife block) stands,
    # measured on its points at the episode's first step (keygen.policies.target_token); the target
    # has no keypoints, so otherwise only the cloud feature says where it is.
    target_token: bool = False
    # Condition also on where the robot's base stands in the yaw frame (keygen.policies.robot_base):
    # the frame moves the base to a different place in every episode, and the arm's reach with it.
    robot_base: bool = False
    obs_horizon: int = 2
    # Clouds encoded per sample: the latest ``cloud_frames`` of the history. One by default: the
    # paper conditions on P_t, and the cloud encoder dominates the training step on a CPU (keypoints
    # and proprioception keep the whole history, so motion stays visible).
    cloud_frames: int = 1
    horizon: int = 16
    execute_steps: int = 8
    num_points: int = 512
    # Keypoint slots: one per (object, keypoint index); filled from the task at fit time.
    num_keypoints: int = 0  # K per object
    num_objects: int = 0  # keypointed objects of the task
    # Point cloud encoder: per-point MLP widths, then max pool.
    pc_dims: tuple[int, ...] = (64, 128, 128)
    pc_out: int = 128  # DP3 projects to 64
    # DiT
    width: int = 128
    depth: int = 4
    heads: int = 4
    mlp_ratio: float = 2.0  # 4 in the DiT paper; 2 keeps a 10-step query within ~25 ms on one core
    # UNet
    unet_channels: tuple[int, ...] = (64, 128, 256)
    unet_kernel: int = 5
    unet_groups: int = 8
    # Diffusion
    train_timesteps: int = 100
    inference_steps: int = 10
    scheduler: str = "ddim"
    beta_schedule: str = "squaredcos_cap_v2"
    ema_decay: float = 0.995

    def __post_init__(self) -> None:
        if self.name not in POLICY_NAMES:
            raise InvalidParameterError(f"policy name must be one of {POLICY_NAMES}, got {self.name!r}")
        for attr, allowed in (
            ("cloud_source", CLOUD_SOURCES),
            ("backbone", BACKBONES),
            ("encoder", ENCODERS),
            ("scheduler", SCHEDULERS),
            ("frame", FRAMES),
            ("yaw_origin", YAW_ORIGINS),
            ("yaw_source", YAW_SOURCES),
        ):
            if getattr(self, attr) not in allowed:
                raise InvalidParameterError(f"{attr} must be one of {allowed}, got {getattr(self, attr)!r}")
        _positive(
            self, "obs_horizon", "cloud_frames", "horizon", "execute_steps", "num_points", "pc_out", "width"
        )
        _positive(self, "depth", "heads", "unet_kernel", "unet_groups", "train_timesteps", "inference_steps")
        if self.cloud_frames > self.obs_horizon:
            raise InvalidParameterError(
                f"cloud_frames ({self.cloud_frames}) cannot exceed obs_horizon ({self.obs_horizon})"
            )
        if self.execute_steps > self.horizon:
            raise InvalidParameterError(
                f"execute_steps ({self.execute_steps}) cannot exceed the horizon ({self.horizon})"
            )
        if self.width % self.heads:
            raise InvalidParameterError(f"width ({self.width}) must be divisible by heads ({self.heads})")
        if self.inference_steps > self.train_timesteps:
            raise InvalidParameterError(
                f"inference_steps ({self.inference_steps}) cannot exceed train_timesteps "
                f"({self.train_timesteps})"
            )
        if not self.mlp_ratio > 0:
            raise InvalidParameterError(f"mlp_ratio must be > 0, got {self.mlp_ratio}")
        if not 0.0 <= self.ema_decay < 1.0:
            raise InvalidParameterError(f"ema_decay must be in [0, 1), got {self.ema_decay}")
        if not self.pc_dims or not self.unet_channels:
            raise InvalidParameterError("pc_dims and unet_channels need at least one entry")
        if self.backbone == "unet" and self.use_keypoints:
            raise InvalidParameterError("the UNet backbone (dp3) takes no keypoints; set use_keypoints=False")
        if self.yaw_frame and self.yaw_source == "keypoints" and not self.use_keypoints:
            raise InvalidParameterError(
                "yaw_frame measures the object by its keypoints; it needs use_keypoints"
            )
        if self.yaw_source != "keypoints" and not self.yaw_frame:
            raise InvalidParameterError(
                f"yaw_source {self.yaw_source!r} says what the yaw frame is measured on; it needs yaw_frame"
            )
        if self.yaw_source == "target" and self.yaw_origin != "centroid":
            raise InvalidParameterError(
                f"a target yaw frame is centred on the target's top face; yaw_origin {self.yaw_origin!r} "
                f"(a keypoint of the manipulated object) does not apply"
            )
        if self.yaw_origin != "centroid" and not self.yaw_frame:
            raise InvalidParameterError(
                f"yaw_origin {self.yaw_origin!r} centres the yaw frame; it needs yaw_frame"
            )
        if self.target_token and self.backbone != "dit":
            raise InvalidParameterError(
                f"target_token adds a conditioning token, which needs the DiT backbone, got {self.backbone!r}"
            )
        if self.robot_base and not self.yaw_frame:
            raise InvalidParameterError(
                "robot_base states where the arm stands in a yaw frame; in the world frame it is a "
                "constant: it needs yaw_frame"
            )
        if self.robot_base and self.backbone != "dit":
            raise InvalidParameterError(
                f"robot_base conditions the DiT's adaLN, which needs the DiT backbone, got {self.backbone!r}"
            )
        if self.frame != "world" and self.backbone != "dit":
            raise InvalidParameterError(f"frame {self.frame!r} needs the DiT backbone, got {self.backbone!r}")
        if self.unet_kernel % 2 == 0:
            raise InvalidParameterError(f"unet_kernel must be odd ('same' padding), got {self.unet_kernel}")
        if self.horizon % (2 ** (len(self.unet_channels) - 1)) and self.backbone == "unet":
            raise InvalidParameterError(
                f"the UNet halves the horizon {len(self.unet_channels) - 1} times; horizon {self.horizon} "
                f"must be divisible by {2 ** (len(self.unet_channels) - 1)}"
            )
        if self.num_keypoints < 0 or self.num_objects < 0:
            raise InvalidParameterError("num_keypoints and num_objects must be >= 0")

    @property
    def num_keypoint_tokens(self) -> int:
        return self.num_keypoints * self.num_objects if self.use_keypoints else 0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PolicyConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise InvalidParameterError(f"unknown policy config fields {unknown}; known: {sorted(known)}")
        data = dict(data)
        for key in ("pc_dims", "unet_channels"):
            if key in data:
                data[key] = tuple(data[key])
        return cls(**data)

    def with_updates(self, **changes: Any) -> PolicyConfig:
        return replace(self, **changes)


# The registry: each named policy is a set of overrides of the defaults above.
_REGISTRY: dict[str, dict[str, Any]] = {
    "keygen": {},
    "keygen_no_kp": {"use_keypoints": False},
    "keygen_scene": {"cloud_source": "scene"},
    # Beyond the paper: KeyGen in the manipulated object's keypoint yaw frame, centred on the keypoint
    # nearest the demonstrated grasp (keygen.policies.yaw_frame). The configuration that measured best
    # on pouring (docs/benchmark.md); meaningless for a round object (a bowl has no heading).
    "keygen_yaw": {"yaw_frame": True, "yaw_origin": "grasp"},
    "dp3": {
        "cloud_source": "scene",
        "use_keypoints": False,
        "encoder": "dp3",
        "backbone": "unet",
        "pc_dims": (64, 128, 256),
        "pc_out": 64,
    },
}


def make_policy_config(name: str, **overrides: Any) -> PolicyConfig:
    """The registered configuration of policy ``name`` with ``overrides`` applied."""
    if name not in _REGISTRY:
        raise InvalidParameterError(f"unknown policy {name!r}; choose one of {POLICY_NAMES}")
    return PolicyConfig(name=name, **(_REGISTRY[name] | overrides))
