"""Target token: where the object the task places into stands, as one conditioning token.

Beyond the paper. Pouring and knife collecting each have a second task object, the placement
target (the box, the knife block), which the policy sees only as part of the object-centric cloud:
only the manipulated object has keypoints. A PointNet's max-pooled feature has to recover the
target's position from that cloud, and in a yaw frame fitted to the manipulated object the target
can lie in any direction. In the pouring failures a quarter of the timeouts poured beside the box
(docs/benchmark.md, "Where the pours fail"). The token states the target's place directly::

    points     the target's cloud points (label TARGET_LABEL in object_cloud_ids)
    centre     the centre (x, y) of the smallest-area rectangle around their horizontal projection
               (keygen.policies.target_frame: one side along a convex hull edge)
    top        the highest point's z (the box's wall top, the block's top face)
    extents    the rectangle's two half sides, larger first (a box turned by 90 degrees is the same
               box, so the sides carry no order)
    token      (centre_x, centre_y, top, half_long, half_short): 5 numbers, metres

Measured once per episode on its first observation (the target is static), like the yaw frames, so
a gripper passing in front of the target later cannot move it. The position (first three numbers)
goes through the policy's frame like any point; the extents are lengths and do not turn. A
hand-written geometric measurement, not learnt; tested on constructed boxes in
tests/policies/test_target_token.py.
"""

from __future__ import annotations

import numpy as np

from keygen.errors import InvalidParameterError
from keygen.policies.target_frame import TARGET_LABEL, bounding_rectangle

TARGET_DIM = 5
MIN_TARGET_POINTS = 12
# Tasks whose placement target has no keypoints of its own (stacking's target bowl has them).
TARGET_TOKEN_TASKS = ("pour", "knife")


def measure_target(points: np.ndarray) -> np.ndarray:
    """(5,) float32 target token of the target's (N, 3) world points (see the module docstring)."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or not np.all(np.isfinite(p)):
        raise InvalidParameterError(f"target points must be a finite (N, 3) array, got shape {p.shape}")
    if len(p) < MIN_TARGET_POINTS:
        raise InvalidParameterError(
            f"the target shows {len(p)} points, fewer than {MIN_TARGET_POINTS}: is it in view and "
            f"labelled {TARGET_LABEL} in object_cloud_ids?"
        )
    u, v, centre = bounding_rectangle(p[:, :2])
    half = np.sort([np.ptp(p[:, :2] @ u) / 2, np.ptp(p[:, :2] @ v) / 2])[::-1]
    return np.array([centre[0], centre[1], p[:, 2].max(), half[0], half[1]], dtype=np.float32)


def target_in_frame(token: np.ndarray, frame) -> np.ndarray:
    """``token`` (..., 5) with its position mapped by ``frame`` (a YawFrame, or anything with a
    ``points`` method); the extents are unchanged."""
    token = np.asarray(token)
    if token.shape[-1] != TARGET_DIM:
        raise InvalidParameterError(f"a target token has {TARGET_DIM} numbers, got shape {token.shape}")
    out = token.astype(np.float32, copy=True)
    out[..., :3] = frame.points(token[..., :3])
    return out
