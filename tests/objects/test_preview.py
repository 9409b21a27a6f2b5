import os

import numpy as np
from PIL import Image

from keygen.objects.preview import anchor_colours, contact_sheet, render_asset


def test_rendering_uses_egl():
    assert os.environ["MUJOCO_GL"] == "egl"


def test_render_asset_shows_object_and_anchor_colours(bowl_asset):
    img = render_asset(bowl_asset, size=128)
    assert img.shape == (128, 128, 3) and img.dtype == np.uint8
    assert img.std() > 5  # not a blank frame
    # the rim-grasp marker's colour appears somewhere in the picture
    colour = np.array(anchor_colours("bowl")["rim_grasp"]) * 255
    close = np.linalg.norm(img.astype(float) - colour, axis=-1) < 60
    assert close.sum() > 3


def test_contact_sheet_grid(tmp_path, bowl_asset):
    out = contact_sheet(
        [bowl_asset, bowl_asset.scaled(1.3)], tmp_path / "s.png", columns=2, tile=96, title="t"
    )
    w, h = Image.open(out).size
    assert w == 192 and h > 96
