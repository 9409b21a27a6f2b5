"""Keypoint yaw frame: train and run a policy in the manipulated object's own planar frame.

With the object's yaw drawn over the full circle (the ``hard`` setting), a world-frame policy has
to learn, from one instance's demonstrations, how every part of the motion turns with the object:
for pouring, where the handle is and from which side to reach it without touching the body. The
keypoints say how the object is turned, so the scene can be turned back instead (beyond the
paper, which conditions on keypoints without changing frames)::

    reference r (K, 2)  the training data's keypoints (x, y), centred, in one common orientation
                        (generalised Procrustes over the first step of every training episode)
    yaw        theta = argmin sum_k |Rz(theta) r_k - (k_k - c)|^2   (closed form; c: keypoint centroid)
    frame      p -> Rz(-theta) (p - o),  o = (c_x, c_y, 0)     (positions; the table stays at z = 0)
               rotations R -> Rz(-theta) R (the 6D columns turn as vectors); gripper unchanged

Origin (``yaw_origin``): the keypoint centroid by default. With ``"grasp"`` the origin is instead the
single keypoint nearest the demonstrated grasp (the tool centre where the gripper command first
reaches its episode minimum, median distance over the training episodes; on pouring this is the
handle keypoint, 0.9 cm off in x, y against 3.4 cm for the next). Beyond the paper: a policy trained
on one instance learns the approach relative to its origin, so with the centroid it reaches for the
handle at the training mug's body radius and, on a wider mug, lands a finger on the body; relative
to the handle keypoint the approach moves with the handle. The yaw is fitted on all keypoints either way.

The frame is measured at an episode's first step (the object at rest) and kept for the episode, in
training (every window of an episode uses that episode's frame) and in a rollout (fixed at the first
query), so the policy acts in one consistent, turned copy of the scene and its plan is turned back.
Keypoints are index-consistent across instances (the dual alignment score), which is what makes the
fit meaningful; for an object symmetric about its vertical axis (a bowl) the yaw is arbitrary and
the frame only adds noise. Off unless asked for (``keygen train --yaw-frame``).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from keygen.atomic import atomic_write_json
from keygen.errors import InvalidParameterError
from keygen.geometry.rotations import yaw_matrix

YAW_REFERENCE_FILE = "yaw_reference.json"
PROCRUSTES_ITERS = 10
# A gripper command this far below its episode maximum counts as "closing" (commands are in [0, 1]).
_MIN_GRIPPER_TRAVEL = 0.05


def _as_keypoints(keypoints: np.ndarray, name: str = "keypoints") -> np.ndarray:
    kp = np.asarray(keypoints, dtype=np.float64)
    if kp.ndim != 2 or kp.shape[1] not in (2, 3) or len(kp) < 2 or not np.all(np.isfinite(kp)):
        raise InvalidParameterError(f"{name} must be finite (K >= 2, 2 or 3), got shape {kp.shape}")
    return kp


def _centred_xy(kp: np.ndarray) -> np.ndarray:
    xy = kp[..., :2]
    return xy - xy.mean(-2, keepdims=True)


def estimate_yaw(keypoints: np.ndarray, reference: np.ndarray) -> float:
    """Angle (rad) turning the centred ``reference`` (K, 2) onto the keypoints' (K, 2|3) x, y."""
    a = _centred_xy(_as_keypoints(keypoints))
    b = _centred_xy(_as_keypoints(reference, "reference"))
    if a.shape != b.shape:
        raise InvalidParameterError(f"keypoints {a.shape} and reference {b.shape} differ in K")
    # 2D Kabsch: maximise sum_k a_k . Rz(theta) b_k = cos * sum(a.b) + sin * sum(a x b).
    dot = float((a * b).sum())
    cross = float((b[:, 0] * a[:, 1] - b[:, 1] * a[:, 0]).sum())
    if dot * dot + cross * cross < 1e-18:
        raise InvalidParameterError("the keypoints have no planar spread; the yaw is undefined")
    return float(np.arctan2(cross, dot))


