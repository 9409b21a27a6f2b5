"""MuJoCo simulation: the robot arm and gripper, its end-effector controller, and the scenes.

Import the submodules directly (``keygen.sim.robot``, ``keygen.sim.controller``); this package
file stays light so that importing ``keygen.sim`` does not pull in the IK solver.
"""
