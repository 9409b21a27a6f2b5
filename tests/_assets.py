"""Small hand-made assets for tests that must not depend on the procedural generators."""

import numpy as np

from keygen.objects.asset import Anchor, Asset, MassProperties
from keygen.objects.meshing import disc_part, revolve_profile, ring_wall_parts


def simple_bowl(instance_id: str = "bowl-test-x") -> Asset:
    """A straight-walled bowl, 12 cm across and 5 cm tall."""
    r, h, w = 0.06, 0.05, 0.005
    profile = np.array([[0, 0], [r, 0], [r, h], [r - w, h], [r - w, w], [0, w]])
    visual = revolve_profile(profile, sections=48)
    parts = ring_wall_parts(np.array([w, h]), np.array([r - w, r - w]), np.array([r, r]), 16)
    parts.append(disc_part(r, 0.0, w))
    anchors = {
        "rim_grasp": Anchor("point", [r - w / 2, 0, h - 0.005]),
        "opening_center": Anchor("point", [0, 0, h]),
        "bottom_center": Anchor("point", [0, 0, 0]),
        "rim_radius": Anchor("scalar", [r]),
    }
    return Asset("bowl", instance_id, visual, parts, MassProperties.from_mesh(visual, 2000.0), anchors)
