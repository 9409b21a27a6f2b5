"""Padded training windows over an episode store, and the train / validation split by episode.

Every step ``t`` of every chosen episode is one sample: the last ``obs_horizon`` observations
(steps ``t - obs_horizon + 1 .. t``) and the next ``action_horizon`` actions (steps
``t .. t + action_horizon - 1``). Near the episode's start the missing observations repeat the
first step; near its end the missing actions repeat the last action (the expert holds its final
target). Masks say which entries are such padding, so a loss can ignore them. Windows never cross
episode boundaries. Numpy only; a torch ``Dataset`` can wrap :class:`WindowSampler` as it is.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from keygen.data.store import ACTION_KEY, EpisodeStore, EpisodeStoreError
from keygen.errors import InvalidParameterError

# Batch keys added next to the observation keys and ACTION_KEY.
OBS_PAD_KEY = "obs_is_pad"
ACTION_PAD_KEY = "action_is_pad"
EPISODE_KEY = "episode"
STEP_KEY = "step"


def train_val_split(
    store: EpisodeStore | int, val_fraction: float, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Split episode ids (of a store, or ``range(n)``) into sorted train and validation ids.

    Deterministic in ``seed``. Whole episodes go to one side so validation windows never share an
    episode with training. With ``val_fraction > 0`` and at least two episodes, both sides get at
    least one episode.
    """
    n = store if isinstance(store, int) else store.num_episodes
    if not 0.0 <= val_fraction < 1.0:
        raise InvalidParameterError(f"val_fraction must be in [0, 1), got {val_fraction}")
    if n < 0:
        raise InvalidParameterError(f"the number of episodes must be >= 0, got {n}")
    n_val = int(round(val_fraction * n))
    if val_fraction > 0 and n >= 2:
        n_val = min(max(n_val, 1), n - 1)
    order = np.random.default_rng(seed).permutation(n)
    return np.sort(order[n_val:]).astype(np.int64), np.sort(order[:n_val]).astype(np.int64)


class WindowSampler:
    """Index every (episode, step) of the chosen episodes; ``sampler[i]`` is one padded window.

    ``keys`` are the observation keys to load (any stored key but the action, anchors included).
    ``episodes`` defaults to every episode of the store. ``in_memory`` reads the needed keys of the
    whole store once up front, which makes ``__getitem__`` a few numpy slices: use it for
    low-dimensional keys (proprio, clouds), not for a large image store.
    """

    def __init__(
        self,
        store: EpisodeStore,
        obs_horizon: int,
        action_horizon: int,
        keys: Sequence[str],
        episodes: Sequence[int] | np.ndarray | None = None,
        in_memory: bool = False,
    ):
        if obs_horizon < 1 or action_horizon < 1:
            raise InvalidParameterError(
                f"obs_horizon and action_horizon must be >= 1, got {obs_horizon} and {action_horizon}"
            )
        keys = list(keys)
        if ACTION_KEY in keys:
            raise InvalidParameterError(
                f"{ACTION_KEY!r} is always returned as the action window; leave it out of keys"
            )
        for key in keys:
            if key not in store.keys():
                raise EpisodeStoreError(f"the store has no key {key!r}; it has {store.keys()}")
        if len(set(keys)) != len(keys):
            raise InvalidParameterError(f"keys must be distinct, got {keys}")
        self.store = store
        self.obs_horizon = int(obs_horizon)
        self.action_horizon = int(action_horizon)
        self.keys = keys
        self.episodes = self._checked_episodes(store, episodes)
        slices = [store.episode_slice(int(e)) for e in self.episodes]
        self._starts = np.array([s.start for s in slices], dtype=np.int64)
        self._stops = np.array([s.stop for s in slices], dtype=np.int64)
        # Sample i belongs to the chosen episode j with _offsets[j] <= i < _offsets[j + 1].
        self._offsets = np.concatenate([[0], np.cumsum(self._stops - self._starts)]).astype(np.int64)
        self._cache: dict[str, np.ndarray] | None = None
        if in_memory:
            self._cache = {key: store.read(key, 0, store.num_steps) for key in [*keys, ACTION_KEY]}

    @staticmethod
    def _checked_episodes(store: EpisodeStore, episodes: Sequence[int] | np.ndarray | None) -> np.ndarray:
        if episodes is None:
            return np.arange(store.num_episodes, dtype=np.int64)
        ids = np.asarray(episodes, dtype=np.int64).reshape(-1)
        if ids.size and (ids.min() < 0 or ids.max() >= store.num_episodes):
            raise InvalidParameterError(
                f"episode ids must be in [0, {store.num_episodes}), got min {ids.min()} and max {ids.max()}"
            )
        if len(np.unique(ids)) != len(ids):
            raise InvalidParameterError("episode ids must be distinct (duplicates would double their weight)")
        return ids

    def __len__(self) -> int:
        return int(self._offsets[-1])

    def locate(self, i: int) -> tuple[int, int]:
        """(episode id in the store, step within that episode) of sample ``i``."""
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"sample index must be in [{-n}, {n}), got {i}")
        i %= n
        j = int(np.searchsorted(self._offsets, i, side="right")) - 1
        return int(self.episodes[j]), int(i - self._offsets[j])

    def _read(self, key: str, start: int, stop: int) -> np.ndarray:
        if self._cache is not None:
            return self._cache[key][start:stop]
        return self.store.read(key, start, stop)

    def __getitem__(self, i: int) -> dict[str, np.ndarray]:
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"sample index must be in [{-n}, {n}), got {i}")
        i %= n
        j = int(np.searchsorted(self._offsets, i, side="right")) - 1
        first, last = int(self._starts[j]), int(self._stops[j]) - 1  # global steps of the episode
        now = first + int(i - self._offsets[j])

        wanted_obs = np.arange(now - self.obs_horizon + 1, now + 1)
        obs_steps = np.clip(wanted_obs, first, last)
        wanted_act = np.arange(now, now + self.action_horizon)
        act_steps = np.clip(wanted_act, first, last)

        # One contiguous read per key, then repeat the edge steps by fancy indexing.
        lo, hi = int(obs_steps[0]), int(obs_steps[-1]) + 1
        sample = {key: self._read(key, lo, hi)[obs_steps - lo] for key in self.keys}
        lo, hi = int(act_steps[0]), int(act_steps[-1]) + 1
        sample[ACTION_KEY] = self._read(ACTION_KEY, lo, hi)[act_steps - lo]
        sample[OBS_PAD_KEY] = wanted_obs < first
        sample[ACTION_PAD_KEY] = wanted_act > last
        sample[EPISODE_KEY] = np.int64(self.episodes[j])
        sample[STEP_KEY] = np.int64(now - first)
        return sample

    def batch(self, indices: Sequence[int] | np.ndarray) -> dict[str, np.ndarray]:
        """Samples ``indices`` stacked along a new first axis."""
        items = [self[int(i)] for i in indices]
        if not items:
            raise InvalidParameterError("a batch needs at least one index")
        return {key: np.stack([item[key] for item in items]) for key in items[0]}
