"""Pouring from a mug held by its handle.

Task:
    A mug with small spheres ("liquid") inside stands on the table next to an open box. Grasp
    the mug by its handle (one finger through the handle opening, the jaws closing on the outer
    bar along the mug's radial axis: the anchors ``handle_grasp`` and ``grasp_approach``), lift it,
    carry it over the box and tip it so that the spheres fall into the box.

Randomisations:
    The mug's position in a region on the robot's left (x 0.42-0.56 m, y 0.08-0.20 m); in
    ``easy`` its yaw is fixed at 0: the handle points away from the robot (+x), the side grasp
    approaches along -y (the hand comes from the left, the wrist well inside the arm's reach and
    clear of the base) and the pour lip faces the robot; ``hard`` draws the mug's yaw (and the
    box's) over the full circle. The box (inner size, wall
    height and thickness from :meth:`ContainerSpec.sample`) stands in a region on the right
    (x 0.42-0.56 m, y -0.15 to -0.25 m). The number of spheres is fixed (12 by default), their
    radius follows the mug's size (5-7 mm at scale 1, smaller when the cavity needs it) and their
    layered start layout inside the cavity is turned by a random angle. Colours, lighting,
    cameras, mass and friction follow the environment's randomisation switches.

Success condition:
    At least 60 % of the spheres lie inside the box (within its inner walls, below the wall top
    + 1 cm), the mug was gripped by its handle (both jaws on handle parts) and never touched by a
    finger on its body or rim, and it was not dropped (after being lifted > 2 cm while gripped,
    losing all finger contact while > 1 cm above the table; or, free of the hand, tipped over
    (> 60 deg) or fallen off the table). A finger on the body fails the episode at once
    (``held_by_body``), and so does a drop (``dropped``).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from keygen.errors import InvalidParameterError
from keygen.objects.asset import Asset
from keygen.sim.object_bodies import add_object
from keygen.sim.props import ContainerSpec, add_container
from keygen.sim.randomization import object_color
from keygen.sim.robot import FINGER_GEOMS, FINGER_MAX, PAD_SIZE
from keygen.sim.tasks.base import (
    PlacedObject,
    Task,
    TaskStatus,
    anchors_in_world,
    body_pose,
    finger_geom_ids,
    sample_planar_pose,
    yaw_quat_wxyz,
)

DEFAULT_PARTICLES = 12
MIN_PARTICLES = 10
PARTICLE_RADIUS = 0.006  # m at mug scale 1; kept within PARTICLE_RADIUS_RANGE unless the cavity is tiny
PARTICLE_RADIUS_RANGE = (0.005, 0.007)
PARTICLE_MIN_RADIUS = 0.002
PARTICLE_DENSITY = 1000.0  # kg/m^3, water
# Low sliding and rolling friction so the spheres flow out of a tipped mug like a granular liquid;
# a little rolling resistance stops spilled ones from rolling across the whole table.
PARTICLE_FRICTION = (0.3, 0.002, 0.0002)
PARTICLE_CONDIM = 6
# Stiff sphere contacts (time constant 5 ms, >= 2 physics steps). With MuJoCo's default 20 ms a
# sphere falling 13 cm into a tall box (1.3-1.5 m/s) sank through the 6-10 mm floor and came to
# rest inside it at table height, counted as spilled (all 12 of a pour on test/hard/0.7 object 8).
# The large solmix makes the sphere's solref win the mix in every contact it is part of.
PARTICLE_SOLREF = (0.005, 1.0)
PARTICLE_SOLMIX = 1000.0
SUCCESS_FRACTION = 0.6
ABOVE_WALL_TOLERANCE = 0.01  # m: a sphere counts as in the box up to 1 cm above its walls
LIFT_HEIGHT = 0.02  # m: lowest mug point above the table that counts as lifted
DROP_HEIGHT = 0.01  # m: losing the grip above this height is a drop
TIPPED_DEG = 60.0
HANDLE_CONTACT_MARGIN = 0.003  # m beyond the body's outer radius: contacts there are on the handle
FINGER_THICKNESS = PAD_SIZE[1] + 0.010  # pad + finger box along the closing axis, m
# Handle toward +x: the grasp approaches along -y from the robot's left. (With the handle toward +y the
# approach would run along +x and the pre-grasp pose, 10 cm short of the handle, folds the arm
# against its joint limits near the base.)
EASY_MUG_YAW = 0.0
MUG_REGION = ((0.49, 0.14), (0.07, 0.06))  # centre (x, y), half extent (x, y), metres
CONTAINER_REGION = ((0.49, -0.20), (0.07, 0.05))
SETTLE_MAX_SECONDS = 1.0
SETTLE_SPEED = 0.02  # m/s: particles slower than this count as settled
_LAYER_GAP = 0.001  # m between stacked spheres at reset, so none start in contact


@dataclass(frozen=True)
class Cavity:
    """The mug's inside in its canonical frame: a cylinder (conservative radius), metres."""

    inner_radius: float  # smallest inner radius between floor and rim
    floor_z: float  # top of the inner floor
    rim_z: float  # top of the rim
    body_radius: float  # largest outer radius of the body (handle excluded)


