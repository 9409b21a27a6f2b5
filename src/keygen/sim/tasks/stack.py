"""Bowl stacking.

Task:
    Two bowls stand on the table. Pick bowl A (the manipulated instance) by its rim and place
    it into bowl B, then let go.

Randomisations:
    Positions of A and B in two side-by-side regions of the workspace (``easy``); plus a yaw of
    each over the full circle (``hard``; the bowls are round, so yaw moves A's rim-grasp anchor).
    B is another procedural bowl (drawn from the train split's family by the episode seed) scaled
    so that its inner rim radius exceeds A's rim radius by 25 to 45 mm: room for a finger between
    the two rims. Colours, lighting, cameras, mass and friction follow the environment's
    randomisation switches.

Success condition:
    A rests nested in B: A's bottom centre lies within B's rim radius horizontally and above B's
    bottom, A is not touched by the gripper, and both bowls have been still (speed below 2 cm/s)
    for at least 1 s (10 control steps).
"""

from __future__ import annotations

import mujoco
import numpy as np

from keygen.objects.splits import SPLIT_SIZES, make_instance
from keygen.sim.object_bodies import add_object
from keygen.sim.randomization import object_color
from keygen.sim.tasks.base import (
    PlacedObject,
    Task,
    TaskStatus,
    anchors_in_world,
    body_pose,
    contacts_between,
    finger_geom_ids,
    geoms_of_body,
    sample_planar_pose,
    yaw_quat_wxyz,
)

SETTLE_STEPS = 10  # control steps (1 s) both bowls must be still
STILL_SPEED = 0.02  # m/s
_BASE_CACHE: dict[int, object] = {}


def base_bowl_pool(index: int):
    """Base bowls come from the train split's family (never from test)."""
    if index not in _BASE_CACHE:
        _BASE_CACHE[index] = make_instance("bowl", "train", index)
    return _BASE_CACHE[index]


