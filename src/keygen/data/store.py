"""The on-disk episode store for expert demonstrations: a zarr directory laid out like a replay buffer.

Layout of a store directory (zarr v3, one writer at a time)::

    commit.json                   the commit record: episode and step counts, keys, shapes, dtypes
    data/<key>                    (S, ...) every episode's steps concatenated along axis 0
    data/anchors/<name>           (S, 3) or (S, 1) privileged anchors, world frame
    meta/episode_ends             (E,) int64, cumulative: episode i is steps [ends[i-1], ends[i])
    meta/episode_meta             (E,) str, one JSON object per episode (task, objects, seed, ...)
    failed/                       the same layout again, for episodes whose ``success`` is False

Keys are the names of :data:`OBS_KEYS`, :data:`ACTION_KEY` and ``anchors/<name>``
(:data:`ANCHOR_PREFIX`). Arrays are chunked along time only, a few steps per chunk for images
and up to :data:`MAX_CHUNK_STEPS` for low-dimensional keys (about :data:`CHUNK_TARGET_BYTES` per
chunk), so a training window touches one or two chunks per key; chunks are compressed with
blosc-zstd.

Atomic append. ``append_episode`` validates everything first (bad input writes nothing), then
grows and fills the arrays past the committed end, then the two ``meta`` arrays, and only then
commits by replacing ``commit.json`` (write to a temporary file, fsync, ``os.replace``). Readers
trust ``commit.json`` alone: anything past its counts is an append that never finished, and a
writable open cuts it away before appending again. A crash or SIGKILL at any moment therefore
leaves the episodes committed before it, whole. This relies on zarr replacing each chunk file
atomically (zarr 3.1's ``LocalStore`` writes a temporary file and renames it), because the last
chunk of a key is shared by the committed tail and the new episode.

Failed episodes (``meta["success"]`` false) are appended to the ``failed/`` sub-store, a complete
store of its own reached through :attr:`EpisodeStore.failed`. They stay on disk for analysis of
failure reasons but are never counted, indexed or returned by the main store, so training
readers (``keygen.data.windows``) only ever see successes.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np
import zarr
from zarr.codecs import BloscCodec

from keygen.atomic import atomic_write_text
from keygen.errors import InvalidParameterError, KeyGenError

FORMAT_VERSION = 1

# Observation keys, as returned per step by keygen.sim.env.KeyGenEnv.
RGB_KEY = "rgb"
DEPTH_KEY = "depth"
SEGMENTATION_KEY = "segmentation"
INTRINSICS_KEY = "intrinsics"
EXTRINSICS_KEY = "extrinsics"
PROPRIO_KEY = "proprio"
OBJECT_CLOUD_KEY = "object_cloud"
OBJECT_CLOUD_IDS_KEY = "object_cloud_ids"
SCENE_CLOUD_KEY = "scene_cloud"
OBS_KEYS = (
    RGB_KEY,
    DEPTH_KEY,
    SEGMENTATION_KEY,
    INTRINSICS_KEY,
    EXTRINSICS_KEY,
    PROPRIO_KEY,
    OBJECT_CLOUD_KEY,
    OBJECT_CLOUD_IDS_KEY,
    SCENE_CLOUD_KEY,
)
ACTION_KEY = "action"
ANCHOR_PREFIX = "anchors/"
ACTION_DIM = 10

# Stored dtype of each key; anchors are float32. Floats of any width are narrowed to float32.
KEY_DTYPES: dict[str, np.dtype] = {
    RGB_KEY: np.dtype(np.uint8),
    DEPTH_KEY: np.dtype(np.float32),
    SEGMENTATION_KEY: np.dtype(np.int32),
    INTRINSICS_KEY: np.dtype(np.float32),
    EXTRINSICS_KEY: np.dtype(np.float32),
    PROPRIO_KEY: np.dtype(np.float32),
    OBJECT_CLOUD_KEY: np.dtype(np.float32),
    OBJECT_CLOUD_IDS_KEY: np.dtype(np.int32),
    SCENE_CLOUD_KEY: np.dtype(np.float32),
    ACTION_KEY: np.dtype(np.float32),
}
ANCHOR_DTYPE = np.dtype(np.float32)

# Per-step shape of each key; None is a size fixed by the first episode (views V, H, W, points N).
KEY_STEP_SHAPES: dict[str, tuple[int | None, ...]] = {
    RGB_KEY: (None, None, None, 3),
    DEPTH_KEY: (None, None, None),
    SEGMENTATION_KEY: (None, None, None),
    INTRINSICS_KEY: (None, 3, 3),
    EXTRINSICS_KEY: (None, 4, 4),
    PROPRIO_KEY: (ACTION_DIM,),
    OBJECT_CLOUD_KEY: (None, 3),
    OBJECT_CLOUD_IDS_KEY: (None,),
    SCENE_CLOUD_KEY: (None, 3),
    ACTION_KEY: (ACTION_DIM,),
}
VIEW_KEYS = (RGB_KEY, DEPTH_KEY, SEGMENTATION_KEY, INTRINSICS_KEY, EXTRINSICS_KEY)
ANCHOR_SIZES = (1, 3)

COMMIT_FILE = "commit.json"
DATA_GROUP = "data"
EPISODE_ENDS = "meta/episode_ends"
EPISODE_META = "meta/episode_meta"
FAILED_GROUP = "failed"
SUCCESS_META_KEY = "success"

CHUNK_TARGET_BYTES = 1 << 20
MAX_CHUNK_STEPS = 1024
META_CHUNK = 4096
_FIRST_CAPACITY = 256  # steps an EpisodeWriter reserves per key; grows by doubling
# Level 1, not 3: half the compression time (0.29 s less per recorded 133-step pour episode,
# a fifth of the recording overhead) for 13% more bytes (15.4 vs 13.6 MB per episode).
COMPRESSOR = BloscCodec(cname="zstd", clevel=1, shuffle="shuffle")

_ANCHOR_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")

StoreMode = Literal["r", "a", "w"]


class EpisodeStoreError(KeyGenError):
    """The episode store cannot do what was asked (missing store, read-only, bad index)."""


class EpisodeDataError(EpisodeStoreError, ValueError):
    """An episode handed to the store is malformed; nothing was written."""


class StoreCorruptedError(EpisodeStoreError):
    """The committed part of a store is inconsistent (found by :meth:`EpisodeStore.validate`)."""


def is_anchor_key(key: str) -> bool:
    return key.startswith(ANCHOR_PREFIX)


def anchor_key(name: str) -> str:
    if not _ANCHOR_NAME.match(name):
        raise EpisodeDataError(
            f"anchor names must match {_ANCHOR_NAME.pattern}, got {name!r}; rename the anchor"
        )
    return ANCHOR_PREFIX + name


def stored_dtype(key: str) -> np.dtype:
    return ANCHOR_DTYPE if is_anchor_key(key) else KEY_DTYPES[key]


def chunk_steps(step_shape: tuple[int, ...], dtype: np.dtype) -> int:
    """Steps per chunk: about CHUNK_TARGET_BYTES uncompressed, a power of two, at most MAX_CHUNK_STEPS."""
    step_bytes = max(1, int(np.prod(step_shape, dtype=np.int64)) * dtype.itemsize)
    steps = max(1, CHUNK_TARGET_BYTES // step_bytes)
    return int(min(MAX_CHUNK_STEPS, 1 << (steps.bit_length() - 1)))


def _json_default(value: Any) -> Any:
    # Metadata often carries numpy scalars and small arrays (seeds, scales, anchor positions).
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def encode_meta(meta: Mapping[str, Any]) -> str:
    if not isinstance(meta, Mapping):
        raise EpisodeDataError(f"episode metadata must be a dict, got {type(meta).__name__}")
    try:
        return json.dumps(dict(meta), default=_json_default, allow_nan=False, sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise EpisodeDataError(
            f"episode metadata must be JSON serialisable (numbers, strings, lists, dicts, numpy "
            f"scalars or arrays; no NaN): {exc}"
        ) from exc


def _dir_bytes(path: Path, exclude: Path | None = None) -> int:
    total = 0
    for root, dirs, files in os.walk(path):
        if exclude is not None and Path(root) == exclude.parent:
            dirs[:] = [d for d in dirs if Path(root) / d != exclude]
        total += sum((Path(root) / f).stat().st_size for f in files)
    return total


def _empty_commit() -> dict[str, Any]:
    return {"format_version": FORMAT_VERSION, "episodes": 0, "steps": 0, "keys": {}}


class EpisodeStore:
    """Episodes of expert demonstrations in a zarr directory; see the module docstring for the layout.

    ``mode``: ``"r"`` read only (the store must exist), ``"a"`` read and append (created if
    missing), ``"w"`` start afresh (an existing store at ``path`` is deleted). One writer per store;
    readers may open it while a writer appends and see the episodes committed when they opened
    (call :meth:`refresh` to see newer ones).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        mode: StoreMode = "a",
        *,
        max_episodes: int | None = None,
        _is_failed: bool = False,
    ):
        if mode not in ("r", "a", "w"):
            raise InvalidParameterError(f"mode must be 'r', 'a' or 'w', got {mode!r}")
        if max_episodes is not None:
            if mode != "r":
                raise InvalidParameterError(
                    "max_episodes views a store's first episodes; open it with mode='r'"
                )
            if isinstance(max_episodes, bool) or not isinstance(max_episodes, int) or max_episodes < 1:
                raise InvalidParameterError(f"max_episodes must be a positive int, got {max_episodes!r}")
        self.path = Path(path)
        self.mode = mode
        self._max_episodes = max_episodes
        self._is_failed = _is_failed
        self._arrays: dict[str, zarr.Array] = {}
        if mode == "w":
            self._remove_existing()
        if mode == "r":
            if not (self.path / COMMIT_FILE).is_file():
                raise EpisodeStoreError(
                    f"no episode store at {self.path} (expected {COMMIT_FILE} there); check the path, "
                    f"or open with mode='a' to create one"
                )
            self._root = zarr.open_group(self.path, mode="r")
        else:
            self._root = zarr.open_group(self.path, mode="a")
            if not (self.path / COMMIT_FILE).is_file():
                # A new store, or one whose creation was interrupted before its first commit.
                atomic_write_text(self.path / COMMIT_FILE, json.dumps(_empty_commit()), durable=True)
        self._commit = self._read_commit()
        if self.writable:
            self._discard_uncommitted()
        self._ends = self._read_ends()
        self._keep_first_episodes()
        self._failed: EpisodeStore | None = None
        if not _is_failed and (self.writable or (self.path / FAILED_GROUP / COMMIT_FILE).is_file()):
            self._failed = EpisodeStore(
                self.path / FAILED_GROUP, "a" if self.writable else "r", _is_failed=True
            )

    # ----------------------------------------------------------------------------------------- opening

    def _remove_existing(self) -> None:
        if not self.path.exists():
            return
        looks_like_store = (self.path / COMMIT_FILE).exists() or (self.path / "zarr.json").exists()
        if not looks_like_store and any(self.path.iterdir()):
            raise EpisodeStoreError(
                f"mode='w' would delete {self.path}, which is not an episode store and not empty; "
                f"pick another path"
            )
        shutil.rmtree(self.path)

    def _read_commit(self) -> dict[str, Any]:
        path = self.path / COMMIT_FILE
        try:
            commit = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise StoreCorruptedError(f"cannot read the commit record {path}: {exc}") from exc
        if commit.get("format_version") != FORMAT_VERSION:
            raise StoreCorruptedError(
                f"{path} has format_version {commit.get('format_version')!r}, this keygen reads "
                f"{FORMAT_VERSION}; convert the store or use a matching keygen version"
            )
        return commit

    def _read_ends(self) -> np.ndarray:
        n = self.num_episodes
        if n == 0:
            return np.zeros(0, dtype=np.int64)
        return np.asarray(self._root[EPISODE_ENDS][:n], dtype=np.int64)

    def _keep_first_episodes(self) -> None:
        """With ``max_episodes``, show only the first committed episodes (for data-efficiency studies:
        one recording, trained on its first 25, 50, 100 ... episodes). Asking for more than the store
        holds is an error rather than a silent smaller dataset."""
        n = self._max_episodes
        if n is None:
            return
        if n > self.num_episodes:
            raise EpisodeStoreError(
                f"{self.path} holds {self.num_episodes} episodes, fewer than the {n} asked for; "
                f"record more (a rerun of `keygen demos` with a larger --episodes adds them) or ask for fewer"
            )
        self._ends = self._ends[:n]
        self._commit = {**self._commit, "episodes": n, "steps": int(self._ends[-1])}

    def _discard_uncommitted(self) -> None:
        """Cut every array back to the committed counts: the leftovers of an append that never finished."""
        steps, episodes, keys = self.num_steps, self.num_episodes, self._commit["keys"]
        if DATA_GROUP in self._root:
            for name, node in list(self._root[DATA_GROUP].members(max_depth=None)):
                if not isinstance(node, zarr.Array):
                    continue
                if name not in keys:
                    del self._root[DATA_GROUP][name]
                elif node.shape[0] != steps:
                    node.resize((steps, *node.shape[1:]))
        for name, dtype in ((EPISODE_ENDS, np.int64), (EPISODE_META, str)):
            if name not in self._root:
                self._root.create_array(name, shape=(0,), chunks=(META_CHUNK,), dtype=dtype)
            node = self._root[name]
            if node.shape[0] != episodes:
                node.resize((episodes,))

    def refresh(self) -> None:
        """Re-read the commit record: a reader opened earlier then sees episodes committed since."""
        self._commit = self._read_commit()
        self._ends = self._read_ends()
        self._keep_first_episodes()
        self._arrays.clear()
        if self._failed is not None:
            self._failed.refresh()
        elif not self._is_failed and (self.path / FAILED_GROUP / COMMIT_FILE).is_file():
            self._failed = EpisodeStore(self.path / FAILED_GROUP, "r", _is_failed=True)

    # ---------------------------------------------------------------------------------------- reading

    @property
    def writable(self) -> bool:
        return self.mode != "r"

    @property
    def num_episodes(self) -> int:
        return int(self._commit["episodes"])

    @property
    def num_steps(self) -> int:
        return int(self._commit["steps"])

    @property
    def episode_ends(self) -> np.ndarray:
        """Cumulative step counts of the committed episodes (a copy)."""
        return self._ends.copy()

    @property
    def failed(self) -> EpisodeStore | None:
        """The sub-store of failed episodes (None for a read-only store that never had one)."""
        return self._failed

    def __len__(self) -> int:
        return self.num_episodes

    def keys(self) -> list[str]:
        return sorted(self._commit["keys"])

    def step_shape(self, key: str) -> tuple[int, ...]:
        self._check_key(key)
        return tuple(self._commit["keys"][key]["shape"])

    def dtype(self, key: str) -> np.dtype:
        self._check_key(key)
        return np.dtype(self._commit["keys"][key]["dtype"])

    def _check_key(self, key: str) -> None:
        if key not in self._commit["keys"]:
            raise EpisodeStoreError(f"the store has no key {key!r}; it has {self.keys()}")

    def _array(self, key: str) -> zarr.Array:
        if key not in self._arrays:
            self._arrays[key] = self._root[f"{DATA_GROUP}/{key}"]
        return self._arrays[key]

    def _episode_index(self, i: int) -> int:
        n = self.num_episodes
        if not -n <= i < n:
            raise EpisodeStoreError(f"episode index must be in [{-n}, {n}), got {i}")
        return i % n

    def episode_slice(self, i: int) -> slice:
        """The steps of episode ``i`` in the concatenated arrays."""
        i = self._episode_index(i)
        start = int(self._ends[i - 1]) if i > 0 else 0
        return slice(start, int(self._ends[i]))

    def episode_length(self, i: int) -> int:
        s = self.episode_slice(i)
        return s.stop - s.start

    def read(self, key: str, start: int, stop: int) -> np.ndarray:
        """Steps [start, stop) of ``key``, within the committed steps."""
        self._check_key(key)
        if not 0 <= start <= stop <= self.num_steps:
            raise EpisodeStoreError(
                f"step range must lie in [0, {self.num_steps}] with start <= stop, got [{start}, {stop})"
            )
        return self._array(key)[start:stop]

    def episode(self, i: int, keys: Iterable[str] | None = None) -> dict[str, np.ndarray]:
        """Every key (or the given ones) of episode ``i``, each (T, ...)."""
        s = self.episode_slice(i)
        return {key: self.read(key, s.start, s.stop) for key in (self.keys() if keys is None else keys)}

    def episode_meta(self, i: int) -> dict[str, Any]:
        i = self._episode_index(i)
        return json.loads(str(self._root[EPISODE_META][i]))

    def all_meta(self) -> list[dict[str, Any]]:
        n = self.num_episodes
        if n == 0:
            return []
        return [json.loads(str(s)) for s in self._root[EPISODE_META][:n]]

    def info(self) -> dict[str, Any]:
        """Counts, keys with per-step shapes and dtypes, bytes on disk, successes and failures."""
        lengths = np.diff(self._ends, prepend=0)
        failed = self._failed
        info: dict[str, Any] = {
            "path": str(self.path),
            "episodes": self.num_episodes,
            "steps": self.num_steps,
            "episode_length": {
                "min": int(lengths.min()) if len(lengths) else 0,
                "mean": float(lengths.mean()) if len(lengths) else 0.0,
                "max": int(lengths.max()) if len(lengths) else 0,
            },
            "keys": {
                key: {
                    "shape": list(spec["shape"]),
                    "dtype": spec["dtype"],
                    "chunk_steps": chunk_steps(tuple(spec["shape"]), np.dtype(spec["dtype"])),
                }
                for key, spec in sorted(self._commit["keys"].items())
            },
            "bytes_on_disk": _dir_bytes(self.path, exclude=self.path / FAILED_GROUP),
        }
        if not self._is_failed:
            n_failed = failed.num_episodes if failed is not None else 0
            total = self.num_episodes + n_failed
            reasons: dict[str, int] = {}
            for meta in failed.all_meta() if failed is not None else []:
                reason = str(meta.get("failure") or meta.get("failure_reason") or "unknown")
                reasons[reason] = reasons.get(reason, 0) + 1
            info["success"] = {
                "succeeded": self.num_episodes,
                "failed": n_failed,
                "success_rate": self.num_episodes / total if total else float("nan"),
                "failure_reasons": reasons,
            }
            info["failed_bytes_on_disk"] = _dir_bytes(failed.path) if failed is not None else 0
        return info

    def validate(self) -> None:
        """Check the committed part for consistency; raise StoreCorruptedError listing every problem."""
        problems: list[str] = []
        n, steps = self.num_episodes, self.num_steps
        ends = self._ends
        if len(ends) != n:
            problems.append(f"{EPISODE_ENDS} holds {len(ends)} committed entries, expected {n}")
        if n and (np.any(np.diff(ends, prepend=0) <= 0) or ends[-1] != steps):
            problems.append(f"{EPISODE_ENDS} must increase strictly and end at {steps}, got {ends.tolist()}")
        if n == 0 and steps != 0:
            problems.append(f"no episodes but {steps} committed steps")
        if self._root[EPISODE_META].shape[0] < n:
            problems.append(f"{EPISODE_META} holds {self._root[EPISODE_META].shape[0]} entries, expected {n}")
        else:
            for i in range(n):
                try:
                    if not isinstance(self.episode_meta(i), dict):
                        problems.append(f"metadata of episode {i} is not a JSON object")
                except ValueError as exc:
                    problems.append(f"metadata of episode {i} is not valid JSON: {exc}")
        for key, spec in self._commit["keys"].items():
            path = f"{DATA_GROUP}/{key}"
            if path not in self._root:
                problems.append(f"committed key {key!r} has no array {path}")
                continue
            arr = self._root[path]
            if arr.shape[0] < steps or list(arr.shape[1:]) != list(spec["shape"]):
                problems.append(f"{path} has shape {arr.shape}, expected ({steps}, *{spec['shape']})")
            if str(arr.dtype) != spec["dtype"]:
                problems.append(f"{path} has dtype {arr.dtype}, expected {spec['dtype']}")
        if n and ACTION_KEY in self._commit["keys"]:
            if not np.all(np.isfinite(self.read(ACTION_KEY, 0, steps))):
                problems.append("actions contain NaN or inf")
        if n and ACTION_KEY not in self._commit["keys"]:
            problems.append(f"committed episodes lack the {ACTION_KEY!r} key")
        if problems:
            raise StoreCorruptedError(
                f"episode store {self.path} is inconsistent: " + "; ".join(problems) + ". "
                "Copy out the readable episodes into a fresh store."
            )
        if self._failed is not None:
            self._failed.validate()

    # ---------------------------------------------------------------------------------------- writing

    def writer(self) -> EpisodeWriter:
        return EpisodeWriter(self)

    def append_episode(self, steps: Mapping[str, np.ndarray], meta: Mapping[str, Any]) -> int:
        """Validate and append one episode atomically; return its index in the store it went to.

        ``steps`` maps every key to a (T, ...) array, the same T for all keys and the same key set
        as the episodes already stored. ``meta["success"]`` (a bool) is required: failed episodes go
        to :attr:`failed` and the returned index counts there.
        """
        if not self.writable:
            raise EpisodeStoreError(f"the store at {self.path} is open read-only; reopen with mode='a'")
        success = meta.get(SUCCESS_META_KEY) if isinstance(meta, Mapping) else None
        if not isinstance(success, (bool, np.bool_)):
            raise EpisodeDataError(
                f"episode metadata needs {SUCCESS_META_KEY!r}: a bool, got {success!r}; "
                f"pass the environment's info['success']"
            )
        if not success and not self._is_failed:
            assert self._failed is not None  # always opened for a writable main store
            return self._failed.append_episode(steps, meta)
        arrays, length = self._checked_steps(steps)
        meta_json = encode_meta(meta)
        return self._write_episode(arrays, length, meta_json)

    def _checked_steps(self, steps: Mapping[str, np.ndarray]) -> tuple[dict[str, np.ndarray], int]:
        """Every check that can fail, done before anything is written."""
        if not isinstance(steps, Mapping) or not steps:
            raise EpisodeDataError("steps must be a non-empty dict of key -> (T, ...) array")
        for key in steps:
            if key not in KEY_DTYPES and not (
                is_anchor_key(key) and _ANCHOR_NAME.match(key[len(ANCHOR_PREFIX) :])
            ):
                raise EpisodeDataError(
                    f"unknown key {key!r}; expected one of {list(KEY_DTYPES)} or '{ANCHOR_PREFIX}<name>'"
                )
        if ACTION_KEY not in steps:
            raise EpisodeDataError(f"the episode has no {ACTION_KEY!r} key; every episode needs its actions")
        stored = self._commit["keys"]
        if stored and set(steps) != set(stored):
            missing, extra = sorted(set(stored) - set(steps)), sorted(set(steps) - set(stored))
            raise EpisodeDataError(
                f"the episode's keys must match the store's: missing {missing}, unexpected {extra}; "
                f"record the same observations for every episode (or start a new store)"
            )
        arrays = {key: self._checked_array(key, value) for key, value in steps.items()}
        lengths = {key: a.shape[0] for key, a in arrays.items()}
        if len(set(lengths.values())) != 1:
            raise EpisodeDataError(f"every key must have the same number of steps T, got {lengths}")
        length = next(iter(lengths.values()))
        if length == 0:
            raise EpisodeDataError("an episode needs at least one step, got T=0")
        self._check_step_shapes(arrays)
        return arrays, length

    def _checked_array(self, key: str, value: Any) -> np.ndarray:
        arr = np.asarray(value)
        target = stored_dtype(key)
        if arr.ndim < 1:
            raise EpisodeDataError(f"{key!r} must be a (T, ...) array, got a scalar")
        if target.kind == "f":
            if arr.dtype.kind not in "fiu":
                raise EpisodeDataError(f"{key!r} must be numeric, got dtype {arr.dtype}")
            arr = arr.astype(target, copy=False)
            if not np.all(np.isfinite(arr)):
                bad = int(np.count_nonzero(~np.isfinite(arr)))
                raise EpisodeDataError(
                    f"{key!r} contains {bad} NaN or inf values (or values beyond float32); "
                    f"an unstable episode should be recorded as failed with finite data, or dropped"
                )
        else:
            if arr.dtype.kind not in "iub":
                raise EpisodeDataError(f"{key!r} must hold integers ({target}), got dtype {arr.dtype}")
            info = np.iinfo(target)
            if arr.size and (arr.min() < info.min or arr.max() > info.max):
                raise EpisodeDataError(
                    f"{key!r} values must fit {target} [{info.min}, {info.max}], got range "
                    f"[{arr.min()}, {arr.max()}]"
                )
            arr = arr.astype(target, copy=False)
        return np.ascontiguousarray(arr)

    def _check_step_shapes(self, arrays: Mapping[str, np.ndarray]) -> None:
        stored = self._commit["keys"]
        for key, arr in arrays.items():
            step = arr.shape[1:]
            if key in stored:
                if list(step) != list(stored[key]["shape"]):
                    raise EpisodeDataError(
                        f"{key!r} steps have shape {step}, but the store holds {tuple(stored[key]['shape'])} "
                        f"per step; keep image size, view count and cloud size fixed within a store"
                    )
                continue
            if is_anchor_key(key):
                if len(step) != 1 or step[0] not in ANCHOR_SIZES:
                    raise EpisodeDataError(f"anchor {key!r} must be (T, 3) or (T, 1), got {arr.shape}")
                continue
            expected = KEY_STEP_SHAPES[key]
            if len(step) != len(expected) or any(
                e is not None and e != s for e, s in zip(expected, step, strict=True)
            ):
                pattern = tuple("*" if e is None else e for e in expected)
                raise EpisodeDataError(f"{key!r} steps must have shape {pattern}, got {step}")
        views = {key: arrays[key].shape[1] for key in VIEW_KEYS if key in arrays}
        if len(set(views.values())) > 1:
            raise EpisodeDataError(f"the camera keys disagree on the number of views V: {views}")
        images = {
            key: arrays[key].shape[2:4] for key in (RGB_KEY, DEPTH_KEY, SEGMENTATION_KEY) if key in arrays
        }
        if len(set(images.values())) > 1:
            raise EpisodeDataError(f"rgb, depth and segmentation disagree on (H, W): {images}")
        if OBJECT_CLOUD_KEY in arrays and OBJECT_CLOUD_IDS_KEY in arrays:
            n_points, n_ids = arrays[OBJECT_CLOUD_KEY].shape[1], arrays[OBJECT_CLOUD_IDS_KEY].shape[1]
            if n_points != n_ids:
                raise EpisodeDataError(
                    f"object_cloud has {n_points} points per step but object_cloud_ids has {n_ids}"
                )

    def _create_array(self, key: str, arr: np.ndarray) -> zarr.Array:
        step_shape = arr.shape[1:]
        return self._root.create_array(
            f"{DATA_GROUP}/{key}",
            shape=(0, *step_shape),
            chunks=(chunk_steps(step_shape, arr.dtype), *step_shape),
            dtype=arr.dtype,
            compressors=COMPRESSOR,
        )

    def _write_episode(self, arrays: Mapping[str, np.ndarray], length: int, meta_json: str) -> int:
        try:
            return self._write_uncommitted_then_commit(arrays, length, meta_json)
        except BaseException:
            # A failed write (disk full, interrupt) must not leave half an episode for the next append.
            self._arrays.clear()
            self._discard_uncommitted()
            raise

    def _write_uncommitted_then_commit(
        self, arrays: Mapping[str, np.ndarray], length: int, meta_json: str
    ) -> int:
        start, index = self.num_steps, self.num_episodes
        stop = start + length
        keys = dict(self._commit["keys"])
        # 1. Data past the committed end: invisible to readers until the commit below.
        for key, arr in arrays.items():
            if key not in keys:
                self._arrays[key] = self._create_array(key, arr)
                keys[key] = {"shape": list(arr.shape[1:]), "dtype": str(arr.dtype)}
            target = self._array(key)
            target.resize((stop, *arr.shape[1:]))
            target[start:stop] = arr
        # 2. The episode's end and metadata, also past the committed count.
        ends, metas = self._root[EPISODE_ENDS], self._root[EPISODE_META]
        ends.resize((index + 1,))
        ends[index] = stop
        metas.resize((index + 1,))
        metas[index] = meta_json
        # 3. The commit: one small file replaced atomically.
        commit = {"format_version": FORMAT_VERSION, "episodes": index + 1, "steps": stop, "keys": keys}
        atomic_write_text(self.path / COMMIT_FILE, json.dumps(commit, sort_keys=True), durable=True)
        self._commit = commit
        self._ends = np.append(self._ends, np.int64(stop))
        return index