def mug_cavity(asset: Asset) -> Cavity:
    """The cavity from the generator's parameters, or estimated from anchors and mesh for imports."""
    s = asset.scale
    rim_z = float(asset.anchor("opening_center")[2])
    v = np.asarray(asset.visual.vertices)
    # The body is round and the handle lies at +x: the side opposite the handle gives its radius.
    back = v[v[:, 0] < 0]
    body_radius = float(np.hypot(back[:, 0], back[:, 1]).max()) if len(back) else float(abs(v[:, 0]).max())
    p = asset.params
    if all(k in p for k in ("radius_bottom", "taper", "wall", "bottom")):
        r_bottom = float(p["radius_bottom"])
        inner = (min(r_bottom, r_bottom * float(p["taper"])) - float(p["wall"])) * s
        floor_z = float(p["bottom"]) * s
    else:  # imported mug: pour_point sits mid-wall on the rim; assume a wall of 8 % of the radius
        rim_mid = abs(float(asset.anchor("pour_point")[0]))
        inner, floor_z = 0.9 * rim_mid, 0.1 * rim_z
    return Cavity(inner_radius=inner, floor_z=floor_z, rim_z=rim_z, body_radius=body_radius)


def particle_layout(cavity: Cavity, count: int, radius: float, turn: float = 0.0) -> tuple[float, np.ndarray]:
    """Sphere radius and (count, 3) centres in the mug frame: rings stacked in layers on the floor.

    The radius shrinks (by 10 % steps) until the stack fits below the rim; InvalidParameterError
    if even PARTICLE_MIN_RADIUS does not fit.
    """
    if count < 1:
        raise InvalidParameterError(f"particle count must be >= 1, got {count}")
    r = float(radius)
    while r >= PARTICLE_MIN_RADIUS:
        centres = _stack(cavity, count, r, turn)
        if centres is not None:
            return r, centres
        r *= 0.9
    raise InvalidParameterError(
        f"{count} spheres do not fit in a mug cavity of inner radius {cavity.inner_radius * 1e3:.1f} mm "
        f"and depth {(cavity.rim_z - cavity.floor_z) * 1e3:.1f} mm even at radius "
        f"{PARTICLE_MIN_RADIUS * 1e3:.0f} mm; use fewer particles or a larger mug scale."
    )


def _stack(cavity: Cavity, count: int, r: float, turn: float) -> np.ndarray | None:
    ring = cavity.inner_radius - r - _LAYER_GAP  # radius of the ring of sphere centres
    if ring < 0:
        return None
    half_chord = r + _LAYER_GAP / 2
    per_ring = 1 if ring < half_chord else int(np.floor(np.pi / np.arcsin(min(1.0, half_chord / ring))))
    per_ring = max(1, per_ring)
    centre_fits = per_ring > 1 and ring >= 2 * r + _LAYER_GAP
    per_layer = per_ring + int(centre_fits)
    layers = int(np.ceil(count / per_layer))
    pitch = 2 * r + _LAYER_GAP
    z0 = cavity.floor_z + r + 0.003  # clear of the floor's fillet
    if z0 + (layers - 1) * pitch + r > cavity.rim_z - 0.002:
        return None
    out = []
    for layer in range(layers):
        z = z0 + layer * pitch
        phase = turn + (np.pi / per_ring) * (layer % 2)
        angles = phase + 2 * np.pi * np.arange(per_ring) / per_ring
        radius = ring if per_ring > 1 else 0.0
        out += [(radius * np.cos(a), radius * np.sin(a), z) for a in angles]
        if centre_fits:
            out.append((0.0, 0.0, z))
    return np.array(out[:count])


