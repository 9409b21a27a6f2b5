"""KeyGen: category-level robot manipulation with self-supervised 3D keypoints.

Importing ``keygen`` registers the gymnasium environments ``keygen/Pour-v0``,
``keygen/CollectKnife-v0`` and ``keygen/StackBowl-v0``; everything else lives in sub-packages
(``keygen.objects``, ``keygen.geometry``, ``keygen.sim``, ``keygen.perception``).
"""

import os

# Offscreen rendering without a display (Mesa EGL on CPU-only machines). It must be set before
# the first `import mujoco` anywhere in the process, so it is set here, on the package's import;
# a value the user already set wins.
os.environ.setdefault("MUJOCO_GL", "egl")

from keygen.sim.registration import ENV_IDS, register_envs  # noqa: E402

__version__ = "0.1.0"
__all__ = ["ENV_IDS", "__version__", "register_envs"]

register_envs()
