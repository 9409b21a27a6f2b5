"""MuJoCo simulation: the robot arm and gripper, its end-effector controller, and the scenes.

Import the submodules directly (``keygen.sim.robot``, ``keygen.sim.controller``); this package
file stays light so that importing ``keygen.sim`` does not pull in the IK solver.
"""

# Revision of the simulated physics. Results measured under one revision are not comparable with
# another's: evaluation records carry it (a resumed evaluation reruns episodes of another revision)
# and `keygen benchmark` fingerprints demonstrations with it (so every later stage reruns).
#   1: the first benchmark.
#   2 (2026-12-07): finger drive armature 0.1 -> 0.5 kg (`robot.FINGER_ARMATURE`): the gripper no
#      longer falls into a limit cycle that walked pinched handles out of the jaws.
PHYSICS_VERSION = 2