def handle_grasp_frame(asset: Asset, depth: float = 0.005) -> tuple[np.ndarray, np.ndarray]:
    """The tcp pose for the handle grasp in the mug frame: position (3,) and rotation (3, 3).

    The tcp's z axis (approach) is ``grasp_approach``, its y axis (closing) the mug's radial +x,
    and the tcp sits ``depth`` beyond ``handle_grasp`` along the approach, so the finger tips
    (5 mm past the tcp) reach past the far side of the bar.
    """
    approach = asset.anchor("grasp_approach")
    approach = approach / np.linalg.norm(approach)
    closing = np.array([1.0, 0.0, 0.0]) - approach[0] * approach
    closing /= np.linalg.norm(closing)
    rotation = np.column_stack([np.cross(closing, approach), closing, approach])
    return asset.anchor("handle_grasp") + depth * approach, rotation


def pregrasp_opening(asset: Asset) -> float:
    """Gripper command (fraction of FINGER_MAX) that puts the inner finger mid-way in the handle gap.

    With the tcp on the bar's centreline each pad face sits ``q`` from it; the inner finger
    (FINGER_THICKNESS thick) then fills [bar - q - thickness, bar - q], centred in the free gap
    between the body and the bar's inner side when q = half bar depth + (gap - thickness) / 2.
    """
    p, s = asset.params, asset.scale
    if "handle_half_depth" in p and "handle_gap" in p:
        half_depth, gap = float(p["handle_half_depth"]) * s, float(p["handle_gap"]) * s
    else:
        cav = mug_cavity(asset)
        half_depth = 0.005 * s
        gap = float(asset.anchor("handle_grasp")[0]) - half_depth - cav.body_radius
    q = half_depth + max(gap - FINGER_THICKNESS, 0.0) / 2
    return float(np.clip(q / FINGER_MAX, 0.0, 1.0))


# The cameras draw a simplified mug (keygen.sim.render_mesh: within 2 mm of the full surface):
# procedural mugs have 11,000-14,000 faces, and drawing them was a third or more of the rendering.
MUG_RENDER_FACES = 7000


