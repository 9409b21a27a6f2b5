"""Backward coherence (keygen.policies.coherence): costs known by hand, the candidate that continues
the previous plan is chosen, and a runner with several samples per query runs exactly that one."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from _policy_runs import TINY_POLICY, tiny_train_config
from keygen.cli.eval import default_out
from keygen.errors import InvalidParameterError
from keygen.evaluation.evaluate import evaluate
from keygen.policies import DiffusionPolicy, load_runner, make_policy_config, train_policy
from keygen.policies.coherence import choose_coherent, coherence_costs


def test_costs_by_hand() -> None:
    # Two candidates of 3 steps in 2-D; the tail covers 2 steps; decay 0.5 weighs them 1 and 0.5.
    candidates = np.array([[[0, 0], [0, 0], [9, 9]], [[1, 0], [0, 2], [0, 0]]], float)
    tail = np.zeros((2, 2))
    np.testing.assert_allclose(coherence_costs(candidates, tail, 0.5), [0.0, 1.0 + 0.5 * 4.0])
    # A tail longer than the candidates is cut to their length.
    np.testing.assert_allclose(coherence_costs(candidates, np.zeros((5, 2)), 1.0), [162.0, 5.0])


def test_the_candidate_that_continues_the_previous_plan_is_chosen() -> None:
    rng = np.random.default_rng(0)
    previous = rng.normal(size=(16, 10))
    executed = 8
    candidates = rng.normal(size=(6, 16, 10))
    candidates[4, :8] = previous[8:] + 0.01 * rng.normal(size=(8, 10))  # continues the previous plan
    assert choose_coherent(candidates, previous, executed, 0.9) == 4
    # Nothing to agree with: the first candidate, as a single draw would run.
    assert choose_coherent(candidates, None, executed, 0.9) == 0
    assert choose_coherent(candidates, previous, 16, 0.9) == 0


def test_bad_input_is_refused() -> None:
    with pytest.raises(InvalidParameterError, match="decay"):
        coherence_costs(np.zeros((2, 4, 10)), np.zeros((3, 10)), 0.0)
    with pytest.raises(InvalidParameterError, match="shape|must be"):
        coherence_costs(np.zeros((4, 10)), np.zeros((3, 10)), 0.9)
    with pytest.raises(InvalidParameterError, match="executed"):
        choose_coherent(np.zeros((2, 4, 10)), np.zeros((4, 10)), -1, 0.9)


@pytest.fixture
def tiny_run(tiny_store, tmp_path, fake_keypoints):
    config = tiny_train_config("keygen", tiny_store, tmp_path / "run", fake_keypoints)
    return train_policy(config, progress=False)


def test_runner_runs_the_most_coherent_of_its_samples(tiny_run, kit) -> None:
    runner = load_runner(tiny_run, execute_steps=4, samples=5)
    drawn = []
    original = runner.model.predict

    def recording_predict(inputs, **kw):
        plans = original(inputs, **kw)
        drawn.append(plans.clone())
        return plans

    runner.model.predict = recording_predict
    ep = kit.synthetic_episode(0)
    plans = []
    for t in range(9):  # queries at steps 0, 4 and 8
        runner.act(kit.observation(ep, t))
        if t % 4 == 0:
            plans.append(runner.last_plan.copy())
    assert [d.shape[0] for d in drawn] == [5, 5, 5]
    # The first query has nothing to agree with and runs the first sample.
    np.testing.assert_allclose(plans[0], drawn[0][0].numpy(), atol=1e-6)
    # Later queries run the sample closest, in normalised actions, to what the previous plan still held.
    normalise = runner.model.normalizer.normalize_action
    for q in (1, 2):
        previous = normalise(torch.from_numpy(plans[q - 1])).numpy()
        costs = coherence_costs(normalise(drawn[q]).numpy(), previous[4:], runner.coherence_decay)
        np.testing.assert_allclose(plans[q], drawn[q][int(np.argmin(costs))].numpy(), atol=1e-6)
    runner.reset()  # a new episode starts with nothing to agree with
    assert runner.last_plan is None and runner._last_normalised_plan is None


def test_one_sample_is_the_plain_runner(tiny_run, kit) -> None:
    ep = kit.synthetic_episode(0)
    plain = load_runner(tiny_run, execute_steps=4)
    one = load_runner(tiny_run, execute_steps=4, samples=1)
    a = np.array([plain.act(kit.observation(ep, t)) for t in range(6)])
    b = np.array([one.act(kit.observation(ep, t)) for t in range(6)])
    np.testing.assert_array_equal(a, b)


def test_samples_are_checked_and_named(tiny_run, tmp_path) -> None:
    for bad in (0, 2.5, True):
        with pytest.raises(InvalidParameterError, match="samples"):
            load_runner(tiny_run, samples=bad)
    with pytest.raises(InvalidParameterError, match="samples"):
        evaluate(tiny_run, "test", "hard", 1, 0, 1, tmp_path / "e.jsonl", samples=0)
    assert default_out(tmp_path, "test", "hard", 1.0, 0, samples=8).name.endswith("_samples8.jsonl")
    assert "samples" not in default_out(tmp_path, "test", "hard", 1.0, 0).name


@pytest.mark.parametrize("frame", ["world", "object"])
def test_several_samples_encode_once_and_match_repeated_inputs(frame) -> None:
    cfg = make_policy_config("keygen", frame=frame, num_keypoints=4, num_objects=1, **TINY_POLICY)
    torch.manual_seed(0)
    model = DiffusionPolicy(cfg).eval()
    rng = np.random.default_rng(0)
    model.normalizer.fit(rng.uniform(-1, 1, (50, 10)), rng.uniform(-1, 1, (50, 10)))
    g = torch.Generator().manual_seed(0)
    obs = {
        "cloud": torch.rand(2, cfg.cloud_frames, cfg.num_points, 3, generator=g) * 0.3 + 0.4,
        "proprio": torch.rand(2, cfg.obs_horizon, 10, generator=g),
        "keypoints": torch.rand(2, cfg.obs_horizon, cfg.num_keypoint_tokens, 3, generator=g),
    }
    encoded = []
    original = model.encode
    model.encode = lambda inputs: encoded.append(inputs["cloud"].shape[0]) or original(inputs)
    many = model.predict(obs, generator=torch.Generator().manual_seed(1), num_samples=3)
    assert many.shape == (6, cfg.horizon, 10) and encoded == [2]
    repeated = {k: v.repeat_interleave(3, dim=0) for k, v in obs.items()}
    same = model.predict(repeated, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(many, same, atol=1e-4, rtol=1e-4)
    with pytest.raises(InvalidParameterError, match="num_samples"):
        model.predict(obs, num_samples=0)