def fit_reference(keypoints: np.ndarray, iters: int = PROCRUSTES_ITERS) -> np.ndarray:
    """(E, K, 2|3) keypoints (one set per episode) -> (K, 2) centred common shape.

    Generalised Procrustes restricted to planar rotations: start from the first set, turn every set
    onto the current mean, average, repeat. Deterministic: the first set fixes the orientation."""
    kp = np.asarray(keypoints, dtype=np.float64)
    if kp.ndim != 3 or kp.shape[2] not in (2, 3) or kp.shape[1] < 2 or len(kp) == 0:
        raise InvalidParameterError(f"keypoints must be (E >= 1, K >= 2, 2|3), got {kp.shape}")
    xy = _centred_xy(kp)
    ref = xy[0]
    for _ in range(iters):
        turned = [(yaw_matrix(-estimate_yaw(x, ref))[:2, :2] @ x.T).T for x in xy]
        mean = np.mean(turned, axis=0)
        # Keep the first set's orientation so the reference does not drift between iterations.
        ref = (yaw_matrix(estimate_yaw(xy[0], mean))[:2, :2] @ mean.T).T
    return ref


def grasp_positions(actions: np.ndarray, episode_ends: np.ndarray) -> np.ndarray:
    """(E, 3) commanded tool-centre position of each episode's grasp: the first step whose gripper
    command (action[..., 9], 0 closed, 1 open) reaches the episode's minimum."""
    act = np.asarray(actions, dtype=np.float64)
    ends = np.asarray(episode_ends, dtype=np.int64)
    if act.ndim != 2 or act.shape[1] != 10 or len(ends) == 0 or ends[-1] != len(act):
        raise InvalidParameterError(
            f"actions must be (S, 10) with episode_ends ending at S; got {act.shape} and ends {ends[-3:]}"
        )
    out = []
    for e, (a, b) in enumerate(zip(np.concatenate([[0], ends[:-1]]), ends, strict=True)):
        grip = act[a:b, 9]
        if len(grip) == 0 or grip.max() - grip.min() < _MIN_GRIPPER_TRAVEL:
            raise InvalidParameterError(
                f"episode {e} never closes its gripper; a grasp-anchored yaw frame needs a grasp in "
                f"every demonstration"
            )
        out.append(act[a + int(np.argmax(grip <= grip.min() + 1e-6)), :3])
    return np.asarray(out)


def nearest_keypoint(first_keypoints: np.ndarray, grasps: np.ndarray) -> int:
    """Index of the keypoint with the smallest median distance to the grasp over the episodes,
    from each episode's (E, K, 3) first-step keypoints and its (E, 3) grasp position."""
    kp = np.asarray(first_keypoints, dtype=np.float64)
    g = np.asarray(grasps, dtype=np.float64)
    if kp.ndim != 3 or kp.shape[2] != 3 or g.shape != (len(kp), 3) or len(kp) == 0:
        raise InvalidParameterError(
            f"need (E, K, 3) keypoints and (E, 3) grasps, got {kp.shape} and {g.shape}"
        )
    return int(np.argmin(np.median(np.linalg.norm(kp - g[:, None], axis=-1), axis=0)))


def write_reference(run_dir: str | Path, reference: np.ndarray, origin_keypoint: int | None = None) -> Path:
    ref = _as_keypoints(reference, "reference")[:, :2]
    if origin_keypoint is not None and not 0 <= origin_keypoint < len(ref):
        raise InvalidParameterError(
            f"origin keypoint {origin_keypoint} is not one of the {len(ref)} keypoints"
        )
    path = Path(run_dir) / YAW_REFERENCE_FILE
    data: dict = {"reference_xy": ref.tolist()}
    if origin_keypoint is not None:
        data["origin_keypoint"] = int(origin_keypoint)
    atomic_write_json(path, data)
    return path