class PourTask(Task):
    name = "pour"
    category = "mug"
    max_steps = 200  # 20 s
    num_particles = DEFAULT_PARTICLES
    # The mug resting on the table with its spheres is ~280 constraint rows, and the robot's
    # no-slip pass makes every row costly: before the hand touches the mug that was half an
    # episode's physics. Asleep, the resting island costs nothing until a finger wakes it.
    sleep_at_rest = True

    # -- scene -----------------------------------------------------------------------------------
    def populate(self, spec: mujoco.MjSpec) -> None:
        if self.num_particles < MIN_PARTICLES:
            raise InvalidParameterError(
                f"pour needs at least {MIN_PARTICLES} particles, got {self.num_particles}"
            )
        rng = self.rng
        mug = self.asset
        self.cavity = mug_cavity(mug)
        self.container = ContainerSpec.sample(rng)
        xy_mug, yaw_mug = sample_planar_pose(rng, self.setting, *MUG_REGION, easy_yaw=EASY_MUG_YAW)
        xy_box, yaw_box = sample_planar_pose(rng, self.setting, *CONTAINER_REGION, easy_yaw=0.0)
        colours = (
            object_color(rng, self.randomization.colors, (0.9, 0.9, 0.85)),
            object_color(rng, self.randomization.colors, (0.55, 0.45, 0.35)),
            object_color(rng, self.randomization.colors, (0.2, 0.45, 0.9)),
        )
        mug_pos = np.array([*xy_mug, 0.0005])
        handles = add_object(
            spec,
            mug,
            "mug",
            pos=mug_pos,
            quat_wxyz=yaw_quat_wxyz(yaw_mug),
            rgba=tuple(colours[0]),
            render_max_faces=MUG_RENDER_FACES,
        )
        self._mug_part_labels = list(handles.part_labels)
        self._mug_collision_names = list(handles.collision_geoms)
        add_container(spec, self.container, "container", (*xy_box, 0.0), yaw_box, tuple(colours[1]))

        radius = float(np.clip(PARTICLE_RADIUS * mug.scale, *PARTICLE_RADIUS_RANGE))
        self.particle_radius, local = particle_layout(
            self.cavity, self.num_particles, radius, turn=float(rng.uniform(0, 2 * np.pi))
        )
        c, s = np.cos(yaw_mug), np.sin(yaw_mug)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        self.particle_names = [f"particle{i:02d}" for i in range(len(local))]
        for name, p in zip(self.particle_names, local @ rot.T + mug_pos, strict=True):
            _add_particle(spec, name, p, self.particle_radius, tuple(colours[2]))
        self.objects = [PlacedObject("mug", 1, mug), PlacedObject("container", 2, None)]
        self._hull_points = np.asarray(mug.visual.convex_hull.vertices)  # for the mug's lowest point

    def bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        super().bind(model, data)
        self._finger_geoms = finger_geom_ids(model)
        left = {mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "robot/" + n) for n in FINGER_GEOMS[::2]}
        self._finger_side = {int(g): (0 if int(g) in left else 1) for g in self._finger_geoms}
        ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, n) for n in self._mug_collision_names]
        self._handle_geoms = self._classify_handle_geoms(ids)
        self._mug_geoms = set(ids)
        self._particle_bodies = np.array(
            [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n) for n in self.particle_names]
        )
        self._particle_qadr = model.jnt_qposadr[model.body_jntadr[self._particle_bodies]]
        self._particle_dadr = model.jnt_dofadr[model.body_jntadr[self._particle_bodies]]
        self._reset_history()

    def _classify_handle_geoms(self, geom_ids: list[int]) -> set[int]:
        """Mug collision geoms that belong to the handle: by part label when the generator sets them,
        else by position (part centre farther from the axis than the body's outer radius)."""
        if any(label is not None for label in self._mug_part_labels):
            return {g for g, lab in zip(geom_ids, self._mug_part_labels, strict=True) if lab == "handle"}
        out = set()
        for g, part in zip(geom_ids, self.asset.collision, strict=True):
            centre = np.asarray(part.to_trimesh().vertices).mean(axis=0)
            if np.hypot(centre[0], centre[1]) > self.cavity.body_radius:
                out.add(g)
        return out

    def _reset_history(self) -> None:
        self._handle_gripped = False  # both jaws were on handle parts at some update
        self._touched_body = False
        self._lifted = False
        self._dropped = False
        self._pending_drop = 0  # consecutive updates in a drop-like state
        self._left_mug = np.zeros(len(self.particle_names), bool)

    def settle(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Let the spheres come to rest in the mug (at most SETTLE_MAX_SECONDS more)."""
        steps = int(0.1 / model.opt.timestep)
        for _ in range(int(SETTLE_MAX_SECONDS / 0.1)):
            if self._particle_speeds(data).max() < SETTLE_SPEED:
                break
            for _ in range(steps):
                mujoco.mj_step(model, data)

    # -- state ---------------------------------------------------------------------------------------
    def particle_positions(self, data: mujoco.MjData) -> np.ndarray:
        """(n, 3) world positions of the spheres."""
        return data.xpos[self._particle_bodies].copy()

    def _particle_speeds(self, data: mujoco.MjData) -> np.ndarray:
        return np.array([np.linalg.norm(data.qvel[d : d + 3]) for d in self._particle_dadr])

    def in_container(self, data: mujoco.MjData, points: np.ndarray) -> np.ndarray:
        """(n,) whether points lie within the box's inner walls, above its floor, below wall top + 1 cm."""
        pos, rot = body_pose(data, self.objects[1].body_id)
        local = (points - pos) @ rot
        c = self.container
        return (
            (np.abs(local[:, 0]) < c.inner_x / 2)
            & (np.abs(local[:, 1]) < c.inner_y / 2)
            & (local[:, 2] > c.wall - 0.002)
            & (local[:, 2] < c.height + ABOVE_WALL_TOLERANCE)
        )

    def in_mug(self, data: mujoco.MjData, points: np.ndarray) -> np.ndarray:
        """(n,) whether points lie in the mug's cavity (a sphere radius of tolerance)."""
        pos, rot = body_pose(data, self.manipulated.body_id)
        local = (points - pos) @ rot
        cav, tol = self.cavity, self.particle_radius
        # The cavity radius grows up to the rim on tapered mugs; the body radius bounds it.
        return (
            (np.hypot(local[:, 0], local[:, 1]) < cav.body_radius)
            & (local[:, 2] > cav.floor_z - tol)
            & (local[:, 2] < cav.rim_z + tol)
        )

    def mug_tilt_deg(self, data: mujoco.MjData) -> float:
        _, rot = body_pose(data, self.manipulated.body_id)
        return float(np.degrees(np.arccos(np.clip(rot[2, 2], -1.0, 1.0))))

    def mug_lowest_z(self, data: mujoco.MjData) -> float:
        pos, rot = body_pose(data, self.manipulated.body_id)
        return float((self._hull_points @ rot[2] + pos[2]).min())

    def finger_contacts(self, model: mujoco.MjModel, data: mujoco.MjData) -> list[tuple[int, bool]]:
        """(finger side 0/1, on handle) for each contact between a finger or pad and the mug."""
        pos, rot = body_pose(data, self.manipulated.body_id)
        found = []
        for i in range(data.ncon):
            c = data.contact[i]
            g1, g2 = int(c.geom1), int(c.geom2)
            if g1 in self._finger_side and g2 in self._mug_geoms:
                finger, mug_geom = g1, g2
            elif g2 in self._finger_side and g1 in self._mug_geoms:
                finger, mug_geom = g2, g1
            else:
                continue
            local = (np.asarray(c.pos) - pos) @ rot
            # Handle parts, or any point well outside the body (the handle's attachment region).
            beyond_body = np.hypot(local[0], local[1]) > self.cavity.body_radius + HANDLE_CONTACT_MARGIN
            found.append((self._finger_side[finger], mug_geom in self._handle_geoms or bool(beyond_body)))
        return found

    # -- episode ---------------------------------------------------------------------------------------
    def update(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        contacts = self.finger_contacts(model, data)
        if any(not on_handle for _, on_handle in contacts):
            self._touched_body = True
        sides = {side for side, _ in contacts}
        gripped = sides == {0, 1}
        if gripped and all(on_handle for _, on_handle in contacts):
            self._handle_gripped = True
        lowest = self.mug_lowest_z(data)
        if gripped and lowest > LIFT_HEIGHT:
            self._lifted = True
        free = not contacts
        pos, _ = body_pose(data, self.manipulated.body_id)
        falling = self._lifted and free and (lowest > DROP_HEIGHT or self._pending_drop > 0)
        lost = free and (self.mug_tilt_deg(data) > TIPPED_DEG or pos[2] < -0.05)
        # One update of a drop-like state may be contact flicker; two in a row is a drop.
        self._pending_drop = self._pending_drop + 1 if (falling or lost) else 0
        if self._pending_drop >= 2:
            self._dropped = True
        self._left_mug |= ~self.in_mug(data, self.particle_positions(data))

    def status(self, model: mujoco.MjModel, data: mujoco.MjData) -> TaskStatus:
        points = self.particle_positions(data)
        n = len(points)
        in_mug = self.in_mug(data, points)
        # Spheres still in a mug that hangs over the box are not poured.
        inside = self.in_container(data, points) & ~in_mug
        held_by_handle = self._handle_gripped and not self._touched_body
        poured = float(inside.sum()) / n
        metrics = {
            "poured_fraction": poured,
            "spilled_fraction": float((~inside & ~in_mug).sum()) / n,
            "left_mug_fraction": float(self._left_mug.sum()) / n,
            "held_by_handle": float(held_by_handle),
            "dropped": float(self._dropped),
            "mug_tilt_deg": self.mug_tilt_deg(data),
        }
        failure = None
        if self._touched_body:
            failure = "held_by_body"
        elif self._dropped:
            failure = "dropped"
        success = poured >= SUCCESS_FRACTION and held_by_handle and not self._dropped
        return TaskStatus(success=bool(success), metrics=metrics, failure=failure)

    def anchors_world(self, model: mujoco.MjModel, data: mujoco.MjData) -> dict[str, np.ndarray]:
        anchors = anchors_in_world(self.asset, data, self.manipulated.body_id)
        pos, rot = body_pose(data, self.objects[1].body_id)
        c = self.container
        anchors["container_center"] = pos + rot @ np.array([0.0, 0.0, c.height])
        # Inner half extents along the box's own x, y, z axes (z: floor top to wall top).
        anchors["container_half_extents"] = np.array([c.inner_x / 2, c.inner_y / 2, (c.height - c.wall) / 2])
        anchors["container_x_axis"] = rot[:, 0].copy()
        return anchors

    # -- constructed states (tests, analysis) ---------------------------------------------------------
    def place_particles(
        self, model: mujoco.MjModel, data: mujoco.MjData, inside: int, beside: int | None = None
    ) -> None:
        """Teleport ``inside`` spheres onto the box floor and the rest on the table beside the box.

        ``beside`` (default: all the others) spheres go on the table along the box's -x side; any
        left over stay where they are.
        """
        n = len(self.particle_names)
        beside = n - inside if beside is None else beside
        if inside < 0 or beside < 0 or inside + beside > n:
            raise InvalidParameterError(f"inside + beside must be within 0..{n}, got {inside} + {beside}")
        pos, rot = body_pose(data, self.objects[1].body_id)
        c, r = self.container, self.particle_radius
        pitch = 2 * r + 0.002
        cols = max(1, int((c.inner_x - 2 * r) // pitch))
        targets = []
        for k in range(inside):  # a grid on the floor, one layer per `cols * cols` spheres
            i, j, layer = k % cols, (k // cols) % cols, k // (cols * cols)
            local = [(i - (cols - 1) / 2) * pitch, (j - (cols - 1) / 2) * pitch, c.wall + r + layer * pitch]
            targets.append(pos + rot @ np.array(local))
        for k in range(beside):  # a row on the table outside the -x wall
            local = [-c.inner_x / 2 - c.wall - 0.03, (k - (beside - 1) / 2) * pitch, r + 0.0005]
            targets.append(pos + rot @ np.array(local))
        for idx, target in enumerate(targets):
            adr, dof = self._particle_qadr[idx], self._particle_dadr[idx]
            data.qpos[adr : adr + 3] = target
            data.qpos[adr + 3 : adr + 7] = (1.0, 0.0, 0.0, 0.0)
            data.qvel[dof : dof + 6] = 0.0
        mujoco.mj_forward(model, data)

    def place_mug_in_gripper(
        self, model: mujoco.MjModel, data: mujoco.MjData, part: str = "handle", tcp_site: str = "robot/tcp"
    ) -> None:
        """Teleport the mug into the open gripper: the handle bar (``part="handle"``) or the rim
        wall opposite the handle (``part="rim"``) between the jaws; sets the finger opening.

        The mug's pose follows the tcp's current pose; step the controller with the gripper
        closed afterwards (and reset it first: its reference must follow the new state).
        """
        site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, tcp_site)
        p_tcp, r_tcp = data.site_xpos[site].copy(), data.site_xmat[site].reshape(3, 3).copy()
        if part == "handle":
            p_local, r_local = handle_grasp_frame(self.asset)
            opening = pregrasp_opening(self.asset)
        elif part == "rim":
            # Jaws across the wall at the pour point, closing radially, fingers reaching down 2 cm.
            lip = self.asset.anchor("pour_point")
            r_local = np.column_stack([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
            p_local = lip - np.array([0.0, 0.0, 0.02])
            wall = float(self.asset.params.get("wall", 0.005)) * self.asset.scale
            opening = (wall / 2 + 0.006) / FINGER_MAX
        else:
            raise InvalidParameterError(f"part must be 'handle' or 'rim', got {part!r}")
        r_mug = r_tcp @ r_local.T
        p_mug = p_tcp - r_mug @ p_local
        joint = model.body_jntadr[self.manipulated.body_id]
        adr, dof = model.jnt_qposadr[joint], model.jnt_dofadr[joint]
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, r_mug.ravel())
        data.qpos[adr : adr + 3] = p_mug
        data.qpos[adr + 3 : adr + 7] = quat
        data.qvel[dof : dof + 6] = 0.0
        for name in ("robot/finger_left", "robot/finger_right"):
            j = model.joint(name)
            data.qpos[j.qposadr[0]] = opening * FINGER_MAX
            data.qvel[j.dofadr[0]] = 0.0
        mujoco.mj_forward(model, data)


def _add_particle(spec: mujoco.MjSpec, name: str, pos: np.ndarray, radius: float, rgba) -> None:
    body = spec.worldbody.add_body()
    body.name = name
    body.pos = [float(v) for v in pos]
    body.add_freejoint().name = f"{name}/free"
    g = body.add_geom()
    g.name = f"{name}/geom"
    g.type = mujoco.mjtGeom.mjGEOM_SPHERE
    g.size = [float(radius), 0.0, 0.0]
    g.density = PARTICLE_DENSITY
    g.rgba = list(rgba)
    g.friction = list(PARTICLE_FRICTION)
    g.condim = PARTICLE_CONDIM
    g.solref = list(PARTICLE_SOLREF)
    g.solmix = PARTICLE_SOLMIX
