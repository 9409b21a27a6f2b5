"""benchmarks/policy_fit.py: where the open-loop fit is queried in a demonstration."""

from __future__ import annotations

import numpy as np


def _actions(grip: list[float]) -> np.ndarray:
    actions = np.zeros((len(grip), 10), np.float32)
    actions[:, 9] = grip
    return actions


def test_pour_approach_opening_is_not_mistaken_for_the_close(policy_fit):
    # The pour expert approaches with a fitted opening (here 0.2 of the stroke), closes to 0 at step 30.
    grip = [1.0] * 100 + [0.2] * 30 + [0.0] * 20  # the episode is steps 100-149 of the store
    steps = policy_fit.query_steps(_actions(grip), 100, 150)
    assert steps == {"t0": 100, "t8": 108, "pre_close": 100 + 30 - 8}


def test_open_then_close_and_never_close(policy_fit):
    steps = policy_fit.query_steps(_actions([1.0] * 12 + [0.0] * 8), 0, 20)
    assert steps["pre_close"] == 4
    # Never closing: the query falls back on the last step's window (8 before the end).
    steps = policy_fit.query_steps(_actions([1.0] * 20), 0, 20)
    assert steps["pre_close"] == 20 - 1 - 8
