"""Collect the knife: put a knife lying on the table into the slot of a knife block.

Task:
    A knife (the manipulated instance, label 1) lies flat on the table; a static knife block
    (label 2) with one vertical slot stands beside it. Grasp the knife by its handle from above,
    lift it, turn it blade down, align the blade's plane with the slot, lower the blade into the
    slot and let go.

Randomisations:
    The knife rests in a statically stable pose found by physics (``_knife_util.resting_pose``;
    most knives tip forward onto the blade or roll a little onto its edge) and is dropped from
    1.5 mm; its handle-grasp point lies in x 0.42-0.55, y 0.05-0.20. ``easy``: blade tip pointing
    +x, face up. ``hard``: yaw over the full circle and, with probability 1/2, face down (turned
    pi about the knife's x axis). The block stands in x 0.42-0.58, y -0.10 to -0.25 with its slot
    along world y (``easy``) or a yaw over the full circle (``hard``); layouts where knife and block
    would touch are redrawn. The block is sized for the blade by ``KnifeBlockSpec.for_blade`` from
    the blade's length, width and thickness (measured on the asset) with random clearances, so it
    varies with the episode seed too. Colours follow the environment's randomisation switches.

Success condition:
    Expressed in the block's frame, the blade segment from blade_base to blade_tip has its tip
    below the block's top, and the part of it below the top and within the slot's x/y bounds
    (+2 mm) is at least half the blade length; the knife has been released (no contact with the
    fingers or pads) and still (below 2 cm/s) for 0.5 s (5 control steps). Metrics:
    ``inserted_fraction``, ``tip_depth`` (below the block top, metres), ``lateral_offset`` (the
    tip's horizontal distance from the slot's centre line), ``still_seconds``, ``held``.
    Failures: ``knife_off_table`` (the knife fell off the table, 5 cm below its top or outside
    it), ``dropped`` (after being lifted by the gripper the knife was let go of, or slipped out,
    and lies on the table again).
"""

from __future__ import annotations

import mujoco
import numpy as np

from keygen.geometry.rotations import matrix_to_quat_wxyz, yaw_matrix
from keygen.sim import props
from keygen.sim.object_bodies import add_object
from keygen.sim.randomization import object_color
from keygen.sim.scene import TABLE_CENTER_XY, TABLE_HALF, TABLE_TOP_Z
from keygen.sim.tasks import _knife_util as util
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
)

KNIFE_REGION = ((0.485, 0.125), (0.065, 0.075))  # centre, half extent of the handle-grasp point (x, y)
BLOCK_REGION = ((0.50, -0.175), (0.08, 0.075))  # centre, half extent of the block's bottom centre
KNIFE_EASY_YAW = 0.0  # blade tip pointing away from the robot
BLOCK_EASY_YAW = np.pi / 2  # slot along world y: the hand inserts with its fingers pointing forward
LAYOUT_CLEARANCE = 0.03  # metres between the knife's footprint and the block's
LAYOUT_TRIES = 100
SLOT_TOLERANCE = 0.002  # metres added to the slot's x/y bounds
INSERTED_FRACTION = 0.5
STILL_SPEED = 0.02  # m/s
SETTLE_STEPS = 5  # control steps (0.5 s) released and still
SETTLE_MAX_SECONDS = 1.0  # extra physics after the env's settling, until the knife is still
LIFTED_HEIGHT = 0.03  # metres above its resting height at which a held knife counts as lifted
OFF_TABLE_DROP = 0.05  # metres below the table top

KNIFE_BODY, BLOCK_BODY = "knife", "knife_block"


