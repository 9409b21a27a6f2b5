"""Expert demonstrations on disk: the zarr episode store and padded training windows over it."""

from keygen.data.store import (
    ACTION_KEY,
    ANCHOR_PREFIX,
    OBS_KEYS,
    EpisodeDataError,
    EpisodeStore,
    EpisodeStoreError,
    EpisodeWriter,
    StoreCorruptedError,
    anchor_key,
)
from keygen.data.windows import (
    ACTION_PAD_KEY,
    EPISODE_KEY,
    OBS_PAD_KEY,
    STEP_KEY,
    WindowSampler,
    train_val_split,
)

__all__ = [
    "ACTION_KEY",
    "ACTION_PAD_KEY",
    "ANCHOR_PREFIX",
    "EPISODE_KEY",
    "OBS_KEYS",
    "OBS_PAD_KEY",
    "STEP_KEY",
    "EpisodeDataError",
    "EpisodeStore",
    "EpisodeStoreError",
    "EpisodeWriter",
    "StoreCorruptedError",
    "WindowSampler",
    "anchor_key",
    "train_val_split",
]
