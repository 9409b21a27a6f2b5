"""A PNG grid of scans with their keypoints coloured by index (same colour = same keypoint index).

Each cell is one scan drawn in its object's canonical frame (via the true pose, so every instance is
seen from the same side and parts line up across cells): grey points shaded by depth, keypoints as
coloured discs numbered by index, drawn nearest-last. Plain PIL, no plotting library.
"""

from __future__ import annotations

import colorsys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from keygen.errors import InvalidParameterError

__all__ = ["draw_cell", "keypoint_colours", "save_grid"]


def keypoint_colours(k: int) -> list[tuple[int, int, int]]:
    """``k`` distinct saturated colours (hues evenly spaced), index i always the same colour."""
    return [tuple(int(255 * c) for c in colorsys.hsv_to_rgb(i / max(k, 1), 0.9, 0.95)) for i in range(k)]


def _view_matrix(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Rows: screen right, screen up, towards the viewer, for a camera circling the z axis."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    toward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    right = np.cross([0.0, 0.0, 1.0], toward)
    right /= np.linalg.norm(right)
    up = np.cross(toward, right)
    return np.stack([right, up, toward])


def draw_cell(
    points: np.ndarray,
    keypoints: np.ndarray,
    size: int = 256,
    azimuth_deg: float = -60.0,
    elevation_deg: float = 25.0,
    title: str = "",
) -> Image.Image:
    """One cell: ``points`` (N, 3) and ``keypoints`` (K, 3) in the same (object) frame."""
    pts, kp = np.asarray(points, np.float64), np.asarray(keypoints, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or kp.ndim != 2 or kp.shape[1] != 3:
        raise InvalidParameterError(
            f"points and keypoints must be (N, 3) and (K, 3), got {pts.shape}, {kp.shape}"
        )
    V = _view_matrix(azimuth_deg, elevation_deg)
    centre = pts.mean(axis=0)
    p2, k2 = (pts - centre) @ V.T, (kp - centre) @ V.T  # (N, 3), (K, 3): x right, y up, z toward viewer
    half = max(np.abs(p2[:, :2]).max(), np.abs(k2[:, :2]).max(), 1e-6) * 1.1
    to_px = lambda q: np.stack([(q[:, 0] / half + 1) * size / 2, (1 - q[:, 1] / half) * size / 2], 1)  # noqa: E731
    img = Image.new("RGB", (size, size), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    order = np.argsort(p2[:, 2])  # far first
    depth = (p2[:, 2] - p2[:, 2].min()) / max(np.ptp(p2[:, 2]), 1e-9)
    for (x, y), d in zip(to_px(p2[order]), depth[order], strict=True):
        g = int(200 - 110 * d)  # nearer is darker
        draw.ellipse([x - 1.5, y - 1.5, x + 1.5, y + 1.5], fill=(g, g, g))
    colours = keypoint_colours(len(kp))
    radius = max(4, size // 40)
    for i in np.argsort(k2[:, 2]):
        x, y = to_px(k2[i : i + 1])[0]
        draw.ellipse([x - radius, y - radius, x + radius, y + radius], fill=colours[i], outline=(0, 0, 0))
        draw.text((x + radius, y - 2 * radius), str(i), fill=(0, 0, 0))
    if title:
        draw.text((4, 4), title, fill=(0, 0, 0))
    return img


def save_grid(
    cells: Sequence[tuple[np.ndarray, np.ndarray, str]], path: str | Path, columns: int = 4, size: int = 256
) -> Path:
    """Tile ``(points, keypoints, title)`` cells into a PNG at ``path``; returns it."""
    if not cells:
        raise InvalidParameterError("save_grid needs at least one cell")
    images = [draw_cell(p, k, size=size, title=t) for p, k, t in cells]
    rows = (len(images) + columns - 1) // columns
    sheet = Image.new("RGB", (columns * size, rows * size), (255, 255, 255))
    for i, im in enumerate(images):
        sheet.paste(im, ((i % columns) * size, (i // columns) * size))
    draw = ImageDraw.Draw(sheet)
    for c in range(1, columns):
        draw.line([(c * size, 0), (c * size, rows * size)], fill=(220, 220, 220))
    for r in range(1, rows):
        draw.line([(0, r * size), (columns * size, r * size)], fill=(220, 220, 220))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(path)
    return path