class KnifeTask(Task):
    name = "knife"
    category = "knife"
    max_steps = 200  # 20 s

    # -- scene -----------------------------------------------------------------------------------
    def populate(self, spec: mujoco.MjSpec) -> None:
        rng = self.rng
        self.blade = util.blade_dimensions(self.asset)
        self.block = props.KnifeBlockSpec.for_blade(
            rng, self.blade.width, self.blade.thickness, self.blade.length
        )
        self.face_down = bool(self.setting == "hard" and rng.uniform() < 0.5)
        rest_rotation, rest_height = util.resting_pose(self.asset, self.face_down)
        self.rest_height = rest_height
        knife_pos, knife_rot, block_xy, block_yaw = self._sample_layout(rest_rotation, rest_height)
        self.block_yaw = block_yaw
        knife_rgba = object_color(rng, self.randomization.colors, (0.78, 0.78, 0.82))
        block_rgba = object_color(rng, self.randomization.colors, (0.55, 0.38, 0.22))
        add_object(
            spec,
            self.asset,
            KNIFE_BODY,
            pos=knife_pos,
            quat_wxyz=matrix_to_quat_wxyz(knife_rot),
            rgba=tuple(knife_rgba),
            contact=util.KNIFE_CONTACT,
        )
        self.block_geoms = props.add_knife_block(
            spec, self.block, BLOCK_BODY, (*block_xy, TABLE_TOP_Z), block_yaw, block_rgba
        )
        self.objects = [PlacedObject(KNIFE_BODY, 1, self.asset), PlacedObject(BLOCK_BODY, 2, None)]
        self._reset_history()

    def _sample_layout(
        self, rest_rotation: np.ndarray, rest_height: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Knife pose (position, rotation) and block (xy, yaw) whose footprints keep apart."""
        grasp = self.asset.anchor("handle_grasp")
        vertices = util.collision_vertices(self.asset)[::4]  # a footprint sample is enough
        block_half = np.array([self.block.size_x, self.block.size_y]) / 2
        for _ in range(LAYOUT_TRIES):
            grasp_xy, yaw = sample_planar_pose(self.rng, self.setting, *KNIFE_REGION, easy_yaw=KNIFE_EASY_YAW)
            block_xy, block_yaw = sample_planar_pose(
                self.rng, self.setting, *BLOCK_REGION, easy_yaw=BLOCK_EASY_YAW
            )
            rotation = yaw_matrix(yaw) @ rest_rotation
            pos = np.array([*(grasp_xy - (rotation @ grasp)[:2]), rest_height + util.DROP_HEIGHT])
            footprint = (vertices @ rotation.T + pos)[:, :2]
            if not util.footprints_overlap(footprint, LAYOUT_CLEARANCE, block_xy, block_yaw, block_half):
                return pos, rotation, block_xy, block_yaw
        # Not reached in practice (the tests draw many layouts); the last draw is kept rather than failing.
        return pos, rotation, block_xy, block_yaw

    def bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        super().bind(model, data)
        self._model = model
        self._finger_geoms = finger_geom_ids(model)
        self._knife_geoms = geoms_of_body(model, self.objects[0].body_id)
        self._table_geom = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "table")
        self._block_geom_ids = geoms_of_body(model, self.objects[1].body_id)
        joint = model.body_jntadr[self.objects[0].body_id]
        self._qadr, self._dadr = model.jnt_qposadr[joint], model.jnt_dofadr[joint]
        self._reset_history()

    def _reset_history(self) -> None:
        self._still_steps = 0
        self._lifted = False
        self._dropped = False
        self.start_stable = False

    def settle(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Let the dropped knife come to rest; ``start_stable`` says whether it did (for checks)."""
        still = 0
        needed = int(0.1 / model.opt.timestep)  # 0.1 s below the rest speed counts as resting
        for _ in range(int(SETTLE_MAX_SECONDS / model.opt.timestep)):
            if self.knife_speed(data) < util.REST_SPEED:
                still += 1
                if still >= needed:
                    break
            else:
                still = 0
            mujoco.mj_step(model, data)
        self.start_stable = still >= needed

    # -- state -----------------------------------------------------------------------------------
    def knife_speed(self, data: mujoco.MjData) -> float:
        return util.knife_speed(data.qvel[self._dadr : self._dadr + 6])

    def block_pose(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        return body_pose(data, self.objects[1].body_id)

    def held(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        return bool(contacts_between(model, data, self._finger_geoms, self._knife_geoms))

    def insertion(self, data: mujoco.MjData) -> tuple[bool, dict[str, float]]:
        """Whether the blade is in the slot (geometry only) and the insertion metrics."""
        anchors = anchors_in_world(self.asset, data, self.objects[0].body_id)
        pos, rot = self.block_pose(data)
        base = rot.T @ (anchors["blade_base"] - pos)  # (3,) block frame
        tip = rot.T @ (anchors["blade_tip"] - pos)
        b = self.block
        top, floor = b.height, b.height - b.slot_depth
        half = np.array([b.slot_length / 2, b.slot_width / 2]) + SLOT_TOLERANCE
        lo = np.array([-half[0], -half[1], floor - SLOT_TOLERANCE])
        hi = np.array([half[0], half[1], top])
        span = util.segment_in_box(base, tip, lo, hi)
        inside = 0.0 if span is None else (span[1] - span[0]) * float(np.linalg.norm(tip - base))
        fraction = inside / self.blade.length
        metrics = {
            "inserted_fraction": float(fraction),
            "tip_depth": float(top - tip[2]),
            "lateral_offset": float(np.linalg.norm(tip[:2])),
        }
        return bool(tip[2] < top and fraction >= INSERTED_FRACTION), metrics

    # -- episode ---------------------------------------------------------------------------------
    def update(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        held = self.held(model, data)
        knife_z = float(data.xpos[self.objects[0].body_id][2])
        if held and knife_z > self.rest_height + LIFTED_HEIGHT:
            self._lifted = True
        on_table = bool(contacts_between(model, data, [self._table_geom], self._knife_geoms))
        if self._lifted and not held and on_table:
            self._dropped = True
        inserted, _ = self.insertion(data)
        if inserted and not held and self.knife_speed(data) < STILL_SPEED:
            self._still_steps += 1
        else:
            self._still_steps = 0

    def status(self, model: mujoco.MjModel, data: mujoco.MjData) -> TaskStatus:
        inserted, metrics = self.insertion(data)
        metrics["still_seconds"] = self._still_steps / 10.0
        metrics["held"] = float(self.held(model, data))
        failure = None
        if self._off_table(data):
            failure = "knife_off_table"
        elif self._dropped:
            failure = "dropped"
        success = bool(inserted and self._still_steps >= SETTLE_STEPS and failure is None)
        return TaskStatus(success=success, metrics=metrics, failure=failure)

    def _off_table(self, data: mujoco.MjData) -> bool:
        pos = data.xpos[self.objects[0].body_id]
        outside = np.any(np.abs(pos[:2] - np.asarray(TABLE_CENTER_XY)) > np.asarray(TABLE_HALF[:2]))
        return bool(pos[2] < TABLE_TOP_Z - OFF_TABLE_DROP or outside)

    def anchors_world(self, model: mujoco.MjModel, data: mujoco.MjData) -> dict[str, np.ndarray]:
        """The knife's anchors plus the slot: opening centre, long axis, depth, top height, size."""
        anchors = anchors_in_world(self.asset, data, self.objects[0].body_id)
        pos, rot = self.block_pose(data)
        b = self.block
        anchors.update(
            slot_center_top=pos + rot @ np.array([0.0, 0.0, b.height]),
            slot_axis=rot[:, 0].copy(),
            slot_depth=np.array([b.slot_depth]),
            block_top_z=np.array([pos[2] + b.height]),
            slot_length=np.array([b.slot_length]),
            slot_width=np.array([b.slot_width]),
        )
        return anchors

    # -- constructed states (tests, analysis) ------------------------------------------------------
    def blade_down_pose(
        self, data: mujoco.MjData, fraction: float, offset: tuple[float, float] = (0.0, 0.0)
    ) -> tuple[np.ndarray, np.ndarray]:
        """Knife pose (position, rotation) with the blade pointing down, its plane along the slot.

        The tip lies ``fraction`` of the blade length below the block top; the blade's width is
        centred on the slot, then shifted by ``offset`` (block x, block y), metres.
        """
        pos_b, rot_b = self.block_pose(data)
        down = np.array([0.0, 0.0, -1.0])
        target = np.column_stack([down, rot_b[:, 0], np.cross(down, rot_b[:, 0])])
        rotation = target @ util.blade_frame(self.asset).T
        top = pos_b + rot_b @ np.array([offset[0], offset[1], self.block.height])
        # Centre the blade's width on the slot: its middle lies center_offset along the edge direction.
        tip = top - self.blade.center_offset * rot_b[:, 0] + fraction * self.blade.length * down
        return tip - rotation @ self.asset.anchor("blade_tip"), rotation

    def place_knife(
        self, model: mujoco.MjModel, data: mujoco.MjData, pos: np.ndarray, rotation: np.ndarray
    ) -> None:
        """Teleport the knife to a pose at rest (qpos write and mj_forward)."""
        data.qpos[self._qadr : self._qadr + 3] = pos
        data.qpos[self._qadr + 3 : self._qadr + 7] = matrix_to_quat_wxyz(rotation)
        data.qvel[self._dadr : self._dadr + 6] = 0.0
        mujoco.mj_forward(model, data)

    def set_block_collisions(self, model: mujoco.MjModel, enabled: bool) -> None:
        """Turn the block's collisions off (e.g. to teleport a blade into its wall) or back on."""
        flag = 1 if enabled else 0
        model.geom_contype[self._block_geom_ids] = flag
        model.geom_conaffinity[self._block_geom_ids] = flag
