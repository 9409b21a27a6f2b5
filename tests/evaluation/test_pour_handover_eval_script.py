"""benchmarks/pour_handover_eval.py: the hand-over from the approaching to the carrying policy, the
frame it hands over, and refusing runs whose frames do not share a reference."""

from __future__ import annotations

import json

import numpy as np
import pytest


@pytest.fixture(scope="module")
def m(load_benchmark_script):
    return load_benchmark_script("pour_handover_eval")


class FakeRunner:
    """Plays back gripper commands; records what it was shown."""

    def __init__(self, name: str, grippers: list[float]):
        self.name, self.grippers = name, grippers
        self.seen: list[int] = []
        self.acted: list[int] = []
        self.yaw_frame = f"frame of {name}"
        self.reset_seeds: list[int | None] = []

    def reset(self, seed=None):
        self.seen, self.acted = [], []
        self.reset_seeds.append(seed)

    def observe(self, obs):
        self.seen.append(obs["t"])

    def act(self, obs):
        self.observe(obs)
        self.acted.append(obs["t"])
        action = np.zeros(10)
        action[9] = self.grippers[len(self.acted) - 1]
        return action


def test_the_carrier_takes_over_after_the_first_closing_command_with_the_approach_frame(m) -> None:
    approach = FakeRunner("approach", [1.0, 1.0, 0.2, 1.0])
    carry = FakeRunner("carry", [0.0] * 5)
    runner = m.HandoverRunner(approach, carry)
    runner.reset(seed=7)
    assert approach.reset_seeds == [7] and carry.reset_seeds == [7]
    actions = [runner.act({"t": t}) for t in range(5)]
    assert approach.acted == [0, 1, 2]  # it closes at step 2, and that action still runs
    assert carry.acted == [3, 4] and carry.seen == [0, 1, 2, 3, 4]  # it saw the whole episode
    assert carry.yaw_frame == "frame of approach"
    assert [a[9] for a in actions] == [1.0, 1.0, 0.2, 0.0, 0.0]
    runner.reset(seed=8)  # a new episode starts with the approaching policy again
    assert not runner.handed_over and runner.act({"t": 0})[9] == 1.0 and approach.acted == [0]


def test_runs_must_share_the_yaw_frame_reference(m, tmp_path) -> None:
    a, b, c = (tmp_path / n for n in "abc")
    for run, ref in ((a, {"k": 1}), (b, {"k": 1}), (c, {"k": 2})):
        run.mkdir()
        (run / "yaw_reference.json").write_text(json.dumps(ref))
    m.check_same_frame_reference(a, b)
    with pytest.raises(SystemExit, match="different references"):
        m.check_same_frame_reference(a, c)
    with pytest.raises(SystemExit, match="not yaw-frame policy runs"):
        m.check_same_frame_reference(a, tmp_path / "missing")