class EpisodeWriter:
    """Buffers one episode in memory, step by step, and appends it to a store on :meth:`commit`.

    Use as a context manager so an exception discards the half-recorded episode::

        with store.writer() as writer:
            for _ in range(horizon):
                obs, _, done, _, info = env.step(action)
                writer.add(obs, action, info["anchors"])
            writer.commit({"task": "pour", "success": info["success"], ...})
    """

    def __init__(self, store: EpisodeStore | None = None, reuse_buffers: bool = False):
        # Without a store it is a plain step buffer (e.g. in a worker process that sends the
        # stacked episode to the single writer).
        self.store = store
        # One preallocated (capacity, ...) array per key, filled step by step: a step is copied
        # once, into place, instead of once on add and again by a final np.stack (0.3-0.6 s of a
        # 10 s recorded episode went to that second copy of ~100 MB of images).
        self._steps: dict[str, np.ndarray] = {}
        self._length = 0
        # With reuse_buffers, the next episode writes into the same arrays: first touches of fresh
        # memory cost 0.4-0.7 s per ~100 MB episode on our VM, a rewrite of touched memory 0.03 s.
        # The views stacked() returned are then only valid until the next episode's first add().
        self.reuse_buffers = reuse_buffers
        self._spare: dict[str, np.ndarray] = {}

    def __len__(self) -> int:
        return self._length

    def add(
        self,
        obs: Mapping[str, np.ndarray],
        action: np.ndarray,
        anchors: Mapping[str, np.ndarray] | None = None,
    ) -> None:
        """Record one control step: its observation, the action taken, and the privileged anchors."""
        unknown = sorted(set(obs) - set(OBS_KEYS))
        if unknown:
            raise EpisodeDataError(
                f"unknown observation keys {unknown}; expected a subset of {list(OBS_KEYS)}"
            )
        step = {key: np.asarray(value) for key, value in obs.items()}
        step[ACTION_KEY] = np.asarray(action)
        for name, value in (anchors or {}).items():
            step[anchor_key(name)] = np.atleast_1d(np.asarray(value))
        if self._steps and set(step) != set(self._steps):
            missing, extra = sorted(set(self._steps) - set(step)), sorted(set(step) - set(self._steps))
            raise EpisodeDataError(
                f"step {len(self)} has different keys than the first step: "
                f"missing {missing}, unexpected {extra}"
            )
        t = self._length
        for key, value in step.items():
            buffer = self._steps.get(key)
            if buffer is None:
                spare = self._spare.pop(key, None)
                fits = spare is not None and spare.shape[1:] == value.shape and spare.dtype == value.dtype
                buffer = spare if fits else np.empty((_FIRST_CAPACITY, *value.shape), value.dtype)
            elif value.shape != buffer.shape[1:]:
                raise EpisodeDataError(
                    f"the steps of key {key!r} changed shape within the episode: "
                    f"{buffer.shape[1:]} before, {value.shape} at step {t}"
                )
            if t == len(buffer) or value.dtype != buffer.dtype:  # grow, or widen as np.stack would
                grown = np.empty(
                    (max(len(buffer), 2 * t), *value.shape), np.result_type(buffer.dtype, value.dtype)
                )
                grown[:t] = buffer[:t]
                buffer = grown
            buffer[t] = value  # the copy: envs may reuse their observation buffers
            self._steps[key] = buffer
        self._length = t + 1

    def stacked(self) -> dict[str, np.ndarray]:
        """The buffered steps as (T, ...) arrays: views of the buffers, which :meth:`commit` and
        :meth:`discard` drop (the views stay valid) unless ``reuse_buffers`` (then the next
        episode overwrites them)."""
        return {key: buffer[: self._length] for key, buffer in self._steps.items()}

    def commit(self, meta: Mapping[str, Any]) -> int:
        """Append the buffered episode (to ``failed/`` if ``meta['success']`` is false); clear the buffer."""
        if not self._steps:
            raise EpisodeDataError("no steps recorded; call add() at least once before commit()")
        if self.store is None:
            raise EpisodeStoreError("this writer has no store; use stacked() and append_episode()")
        index = self.store.append_episode(self.stacked(), meta)
        self.discard()
        return index

    def discard(self) -> None:
        """Drop the buffered steps (kept as spare arrays for the next episode with ``reuse_buffers``)."""
        # Merged, not replaced: a second discard (e.g. after commit) must not lose the spares.
        self._spare = {**self._spare, **self._steps} if self.reuse_buffers else {}
        self._steps, self._length = {}, 0

    def __enter__(self) -> EpisodeWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.discard()