def read_origin_keypoint(run_dir: str | Path) -> int | None:
    """The keypoint index a grasp-anchored frame is centred on (None: the keypoint centroid)."""
    read_reference(run_dir)  # the same clear error when the file is missing
    value = json.loads((Path(run_dir) / YAW_REFERENCE_FILE).read_text()).get("origin_keypoint")
    return None if value is None else int(value)


def read_reference(run_dir: str | Path) -> np.ndarray:
    path = Path(run_dir) / YAW_REFERENCE_FILE
    if not path.is_file():
        raise InvalidParameterError(
            f"{path} is missing: a yaw-frame policy needs the reference keypoints that `keygen train` "
            f"writes there (rerun the run's train command to rebuild it)"
        )
    return _as_keypoints(np.asarray(json.loads(path.read_text())["reference_xy"]), "reference")


@dataclass(frozen=True)
class YawFrame:
    """World -> policy: ``Rz(-yaw) (p - origin)``; policy -> world: the inverse."""

    origin: np.ndarray  # (3,) float64, (x, y, 0)
    yaw: float  # rad

    @classmethod
    def measure(
        cls, keypoints: np.ndarray, reference: np.ndarray, origin_keypoint: int | None = None
    ) -> YawFrame:
        """The frame of the manipulated object's (K, 3) keypoints against the run's reference,
        centred on their centroid or, given ``origin_keypoint``, on that keypoint (x, y)."""
        kp = _as_keypoints(keypoints)
        if origin_keypoint is not None and not 0 <= origin_keypoint < len(kp):
            raise InvalidParameterError(
                f"origin keypoint {origin_keypoint} is not one of the {len(kp)} keypoints"
            )
        origin = np.zeros(3)
        origin[:2] = kp[:, :2].mean(0) if origin_keypoint is None else kp[origin_keypoint, :2]
        return cls(origin, estimate_yaw(kp, reference))

    def _rotation(self, inverse: bool) -> np.ndarray:
        return yaw_matrix(self.yaw if inverse else -self.yaw)

    def points(self, p: np.ndarray, inverse: bool = False) -> np.ndarray:
        """(..., 3) positions into the frame (or back to the world with ``inverse``)."""
        p = np.asarray(p, dtype=np.float64)
        R = self._rotation(inverse)
        if inverse:
            return p @ R.T + self.origin
        return (p - self.origin) @ R.T

    def poses(self, x: np.ndarray, inverse: bool = False) -> np.ndarray:
        """(..., 10) tcp vectors [position, 6D rotation columns, gripper] into (or out of) the frame."""
        x = np.asarray(x, dtype=np.float64)
        if x.shape[-1] != 10:
            raise InvalidParameterError(f"tcp vectors must be (..., 10), got {x.shape}")
        R = self._rotation(inverse)
        out = x.copy()
        out[..., :3] = self.points(x[..., :3], inverse)
        out[..., 3:6] = x[..., 3:6] @ R.T
        out[..., 6:9] = x[..., 6:9] @ R.T
        return out

    def to_policy(self, feats: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """A step's features (``cloud``, ``proprio``, optional ``keypoints``) in the frame."""
        out = dict(feats)
        out["cloud"] = self.points(feats["cloud"]).astype(np.float32)
        if "keypoints" in feats:
            out["keypoints"] = self.points(feats["keypoints"]).astype(np.float32)
        out["proprio"] = self.poses(feats["proprio"]).astype(np.float32)
        return out

    def to_world(self, plan: np.ndarray) -> np.ndarray:
        """(T, 10) planned actions back to the world frame."""
        return self.poses(plan, inverse=True).astype(np.asarray(plan).dtype)


def episode_frames(
    first_keypoints: np.ndarray, reference: np.ndarray, origin_keypoint: int | None = None
) -> list[YawFrame]:
    """One frame per episode from its first step's (E, K, 3) manipulated-object keypoints."""
    return [YawFrame.measure(kp, reference, origin_keypoint) for kp in np.asarray(first_keypoints)]
