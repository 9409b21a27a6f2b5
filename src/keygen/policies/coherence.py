"""Choosing one of several sampled trajectories so that consecutive predictions agree.

A diffusion policy run with receding horizon draws a fresh trajectory every ``execute_steps``
actions. Where the demonstrations hold several ways to do a task (which lip of the mug to pour
over, how far to turn), two consecutive draws can follow different ways, and the robot switches
between them half-way. Backward coherence (the backward half of "bidirectional decoding",
Liu et al., 2024) draws several candidates per query and runs the one whose start agrees best with
what the previous trajectory planned for the same steps, so a way once begun is kept. The cost is
a batch of candidates per query instead of one.

Distances are taken in the policy's normalised action space, the space the network denoises in,
with weights ``decay ** k`` on the k-th overlapping step: the far end of the previous plan is the
part it was least sure of.
"""

from __future__ import annotations

import numpy as np

from keygen.errors import InvalidParameterError

# Weight of the k-th overlapping step is COHERENCE_DECAY ** k (0.9: the 8th step counts about half).
COHERENCE_DECAY = 0.9


def check_samples(samples: int, name: str = "samples") -> int:
    """``samples`` if it is a valid number of trajectories per query (an int >= 1); ``name`` is the
    argument's name in the error."""
    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
        raise InvalidParameterError(f"{name} must be an int >= 1, got {samples!r}")
    return samples


def coherence_costs(candidates: np.ndarray, previous_tail: np.ndarray, decay: float) -> np.ndarray:
    """(N,) weighted squared distances between each candidate's first steps and ``previous_tail``.

    ``candidates`` is (N, T, D); ``previous_tail`` (L, D) holds the previous plan's actions for the
    candidates' first ``L`` steps (only the first ``min(L, T)`` are compared)."""
    candidates = np.asarray(candidates, dtype=np.float64)
    tail = np.asarray(previous_tail, dtype=np.float64)
    if candidates.ndim != 3 or tail.ndim != 2 or tail.shape[-1] != candidates.shape[-1]:
        raise InvalidParameterError(
            f"candidates must be (N, T, D) and the previous tail (L, D), got {candidates.shape} "
            f"and {tail.shape}"
        )
    if not 0.0 < decay <= 1.0:
        raise InvalidParameterError(f"decay must be in (0, 1], got {decay}")
    overlap = min(len(tail), candidates.shape[1])
    weights = decay ** np.arange(overlap)
    sq = ((candidates[:, :overlap] - tail[None, :overlap]) ** 2).sum(axis=-1)  # (N, overlap)
    return sq @ weights


def choose_coherent(
    candidates: np.ndarray, previous_plan: np.ndarray | None, executed: int, decay: float
) -> int:
    """Index of the candidate to run. ``previous_plan`` (T, D) is the trajectory chosen at the previous
    query, of which the first ``executed`` actions were run; with no previous plan, or nothing of it
    left to overlap (``executed`` >= T), the first candidate is taken, as a single draw would be."""
    if previous_plan is None or executed >= len(previous_plan):
        return 0
    if executed < 0:
        raise InvalidParameterError(f"executed must be >= 0, got {executed}")
    return int(np.argmin(coherence_costs(candidates, np.asarray(previous_plan)[executed:], decay)))
