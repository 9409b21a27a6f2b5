"""What every task provides to the environment, and the pieces tasks share.

A task owns its objects: it adds them to the scene spec (``populate``), finds them in the
compiled model (``bind``), follows the episode step by step (``update``, e.g. how the object is
held) and judges it (``status``). The environment does the rest (robot, cameras, perception,
control, time limit).

Poses: ``easy`` places the manipulated object at a random position in a fixed region with a
fixed yaw; ``hard`` adds a yaw drawn over the full circle.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import mujoco
import numpy as np

from keygen.errors import InvalidParameterError
from keygen.objects.asset import Asset
from keygen.sim.randomization import Randomization

SETTINGS = ("easy", "hard")


@dataclass
class TaskStatus:
    """The verdict so far: ``success``, task metrics, and a failure reason once the episode is lost."""

    success: bool
    metrics: dict[str, float] = field(default_factory=dict)
    failure: str | None = None


@dataclass
class PlacedObject:
    """An object of the task in the scene: its body name, label (>= 1 in masks) and asset, if any."""

    body: str
    label: int
    asset: Asset | None = None
    body_id: int = -1


def yaw_quat_wxyz(yaw: float) -> np.ndarray:
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


def sample_planar_pose(
    rng: np.random.Generator,
    setting: str,
    center: tuple[float, float],
    half_extent: tuple[float, float],
    easy_yaw: float = 0.0,
) -> tuple[np.ndarray, float]:
    """(x, y) in the region and a yaw: fixed in ``easy``, uniform on the circle in ``hard``."""
    if setting not in SETTINGS:
        raise InvalidParameterError(f"setting must be one of {SETTINGS}, got {setting!r}")
    xy = np.asarray(center) + rng.uniform(-1, 1, 2) * np.asarray(half_extent)
    yaw = easy_yaw if setting == "easy" else float(rng.uniform(-np.pi, np.pi))
    return xy, yaw


def body_pose(data: mujoco.MjData, body_id: int) -> tuple[np.ndarray, np.ndarray]:
    """World position (3,) and rotation (3, 3) of a body's frame (the asset's canonical frame)."""
    return data.xpos[body_id].copy(), data.xmat[body_id].reshape(3, 3).copy()


def anchors_in_world(
    asset: Asset, data: mujoco.MjData, body_id: int, prefix: str = ""
) -> dict[str, np.ndarray]:
    """The asset's anchors mapped to the world frame under the body's current pose."""
    pos, rot = body_pose(data, body_id)
    out = {}
    for name, anchor in asset.require_anchors().items():
        out[prefix + name] = anchor.transformed(rot, pos).value.copy()
    return out


def geoms_of_body(model: mujoco.MjModel, body_id: int) -> np.ndarray:
    return np.flatnonzero(model.geom_bodyid == body_id)


def finger_geom_ids(model: mujoco.MjModel, prefix: str = "robot/") -> np.ndarray:
    """Ids of the gripper's finger and pad geoms."""
    from keygen.sim.robot import FINGER_GEOMS

    return np.array([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, prefix + n) for n in FINGER_GEOMS])


def contacts_between(model: mujoco.MjModel, data: mujoco.MjData, geoms_a, geoms_b) -> list[int]:
    """Indices of active contacts between any geom of set a and any of set b."""
    a, b = set(int(g) for g in geoms_a), set(int(g) for g in geoms_b)
    found = []
    for i in range(data.ncon):
        c = data.contact[i]
        g1, g2 = int(c.geom1), int(c.geom2)
        if (g1 in a and g2 in b) or (g1 in b and g2 in a):
            found.append(i)
    return found


class Task(ABC):
    """One pose-sensitive manipulation task (see the module docstring of each task)."""

    name: str
    category: str  # category of the manipulated object
    max_steps: int  # episode time limit in control steps (10 Hz)
    # MuJoCo's island sleeping: objects at rest (and everything resting on them) skip the dynamics
    # until a contact from a moving body wakes them. On for tasks whose resting scene is costly
    # (see PourTask); the others keep the physics their measured results were produced with.
    sleep_at_rest: bool = False

    def __init__(self, asset: Asset, setting: str, rng: np.random.Generator, randomization: Randomization):
        if asset.category != self.category:
            raise InvalidParameterError(
                f"task {self.name!r} manipulates a {self.category}, got a {asset.category} asset"
            )
        if setting not in SETTINGS:
            raise InvalidParameterError(f"setting must be one of {SETTINGS}, got {setting!r}")
        asset.require_anchors(self.name)
        self.asset = asset
        self.setting = setting
        self.rng = rng
        self.randomization = randomization
        self.objects: list[PlacedObject] = []

    # -- scene ---------------------------------------------------------------------------------
    @abstractmethod
    def populate(self, spec: mujoco.MjSpec) -> None:
        """Add the task's objects to the scene spec; fill ``self.objects`` (manipulated first)."""

    def bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Resolve ids in the compiled model; called once per episode after compiling."""
        for obj in self.objects:
            obj.body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, obj.body)
            if obj.body_id < 0:
                raise InvalidParameterError(f"task body {obj.body!r} missing from the model")

    def geom_labels(self, model: mujoco.MjModel) -> np.ndarray:
        """(ngeom,) label per geom: the object's label for task objects, 0 elsewhere."""
        labels = np.zeros(model.ngeom, np.int32)
        for obj in self.objects:
            labels[geoms_of_body(model, obj.body_id)] = obj.label
        return labels

    @property
    def manipulated(self) -> PlacedObject:
        return self.objects[0]

    # -- episode -------------------------------------------------------------------------------
    def settle(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Hook run after reset before the first observation (e.g. let particles settle)."""
        return None

    @abstractmethod
    def update(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Follow the episode after every control step (grasp history, settling timers, ...)."""

    @abstractmethod
    def status(self, model: mujoco.MjModel, data: mujoco.MjData) -> TaskStatus:
        """Success, metrics and failure reason given the current state and the history."""

    def anchors_world(self, model: mujoco.MjModel, data: mujoco.MjData) -> dict[str, np.ndarray]:
        """Privileged anchors of the task's objects in the world frame (for the expert and analysis)."""
        obj = self.manipulated
        return anchors_in_world(obj.asset, data, obj.body_id)

    def object_ids(self) -> dict[str, str]:
        """Instance ids of the task's objects (for episode metadata)."""
        return {obj.body: obj.asset.instance_id for obj in self.objects if obj.asset is not None}
