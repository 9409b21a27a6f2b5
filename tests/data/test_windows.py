"""Padded windows over the episode store and the split by episode."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from keygen.data import (
    ACTION_KEY,
    ACTION_PAD_KEY,
    EPISODE_KEY,
    OBS_PAD_KEY,
    STEP_KEY,
    EpisodeStore,
    WindowSampler,
    train_val_split,
)
from keygen.errors import KeyGenError

LENGTHS = [5, 1, 9, 3]


def make_store(path: Path) -> EpisodeStore:
    """Episodes whose values encode (episode, step), so every window can be checked by arithmetic."""
    store = EpisodeStore(path, mode="w")
    for e, length in enumerate(LENGTHS):
        t = np.arange(length, dtype=np.float32)
        proprio = np.zeros((length, 10), np.float32)
        proprio[:, 0], proprio[:, 1] = e, t
        action = np.zeros((length, 10), np.float32)
        action[:, 0], action[:, 1] = e, 100 + t
        cloud = np.zeros((length, 8, 3), np.float32) + t[:, None, None]
        store.append_episode(
            {"proprio": proprio, ACTION_KEY: action, "object_cloud": cloud, "anchors/spout": proprio[:, :3]},
            {"task": "pour", "seed": e, "success": True},
        )
    return store


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> EpisodeStore:
    return make_store(tmp_path_factory.mktemp("windows") / "s.zarr")


def expected_window(episode: int, step: int, to: int, ta: int) -> dict[str, np.ndarray]:
    last = LENGTHS[episode] - 1
    wanted_obs = np.arange(step - to + 1, step + 1)
    wanted_act = np.arange(step, step + ta)
    return {
        "obs_steps": np.clip(wanted_obs, 0, last),
        "act_steps": np.clip(wanted_act, 0, last),
        OBS_PAD_KEY: wanted_obs < 0,
        ACTION_PAD_KEY: wanted_act > last,
    }


@pytest.mark.parametrize("in_memory", [False, True])
def test_every_window_has_the_right_steps_and_padding(store: EpisodeStore, in_memory: bool) -> None:
    to, ta = 3, 4
    sampler = WindowSampler(store, to, ta, keys=["proprio", "object_cloud"], in_memory=in_memory)
    assert len(sampler) == sum(LENGTHS)
    seen = set()
    for i in range(len(sampler)):
        item = sampler[i]
        e, t = int(item[EPISODE_KEY]), int(item[STEP_KEY])
        assert sampler.locate(i) == (e, t)
        seen.add((e, t))
        want = expected_window(e, t, to, ta)
        assert item["proprio"].shape == (to, 10) and item[ACTION_KEY].shape == (ta, 10)
        assert item["object_cloud"].shape == (to, 8, 3)
        np.testing.assert_array_equal(item["proprio"][:, 0], e)  # never crosses an episode boundary
        np.testing.assert_array_equal(item[ACTION_KEY][:, 0], e)
        np.testing.assert_array_equal(item["proprio"][:, 1], want["obs_steps"])
        np.testing.assert_array_equal(item["object_cloud"][:, 0, 0], want["obs_steps"])
        np.testing.assert_array_equal(item[ACTION_KEY][:, 1], 100 + want["act_steps"])
        np.testing.assert_array_equal(item[OBS_PAD_KEY], want[OBS_PAD_KEY])
        np.testing.assert_array_equal(item[ACTION_PAD_KEY], want[ACTION_PAD_KEY])
    assert seen == {(e, t) for e, n in enumerate(LENGTHS) for t in range(n)}


def test_start_middle_and_end_explicitly(store: EpisodeStore) -> None:
    sampler = WindowSampler(store, obs_horizon=2, action_horizon=16, keys=["proprio"], episodes=[2])
    start, middle, end = sampler[0], sampler[4], sampler[8]
    # Start: the missing previous observation repeats step 0.
    np.testing.assert_array_equal(start["proprio"][:, 1], [0, 0])
    np.testing.assert_array_equal(start[OBS_PAD_KEY], [True, False])
    np.testing.assert_array_equal(start[ACTION_KEY][:, 1], 100 + np.minimum(np.arange(16), 8))
    np.testing.assert_array_equal(start[ACTION_PAD_KEY], np.arange(16) > 8)
    # Middle: no observation padding, actions padded past the end (16 > 9 steps).
    np.testing.assert_array_equal(middle["proprio"][:, 1], [3, 4])
    assert not middle[OBS_PAD_KEY].any()
    np.testing.assert_array_equal(middle[ACTION_PAD_KEY], np.arange(4, 20) > 8)
    # End: every action after the first repeats the last one.
    np.testing.assert_array_equal(end[ACTION_KEY][:, 1], np.full(16, 108))
    np.testing.assert_array_equal(end[ACTION_PAD_KEY], [False] + [True] * 15)
    # A one-step episode pads everything but the current entries.
    single = WindowSampler(store, 3, 2, keys=["anchors/spout"], episodes=[1])[0]
    np.testing.assert_array_equal(single[OBS_PAD_KEY], [True, True, False])
    np.testing.assert_array_equal(single[ACTION_PAD_KEY], [False, True])
    np.testing.assert_array_equal(single["anchors/spout"][:, 0], [1, 1, 1])


def test_batch_and_episode_subset(store: EpisodeStore) -> None:
    sampler = WindowSampler(store, 2, 4, keys=["proprio"], episodes=np.array([3, 0]))
    assert len(sampler) == LENGTHS[3] + LENGTHS[0]
    assert sampler.locate(0) == (3, 0) and sampler.locate(-1) == (0, LENGTHS[0] - 1)
    batch = sampler.batch([0, 1, len(sampler) - 1])
    assert batch["proprio"].shape == (3, 2, 10) and batch[ACTION_KEY].shape == (3, 4, 10)
    assert batch[OBS_PAD_KEY].dtype == bool and batch[OBS_PAD_KEY].shape == (3, 2)
    np.testing.assert_array_equal(batch[EPISODE_KEY], [3, 3, 0])
    with pytest.raises(IndexError):
        sampler[len(sampler)]


def test_sampler_rejects_bad_arguments(store: EpisodeStore) -> None:
    for kwargs in (
        {"obs_horizon": 0, "action_horizon": 4, "keys": ["proprio"]},
        {"obs_horizon": 2, "action_horizon": 4, "keys": [ACTION_KEY]},
        {"obs_horizon": 2, "action_horizon": 4, "keys": ["rgb"]},
        {"obs_horizon": 2, "action_horizon": 4, "keys": ["proprio"], "episodes": [4]},
        {"obs_horizon": 2, "action_horizon": 4, "keys": ["proprio"], "episodes": [0, 0]},
    ):
        with pytest.raises(KeyGenError):
            WindowSampler(store, **kwargs)


def test_train_val_split_by_episode_is_disjoint_and_deterministic(store: EpisodeStore) -> None:
    train, val = train_val_split(store, val_fraction=0.25, seed=0)
    assert len(val) == 1 and len(train) == 3
    assert set(train).isdisjoint(val) and sorted([*train, *val]) == list(range(store.num_episodes))
    again = train_val_split(store, 0.25, seed=0)
    np.testing.assert_array_equal(again[0], train)
    np.testing.assert_array_equal(again[1], val)

    splits = {tuple(train_val_split(100, 0.2, seed)[1]) for seed in range(5)}
    assert len(splits) > 1  # the seed matters
    tr, va = train_val_split(100, 0.2, seed=3)
    assert len(va) == 20 and len(tr) == 80 and np.all(np.diff(tr) > 0)
    assert len(train_val_split(2, 0.01, 0)[1]) == 1  # both sides non-empty once there are two episodes
    assert len(train_val_split(5, 0.0, 0)[1]) == 0
    with pytest.raises(KeyGenError):
        train_val_split(5, 1.0, 0)

    # Windows of the two sides never share an episode.
    tr_sampler = WindowSampler(store, 2, 4, ["proprio"], episodes=train)
    va_sampler = WindowSampler(store, 2, 4, ["proprio"], episodes=val)
    tr_eps = {tr_sampler.locate(i)[0] for i in range(len(tr_sampler))}
    va_eps = {va_sampler.locate(i)[0] for i in range(len(va_sampler))}
    assert tr_eps.isdisjoint(va_eps)
