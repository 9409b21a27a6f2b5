"""The expert interface.

An expert is a state machine written as a Python generator: ``script`` yields one absolute
end-effector target (10 numbers, the env's action) at a time and receives the next
``(obs, info)`` back, so each phase reads like straight-line code with its guards::

    def script(self, obs, info):
        anchors = info["anchors"]
        # pre-grasp: above the handle, gripper open
        obs, info = yield target(above, down, OPEN)
        ...

Experts may read privileged information (``info["anchors"]``, the env's task) — that is what
makes them experts — but they are parameterised only by anchors, never tuned per instance. When
an expert gives up (a missed grasp after its retry, an unreachable pose) it sets ``failure`` and
stops; the runner then ends the episode with that reason.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Generator
from typing import Any

import numpy as np

from keygen.errors import KeyGenError
from keygen.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle, matrix_to_rot6d

OPEN, CLOSED = 1.0, 0.0

Action = np.ndarray
Step = tuple[dict[str, np.ndarray], dict[str, Any]]


def smooth_fraction(s: float) -> float:
    """Cosine timing of a straight move: 0 -> 1 as ``s`` goes 0 -> 1, with zero speed at both ends."""
    return float(0.5 - 0.5 * np.cos(np.pi * np.clip(s, 0.0, 1.0)))


def interpolate_rotation(r0: np.ndarray, r1: np.ndarray, s: float) -> np.ndarray:
    """Geodesic interpolation (slerp) from ``r0`` (s = 0) to ``r1`` (s = 1) about one constant axis."""
    return r0 @ axis_angle_to_matrix(s * matrix_to_axis_angle(r0.T @ r1))


class ExpertGaveUp(KeyGenError):
    """Raised inside a script to stop with a failure reason (caught by :class:`Expert`)."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def target(position: np.ndarray, rotation: np.ndarray, gripper: float) -> Action:
    """The env action for a tcp pose (rotation matrix, columns = tcp axes in the world) and gripper."""
    return np.concatenate(
        [np.asarray(position, float), matrix_to_rot6d(np.asarray(rotation, float)), [gripper]]
    )


class Expert(ABC):
    """Base class: runs :meth:`script` as a generator; ``act`` returns its next action."""

    task: str

    def __init__(self) -> None:
        self.failure: str | None = None
        self.phase: str = "start"
        self._gen: Generator[Action, Step, None] | None = None
        self._last: Action | None = None

    @abstractmethod
    def script(self, env, obs: dict, info: dict) -> Generator[Action, Step, None]:
        """Yield actions phase by phase; receives ``(obs, info)`` after each step."""

    def reset(self, env, obs: dict, info: dict) -> None:
        self.failure, self.phase, self._last = None, "start", None
        self._env = env
        self._gen = self.script(env, obs, info)
        self._pending_first = True

    @property
    def done(self) -> bool:
        return self._gen is None

    def act(self, obs: dict, info: dict) -> Action | None:
        """The next action, or None when the script has finished (or given up)."""
        if self._gen is None:
            return None
        try:
            if self._pending_first:
                self._pending_first = False
                action = next(self._gen)
            else:
                action = self._gen.send((obs, info))
        except StopIteration:
            self._gen = None
            return None
        except ExpertGaveUp as stop:
            self.failure = f"expert_{stop.reason}"
            self._gen = None
            return None
        self._last = np.asarray(action, dtype=np.float64)
        return self._last
