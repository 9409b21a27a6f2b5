"""Task props built from boxes: the pouring container and the knife block.

Props are static (welded to the table) or free bodies made of box geoms. Their sizes come from
the episode's generator, so the other objects of a task vary too.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from keygen.sim.object_bodies import COLLISION_GROUP


@dataclass(frozen=True)
class ContainerSpec:
    """An open-top box: inner size (x, y), wall height and thickness, metres."""

    inner_x: float
    inner_y: float
    height: float
    wall: float = 0.008

    @staticmethod
    def sample(rng: np.random.Generator) -> ContainerSpec:
        return ContainerSpec(
            inner_x=float(rng.uniform(0.12, 0.18)),
            inner_y=float(rng.uniform(0.12, 0.18)),
            height=float(rng.uniform(0.045, 0.08)),
            wall=float(rng.uniform(0.006, 0.01)),
        )


def add_box_geom(
    body: mujoco.MjsBody, name: str, center, half, rgba, visual_and_collision: bool = True
) -> None:
    g = body.add_geom()
    g.name = name
    g.type = mujoco.mjtGeom.mjGEOM_BOX
    g.pos = [float(v) for v in center]
    g.size = [float(v) for v in half]
    g.rgba = list(rgba)
    g.friction = [1.0, 0.01, 0.001]
    g.condim = 4
    if not visual_and_collision:
        g.group = COLLISION_GROUP


def add_container(spec: mujoco.MjSpec, c: ContainerSpec, name: str, pos, yaw: float, rgba) -> list[str]:
    """Add an open box container standing on the table at ``pos`` (its bottom centre); static."""
    body = spec.worldbody.add_body()
    body.name = name
    body.pos = [float(v) for v in pos]
    body.quat = [float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))]
    w, hx, hy, h = c.wall, c.inner_x / 2, c.inner_y / 2, c.height
    names = []
    parts = {
        "floor": ((0, 0, w / 2), (hx + w, hy + w, w / 2)),
        "wall_px": ((hx + w / 2, 0, h / 2), (w / 2, hy + w, h / 2)),
        "wall_nx": ((-hx - w / 2, 0, h / 2), (w / 2, hy + w, h / 2)),
        "wall_py": ((0, hy + w / 2, h / 2), (hx, w / 2, h / 2)),
        "wall_ny": ((0, -hy - w / 2, h / 2), (hx, w / 2, h / 2)),
    }
    for part, (center, half) in parts.items():
        geom_name = f"{name}/{part}"
        add_box_geom(body, geom_name, center, half, rgba)
        names.append(geom_name)
    return names


@dataclass(frozen=True)
class KnifeBlockSpec:
    """A block with one vertical slot: outer size, slot size (x along the slot), metres."""

    size_x: float
    size_y: float
    height: float
    slot_length: float  # along the block's x axis
    slot_width: float  # along y
    slot_depth: float

    @staticmethod
    def for_blade(rng: np.random.Generator, blade_width: float, blade_thickness: float, blade_length: float):
        """A block whose slot fits the blade with random clearances, deep enough for half the blade."""
        slot_length = blade_width + float(rng.uniform(0.015, 0.03))
        slot_width = max(blade_thickness, 0.002) + float(rng.uniform(0.008, 0.014))
        slot_depth = max(0.6 * blade_length, 0.06) + float(rng.uniform(0.0, 0.02))
        margin = float(rng.uniform(0.025, 0.04))
        return KnifeBlockSpec(
            size_x=slot_length + 2 * margin,
            size_y=slot_width + 2 * float(rng.uniform(0.03, 0.045)),
            height=slot_depth + float(rng.uniform(0.01, 0.02)),
            slot_length=slot_length,
            slot_width=slot_width,
            slot_depth=slot_depth,
        )


def add_knife_block(spec: mujoco.MjSpec, b: KnifeBlockSpec, name: str, pos, yaw: float, rgba) -> list[str]:
    """Add a static knife block at ``pos`` (bottom centre) built from five boxes around the slot."""
    body = spec.worldbody.add_body()
    body.name = name
    body.pos = [float(v) for v in pos]
    body.quat = [float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))]
    H, bottom = b.height, b.height - b.slot_depth
    sx, sy, lx, ly = b.size_x / 2, b.size_y / 2, b.slot_length / 2, b.slot_width / 2
    parts = {
        "base": ((0, 0, bottom / 2), (sx, sy, bottom / 2)),
        "side_py": ((0, (sy + ly) / 2, (H + bottom) / 2), (sx, (sy - ly) / 2, b.slot_depth / 2)),
        "side_ny": ((0, -(sy + ly) / 2, (H + bottom) / 2), (sx, (sy - ly) / 2, b.slot_depth / 2)),
        "end_px": (((sx + lx) / 2, 0, (H + bottom) / 2), ((sx - lx) / 2, ly, b.slot_depth / 2)),
        "end_nx": ((-(sx + lx) / 2, 0, (H + bottom) / 2), ((sx - lx) / 2, ly, b.slot_depth / 2)),
    }
    names = []
    for part, (center, half) in parts.items():
        geom_name = f"{name}/{part}"
        add_box_geom(body, geom_name, center, half, rgba)
        names.append(geom_name)
    return names