class StackTask(Task):
    name = "stack"
    category = "bowl"
    max_steps = 120  # 12 s

    def populate(self, spec: mujoco.MjSpec) -> None:
        rng = self.rng
        a = self.asset
        r_a = float(a.anchor("rim_radius")[0])
        base = base_bowl_pool(int(rng.integers(SPLIT_SIZES["train"])))
        wall = float(base.params.get("wall_thickness", 0.006))
        inner_rim = float(base.anchor("rim_radius")[0]) - wall
        target_inner = r_a + float(rng.uniform(0.025, 0.045))
        self.base_asset = base.scaled(max(target_inner / inner_rim, 0.3))
        r_b = float(self.base_asset.anchor("rim_radius")[0])

        # A on the robot's left (+y), B on its right (-y), far enough apart not to touch.
        xy_a, yaw_a = sample_planar_pose(rng, self.setting, (0.5, 0.05 + r_a), (0.06, 0.04))
        xy_b, yaw_b = sample_planar_pose(rng, self.setting, (0.5, -0.05 - r_b), (0.06, 0.04))
        gap = np.linalg.norm(xy_a - xy_b) - (r_a + r_b)
        if gap < 0.03:  # push B further right so the bowls start apart
            xy_b[1] -= 0.03 - gap
        colours = (
            object_color(rng, self.randomization.colors, (0.85, 0.55, 0.35)),
            object_color(rng, self.randomization.colors, (0.35, 0.55, 0.8)),
        )
        add_object(
            spec, a, "bowl_a", pos=(*xy_a, 0.0005), quat_wxyz=yaw_quat_wxyz(yaw_a), rgba=tuple(colours[0])
        )
        add_object(
            spec,
            self.base_asset,
            "bowl_b",
            pos=(*xy_b, 0.0005),
            quat_wxyz=yaw_quat_wxyz(yaw_b),
            rgba=tuple(colours[1]),
        )
        self.objects = [PlacedObject("bowl_a", 1, a), PlacedObject("bowl_b", 2, self.base_asset)]
        self._still_steps = 0

    def bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        super().bind(model, data)
        self._model = model
        self._finger_geoms = finger_geom_ids(model)
        self._a_geoms = geoms_of_body(model, self.objects[0].body_id)
        self._still_steps = 0

    # -- judging ---------------------------------------------------------------------------------
    def _nested(self, data: mujoco.MjData) -> tuple[bool, dict[str, float]]:
        pos_a, rot_a = body_pose(data, self.objects[0].body_id)
        pos_b, rot_b = body_pose(data, self.objects[1].body_id)
        bottom_a = pos_a + rot_a @ self.asset.anchor("bottom_center")
        bottom_b = pos_b + rot_b @ self.base_asset.anchor("bottom_center")
        r_b = float(self.base_asset.anchor("rim_radius")[0])
        offset = float(np.linalg.norm((bottom_a - bottom_b)[:2]))
        height = float(bottom_a[2] - bottom_b[2])
        nested = offset < r_b and height > 0.002
        return nested, {"offset": offset, "height_above_base": height}

    def _speeds(self, data: mujoco.MjData) -> float:
        v = 0.0
        for obj in self.objects:
            vel = np.zeros(6)
            mujoco.mj_objectVelocity(self._model, data, mujoco.mjtObj.mjOBJ_BODY, obj.body_id, vel, 0)
            v = max(v, float(np.linalg.norm(vel[3:])))
        return v

    def update(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        nested, _ = self._nested(data)
        touched = bool(contacts_between(model, data, self._finger_geoms, self._a_geoms))
        if nested and not touched and self._speeds(data) < STILL_SPEED:
            self._still_steps += 1
        else:
            self._still_steps = 0

    def status(self, model: mujoco.MjModel, data: mujoco.MjData) -> TaskStatus:
        nested, metrics = self._nested(data)
        metrics["still_seconds"] = self._still_steps / 10.0
        metrics["nested"] = float(nested)
        failure = None
        pos_a, _ = body_pose(data, self.objects[0].body_id)
        if pos_a[2] < -0.05:
            failure = "object_fell_off_table"
        return TaskStatus(
            success=bool(nested and self._still_steps >= SETTLE_STEPS), metrics=metrics, failure=failure
        )

    def anchors_world(self, model: mujoco.MjModel, data: mujoco.MjData) -> dict[str, np.ndarray]:
        anchors = anchors_in_world(self.asset, data, self.objects[0].body_id)
        anchors.update(anchors_in_world(self.base_asset, data, self.objects[1].body_id, prefix="base_"))
        return anchors

    # -- constructed states (tests, analysis) ------------------------------------------------------
    def place_nested(self, model: mujoco.MjModel, data: mujoco.MjData, drop: float = 0.005) -> None:
        """Teleport A to just above B's opening, centred; physics then lets it drop into B."""
        pos_b, rot_b = body_pose(data, self.objects[1].body_id)
        opening = pos_b + rot_b @ self.base_asset.anchor("opening_center")
        self._teleport(model, data, 0, np.array([opening[0], opening[1], opening[2] + drop]))

    def place_beside(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Teleport A onto the table just outside B's rim (a near miss)."""
        pos_b, _ = body_pose(data, self.objects[1].body_id)
        r = float(self.asset.anchor("rim_radius")[0]) + float(self.base_asset.anchor("rim_radius")[0]) + 0.01
        self._teleport(model, data, 0, np.array([pos_b[0], pos_b[1] + r, 0.0005]))

    def _teleport(self, model: mujoco.MjModel, data: mujoco.MjData, index: int, pos: np.ndarray) -> None:
        joint = model.body_jntadr[self.objects[index].body_id]
        adr, dof = model.jnt_qposadr[joint], model.jnt_dofadr[joint]
        data.qpos[adr : adr + 3] = pos
        data.qvel[dof : dof + 6] = 0.0
        mujoco.mj_forward(model, data)
