import os

# Offscreen rendering on machines without a display or GPU (Mesa EGL); must precede `import mujoco`.
os.environ.setdefault("MUJOCO_GL", "egl")
