"""Contact sheets: a grid of asset renders with their semantic anchors marked.

Each asset is rendered offscreen by MuJoCo (``MUJOCO_GL=egl`` on headless machines) on its own:
the visual mesh, small spheres at point anchors, short arrows along direction anchors, and a
ring for scalar radii. Colours are fixed per anchor name so the same anchor has the same colour
across a sheet.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from keygen.objects.asset import CATEGORY_ANCHORS, Asset

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402  (MUJOCO_GL must be set before the import)

# Distinct, colour-blind-friendly colours (Okabe-Ito), cycled over each category's anchor names.
_PALETTE = [
    (0.90, 0.62, 0.00),
    (0.34, 0.71, 0.91),
    (0.00, 0.62, 0.45),
    (0.94, 0.89, 0.26),
    (0.00, 0.45, 0.70),
    (0.84, 0.37, 0.00),
    (0.80, 0.47, 0.65),
]
# Where the camera looks from, per category, in the asset's canonical frame (unit-less direction).
_VIEW_DIRECTIONS = {"mug": (0.45, -1.0, 0.6), "knife": (0.15, -0.6, 1.0), "bowl": (0.8, -1.2, 1.1)}


def anchor_colours(category: str) -> dict[str, tuple[float, float, float]]:
    names = list(CATEGORY_ANCHORS[category])
    return {name: _PALETTE[i % len(_PALETTE)] for i, name in enumerate(names)}


def _scene_xml_spec(asset: Asset, mesh_file: Path) -> mujoco.MjSpec:
    spec = mujoco.MjSpec()
    spec.visual.global_.offwidth = 1024
    spec.visual.global_.offheight = 1024
    spec.visual.headlight.ambient = [0.45, 0.45, 0.45]
    spec.visual.headlight.diffuse = [0.6, 0.6, 0.6]
    sky = spec.add_texture()
    sky.name = "sky"
    sky.type = mujoco.mjtTexture.mjTEXTURE_SKYBOX
    sky.builtin = mujoco.mjtBuiltin.mjBUILTIN_GRADIENT
    sky.rgb1 = [1.0, 1.0, 1.0]
    sky.rgb2 = [0.85, 0.87, 0.9]
    sky.width = sky.height = 64
    mesh = spec.add_mesh()
    mesh.name = "visual"
    mesh.file = str(mesh_file)
    world = spec.worldbody
    body = world.add_body()
    geom = body.add_geom()
    geom.type = mujoco.mjtGeom.mjGEOM_MESH
    geom.meshname = "visual"
    geom.rgba = [0.78, 0.78, 0.82, 0.55]
    geom.contype = geom.conaffinity = 0
    size = float(np.linalg.norm(asset.bbox[1] - asset.bbox[0]))
    marker = 0.025 * size
    colours = anchor_colours(asset.category)
    for name, anchor in (asset.anchors or {}).items():
        if name not in colours:
            continue
        rgba = [*colours[name], 1.0]
        if anchor.kind == "point":
            g = world.add_geom()
            g.type = mujoco.mjtGeom.mjGEOM_SPHERE
            g.size = [marker, 0, 0]
            g.pos = anchor.value
            g.rgba = rgba
        elif anchor.kind == "direction":
            origin = _direction_origin(asset, name)
            g = world.add_geom()
            g.type = mujoco.mjtGeom.mjGEOM_CAPSULE
            g.fromto = np.concatenate([origin, origin + 0.25 * size * anchor.value])
            g.size = [0.35 * marker, 0, 0]
            g.rgba = rgba
        else:  # a scalar radius: a thin ring of small spheres at the opening height
            centre = asset.anchors.get("opening_center")
            z = centre.value[2] if centre is not None else asset.bbox[1][2]
            for a in np.linspace(0, 2 * np.pi, 24, endpoint=False):
                g = world.add_geom()
                g.type = mujoco.mjtGeom.mjGEOM_SPHERE
                g.size = [0.3 * marker, 0, 0]
                g.pos = [anchor.value[0] * np.cos(a), anchor.value[0] * np.sin(a), z]
                g.rgba = rgba
    return spec


def _direction_origin(asset: Asset, name: str) -> np.ndarray:
    """Where to draw a direction arrow from: the point anchor it belongs to."""
    owners = {
        "grasp_approach": "handle_grasp",
        "handle_axis": "handle_grasp",
        "blade_axis": "blade_base",
        "edge_direction": "blade_base",
    }
    owner = owners.get(name)
    if owner and asset.anchors and owner in asset.anchors:
        return asset.anchors[owner].value
    return asset.bbox.mean(axis=0)


def render_asset(asset: Asset, size: int = 256, tmp_dir: str | os.PathLike | None = None) -> np.ndarray:
    """Render one asset with its anchors; returns an (size, size, 3) uint8 image."""
    import tempfile

    with tempfile.TemporaryDirectory(dir=tmp_dir) as tmp:
        mesh_file = Path(tmp) / "visual.obj"
        asset.visual.export(mesh_file)
        model = _scene_xml_spec(asset, mesh_file).compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    centre = asset.bbox.mean(axis=0)
    radius = 0.5 * float(np.linalg.norm(asset.bbox[1] - asset.bbox[0]))
    direction = np.asarray(_VIEW_DIRECTIONS.get(asset.category, (1.0, -1.0, 1.0)), dtype=float)
    direction /= np.linalg.norm(direction)
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_FREE
    camera.lookat[:] = centre
    camera.distance = radius / np.sin(np.deg2rad(model.vis.global_.fovy / 2)) * 1.05
    # MuJoCo's free camera sits at lookat - distance * forward(azimuth, elevation): point forward
    # from the camera to the object, i.e. against the view direction.
    camera.azimuth = float(np.rad2deg(np.arctan2(-direction[1], -direction[0])))
    camera.elevation = -float(np.rad2deg(np.arcsin(direction[2])))
    with mujoco.Renderer(model, size, size) as renderer:
        renderer.update_scene(data, camera)
        return renderer.render().copy()


def contact_sheet(
    assets: Sequence[Asset],
    out: str | os.PathLike,
    columns: int = 6,
    tile: int = 256,
    title: str | None = None,
) -> Path:
    """Render ``assets`` into a labelled grid PNG with an anchor legend; returns the path."""
    if not assets:
        raise ValueError("contact_sheet needs at least one asset")
    rows = (len(assets) + columns - 1) // columns
    label_h, legend_h = 18, 22 if assets[0].anchors else 0
    title_h = 24 if title else 0
    sheet = Image.new("RGB", (columns * tile, title_h + legend_h + rows * (tile + label_h)), "white")
    draw = ImageDraw.Draw(sheet)
    if title:
        draw.text((8, 6), title, fill="black")
    x = 8
    for name, colour in anchor_colours(assets[0].category).items():
        if not assets[0].anchors:
            break
        rgb = tuple(int(255 * c) for c in colour)
        draw.rectangle([x, title_h + 6, x + 10, title_h + 16], fill=rgb)
        draw.text((x + 14, title_h + 5), name, fill="black")
        x += 18 + 7 * len(name)
    for i, asset in enumerate(assets):
        r, c = divmod(i, columns)
        top = title_h + legend_h + r * (tile + label_h)
        sheet.paste(Image.fromarray(render_asset(asset, tile)), (c * tile, top))
        style = asset.params.get("style", "")
        scale = f" x{asset.scale:g}" if abs(asset.scale - 1.0) > 1e-9 else ""
        draw.text((c * tile + 4, top + tile + 2), f"{asset.instance_id} {style}{scale}", fill="black")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out)
    return out
