"""Robot-base input: where the arm stands, seen from a policy that works in a yaw frame.

Beyond the paper. A yaw frame (keygen.policies.yaw_frame, target_frame) turns and shifts each
episode so that the manipulated object (or the target) always looks the same; the price is that the
arm's base, fixed in the world, now lies in a different place in every episode. The policy then
knows where the base is only through its proprioception at the episode's first steps (the arm
starts at one home pose in the world), and its observation history is two steps long. Yet the
demonstrator's plan depends on it: on pouring the policy failed most where the handle lies at the
arm's reach limit (docs/benchmark.md, "Pouring under revision 2"), where the expert's grasp and
transport change with the handle's distance and direction from the base. This input states it::

    base       frame.points(0): the robot base (the world origin) in the episode's frame, x, y (m)
    heading    the world's +x axis in the episode's frame: cos(-yaw), sin(-yaw)
    input      (base_x, base_y, cos, sin): 4 numbers, fixed for the episode

It is added to the DiT's conditioning vector (the proprioception token and every block's adaLN), as
the object frame's origin is. Fixed for an episode because the frame is; exact in training (the
frame of the recorded keypoints) and measured with the frame at a rollout's first query. Measured on
pouring it did not help, at the reach limit or overall (docs/policies.md, "Robot-base input"): the
policy's failures there are not for want of knowing where the base is. Off by default.
"""

from __future__ import annotations

import numpy as np

from keygen.policies.yaw_frame import YawFrame

BASE_DIM = 4


def base_in_frame(frame: YawFrame) -> np.ndarray:
    """(4,) float32: the robot base's (x, y) in ``frame`` and the world's +x axis there."""
    base = frame.points(np.zeros(3))
    return np.array([base[0], base[1], np.cos(-frame.yaw), np.sin(-frame.yaw)], dtype=np.float32)


def episode_bases(frames: list[YawFrame], episode_ends: np.ndarray) -> np.ndarray:
    """(S, 4) robot-base input of every step: its episode's."""
    ends = np.asarray(episode_ends, dtype=np.int64)
    lengths = np.diff(np.concatenate([[0], ends]))
    per_episode = np.stack([base_in_frame(f) for f in frames]) if frames else np.zeros((0, BASE_DIM))
    return np.repeat(per_episode.astype(np.float32), lengths, axis=0)
