"""The zarr episode store: round trips, metadata, failed episodes, bad input, and crash safety."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from keygen.data import (
    ACTION_KEY,
    OBS_KEYS,
    EpisodeDataError,
    EpisodeStore,
    EpisodeStoreError,
    EpisodeWriter,
    StoreCorruptedError,
)
from keygen.errors import KeyGenError

V, H, W, N = 2, 16, 16, 64
ANCHORS = {"spout": 3, "fill_level": 1}


def episode_length(seed: int) -> int:
    return 4 + seed % 7


def make_episode(seed: int, length: int | None = None) -> dict[str, np.ndarray]:
    """A synthetic episode with the environment's keys and dtypes, small sizes; a pure function of seed."""
    rng = np.random.default_rng(seed)
    t = episode_length(seed) if length is None else length
    steps = {
        "rgb": rng.integers(0, 256, (t, V, H, W, 3), dtype=np.uint8),
        "depth": rng.uniform(0.0, 2.0, (t, V, H, W)).astype(np.float32),
        "segmentation": rng.integers(0, 3, (t, V, H, W), dtype=np.int32),
        "intrinsics": np.broadcast_to(np.eye(3, dtype=np.float32), (t, V, 3, 3)).copy(),
        "extrinsics": rng.normal(size=(t, V, 4, 4)).astype(np.float32),
        "proprio": rng.normal(size=(t, 10)).astype(np.float32),
        "object_cloud": rng.normal(size=(t, N, 3)).astype(np.float32),
        "object_cloud_ids": rng.integers(1, 3, (t, N), dtype=np.int32),
        "scene_cloud": rng.normal(size=(t, N, 3)).astype(np.float32),
        ACTION_KEY: rng.normal(size=(t, 10)).astype(np.float32),
    }
    for name, size in ANCHORS.items():
        steps[f"anchors/{name}"] = rng.normal(size=(t, size)).astype(np.float32)
    return steps


def make_meta(seed: int, success: bool = True) -> dict:
    return {
        "task": "pour",
        "object_ids": [["mug", "policy", seed % 5]],
        "split": "policy",
        "setting": "in_domain",
        "scale": np.float64(1.0 + 0.01 * seed),
        "seed": np.int64(seed),
        "success": success,
        "failure": None if success else "dropped",
        "extra": {"nested": [1, 2, 3]},
    }


def assert_episode_equal(got: dict[str, np.ndarray], want: dict[str, np.ndarray]) -> None:
    assert set(got) == set(want)
    for key in want:
        assert got[key].dtype == want[key].dtype, key
        np.testing.assert_array_equal(got[key], want[key], err_msg=key)


def test_round_trip_reopen_and_meta(tmp_path: Path) -> None:
    path = tmp_path / "demos.zarr"
    store = EpisodeStore(path, mode="w")
    seeds = [0, 1, 2, 3]
    for k, seed in enumerate(seeds):
        assert store.append_episode(make_episode(seed), make_meta(seed)) == k
    lengths = [episode_length(s) for s in seeds]
    assert store.num_episodes == 4 and len(store) == 4
    assert store.num_steps == sum(lengths)
    np.testing.assert_array_equal(store.episode_ends, np.cumsum(lengths))

    reopened = EpisodeStore(path, mode="r")
    assert reopened.keys() == sorted([*OBS_KEYS, ACTION_KEY, "anchors/spout", "anchors/fill_level"])
    for k, seed in enumerate(seeds):
        assert_episode_equal(reopened.episode(k), make_episode(seed))
        meta = reopened.episode_meta(k)
        assert meta["seed"] == seed and meta["scale"] == pytest.approx(1.0 + 0.01 * seed)
        assert meta["extra"] == {"nested": [1, 2, 3]} and meta["success"] is True
        s = reopened.episode_slice(k)
        assert s.stop - s.start == lengths[k]
    assert_episode_equal(reopened.episode(-1), make_episode(seeds[-1]))
    assert set(reopened.episode(1, keys=["proprio"])) == {"proprio"}
    reopened.validate()

    # Appending after reopening continues where the store ended.
    again = EpisodeStore(path, mode="a")
    assert again.append_episode(make_episode(10), make_meta(10)) == 4
    assert_episode_equal(EpisodeStore(path, "r").episode(4), make_episode(10))


def test_info_reports_counts_shapes_bytes_and_failures(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path / "s.zarr", mode="w")
    store.append_episode(make_episode(0), make_meta(0))
    store.append_episode(make_episode(1), make_meta(1))
    assert store.append_episode(make_episode(2), make_meta(2, success=False)) == 0  # index in failed/
    info = store.info()
    assert info["episodes"] == 2
    assert info["steps"] == episode_length(0) + episode_length(1)
    assert info["keys"]["rgb"] == {
        "shape": [V, H, W, 3],
        "dtype": "uint8",
        "chunk_steps": info["keys"]["rgb"]["chunk_steps"],
    }
    assert info["keys"]["object_cloud_ids"]["dtype"] == "int32"
    assert info["keys"]["anchors/fill_level"]["shape"] == [1]
    assert info["success"]["succeeded"] == 2 and info["success"]["failed"] == 1
    assert info["success"]["success_rate"] == pytest.approx(2 / 3)
    assert info["success"]["failure_reasons"] == {"dropped": 1}
    assert info["bytes_on_disk"] > 0 and info["failed_bytes_on_disk"] > 0
    json.dumps(info)  # plain JSON, ready for a CLI


def test_failed_episodes_are_kept_apart(tmp_path: Path) -> None:
    path = tmp_path / "s.zarr"
    store = EpisodeStore(path, mode="w")
    store.append_episode(make_episode(0), make_meta(0))
    store.append_episode(make_episode(5), make_meta(5, success=False))
    store.append_episode(make_episode(1), make_meta(1))
    reader = EpisodeStore(path, mode="r")
    assert reader.num_episodes == 2
    assert all(reader.episode_meta(i)["success"] for i in range(2))
    assert reader.failed is not None and reader.failed.num_episodes == 1
    assert_episode_equal(reader.failed.episode(0), make_episode(5))
    assert reader.failed.episode_meta(0)["failure"] == "dropped"
    reader.validate()


def test_writer_buffers_steps_and_commits(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path / "s.zarr", mode="w")
    episode = make_episode(3)
    obs_keys = [k for k in episode if k in OBS_KEYS]
    with store.writer() as writer:
        for t in range(episode_length(3)):
            obs = {k: episode[k][t] for k in obs_keys}
            anchors = {
                "spout": episode["anchors/spout"][t],
                "fill_level": float(episode["anchors/fill_level"][t, 0]),
            }
            writer.add(obs, episode[ACTION_KEY][t].astype(np.float64), anchors)
        assert len(writer) == episode_length(3)
        assert writer.commit(make_meta(3)) == 0
        assert len(writer) == 0
    assert_episode_equal(store.episode(0), episode)

    # Leaving the block by an exception discards the partial episode.
    with pytest.raises(RuntimeError), store.writer() as writer:
        writer.add({k: episode[k][0] for k in obs_keys}, episode[ACTION_KEY][0])
        raise RuntimeError("simulated crash of the rollout")
    assert store.num_episodes == 1
    with pytest.raises(EpisodeDataError, match="no steps"):
        store.writer().commit(make_meta(0))


def test_writer_copies_each_step_grows_past_its_capacity_and_checks_shapes() -> None:
    writer = EpisodeWriter()
    reused = np.zeros(3, np.float32)  # an env that writes every observation into one buffer
    for t in range(300):  # more steps than the first reservation
        reused[:] = t
        writer.add({"proprio": reused}, np.full(10, t, np.int64), {"spout": np.full(3, t, np.int64)})
    steps = writer.stacked()
    assert len(writer) == 300 and steps["proprio"].shape == (300, 3)
    np.testing.assert_array_equal(steps["proprio"][:, 0], np.arange(300, dtype=np.float32))
    assert steps[ACTION_KEY].dtype == np.int64
    # A later float step widens the column as np.stack of the steps would, keeping earlier values.
    writer.add({"proprio": reused}, np.full(10, 0.5), {"spout": np.zeros(3, np.int64)})
    steps = writer.stacked()
    assert steps[ACTION_KEY].dtype == np.float64 and steps[ACTION_KEY][299, 0] == 299
    assert steps[ACTION_KEY][300, 0] == 0.5
    with pytest.raises(EpisodeDataError, match="changed shape"):
        writer.add({"proprio": np.zeros(4, np.float32)}, np.zeros(10), {"spout": np.zeros(3)})
    writer.discard()
    assert len(writer) == 0 and writer.stacked() == {}


def test_a_reusing_writer_records_the_next_episode_into_the_same_arrays() -> None:
    writer = EpisodeWriter(reuse_buffers=True)
    for t in range(5):
        writer.add({"proprio": np.full(3, t, np.float32)}, np.zeros(10))
    first = writer.stacked()["proprio"]
    writer.discard()
    writer.discard()  # twice in a row (as a commit then a discard): the spare arrays survive
    for t in range(3):
        writer.add({"proprio": np.full(3, 10 + t, np.float32)}, np.ones(10))
    second = writer.stacked()
    assert np.shares_memory(first, second["proprio"]) and len(second["proprio"]) == 3
    np.testing.assert_array_equal(second["proprio"][:, 0], [10, 11, 12])
    np.testing.assert_array_equal(second[ACTION_KEY], np.ones((3, 10)))
    # A key of another shape or dtype gets a fresh array; a plain writer never reuses.
    writer.discard()
    writer.add({"proprio": np.zeros(4, np.float64)}, np.zeros(10))
    assert not np.shares_memory(first, writer.stacked()["proprio"])
    plain = EpisodeWriter()
    plain.add({"proprio": np.zeros(3, np.float32)}, np.zeros(10))
    kept = plain.stacked()["proprio"]
    plain.discard()
    plain.add({"proprio": np.ones(3, np.float32)}, np.zeros(10))
    assert not np.shares_memory(kept, plain.stacked()["proprio"]) and kept[0, 0] == 0


def _bad_inputs() -> list[tuple[str, dict, dict]]:
    good = make_episode(7)
    cases = []
    missing = dict(good)
    del missing["depth"]
    cases.append(("missing", missing, make_meta(7)))
    no_action = dict(good)
    del no_action[ACTION_KEY]
    cases.append(("action", no_action, make_meta(7)))
    extra = dict(good, bogus=good["proprio"])
    cases.append(("unknown key", extra, make_meta(7)))
    wrong_shape = dict(good, rgb=np.zeros((episode_length(7), V, H + 1, W, 3), np.uint8))
    cases.append(("shape", wrong_shape, make_meta(7)))
    nan_action = dict(good, action=good[ACTION_KEY].copy())
    nan_action[ACTION_KEY][2, 4] = np.nan
    cases.append(("NaN", nan_action, make_meta(7)))
    t_mismatch = dict(good, proprio=good["proprio"][:-1])
    cases.append(("same number of steps", t_mismatch, make_meta(7)))
    bad_ids = dict(good, object_cloud_ids=good["object_cloud_ids"].astype(np.float32))
    cases.append(("integers", bad_ids, make_meta(7)))
    cases.append(("success", good, {"task": "pour"}))
    cases.append(("JSON", good, dict(make_meta(7), blob=object())))
    return cases


@pytest.mark.parametrize("case", range(len(_bad_inputs())))
def test_bad_input_raises_and_writes_nothing(tmp_path: Path, case: int) -> None:
    path = tmp_path / "s.zarr"
    store = EpisodeStore(path, mode="w")
    store.append_episode(make_episode(0), make_meta(0))
    before = store.info()
    match, steps, meta = _bad_inputs()[case]
    with pytest.raises(EpisodeDataError, match=match) as err:
        store.append_episode(steps, meta)
    assert isinstance(err.value, KeyGenError)
    assert store.num_episodes == 1 and store.failed is not None and store.failed.num_episodes == 0
    after = EpisodeStore(path, mode="r").info()
    assert after["episodes"] == 1 and after["steps"] == before["steps"]
    assert after["bytes_on_disk"] == before["bytes_on_disk"]


def test_first_episode_shape_rules(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path / "s.zarr", mode="w")
    bad = make_episode(0)
    bad["proprio"] = bad["proprio"][:, :9]
    with pytest.raises(EpisodeDataError, match="proprio"):
        store.append_episode(bad, make_meta(0))
    bad = make_episode(0)
    bad["object_cloud_ids"] = bad["object_cloud_ids"][:, :10]
    with pytest.raises(EpisodeDataError, match="object_cloud_ids"):
        store.append_episode(bad, make_meta(0))
    assert store.num_episodes == 0 and store.keys() == []
    store.append_episode(make_episode(0), make_meta(0))  # the store still accepts a good first episode
    assert store.num_episodes == 1


def test_modes_and_errors(tmp_path: Path) -> None:
    with pytest.raises(EpisodeStoreError, match="no episode store"):
        EpisodeStore(tmp_path / "absent", mode="r")
    path = tmp_path / "s.zarr"
    EpisodeStore(path, mode="w").append_episode(make_episode(0), make_meta(0))
    reader = EpisodeStore(path, mode="r")
    with pytest.raises(EpisodeStoreError, match="read-only"):
        reader.append_episode(make_episode(1), make_meta(1))
    with pytest.raises(EpisodeStoreError, match="episode index"):
        reader.episode(1)
    with pytest.raises(EpisodeStoreError, match="no key"):
        reader.read("nope", 0, 1)
    assert EpisodeStore(path, mode="w").num_episodes == 0
    other = tmp_path / "notastore"
    other.mkdir()
    (other / "precious.txt").write_text("keep me")
    with pytest.raises(EpisodeStoreError, match="not an episode store"):
        EpisodeStore(other, mode="w")
    assert (other / "precious.txt").exists()


def test_reader_sees_only_committed_until_refresh(tmp_path: Path) -> None:
    path = tmp_path / "s.zarr"
    writer = EpisodeStore(path, mode="w")
    writer.append_episode(make_episode(0), make_meta(0))
    reader = EpisodeStore(path, mode="r")
    writer.append_episode(make_episode(1), make_meta(1))
    assert reader.num_episodes == 1
    reader.refresh()
    assert reader.num_episodes == 2
    assert_episode_equal(reader.episode(1), make_episode(1))


def test_max_episodes_views_the_first_episodes_only(tmp_path: Path) -> None:
    path = tmp_path / "s.zarr"
    writer = EpisodeStore(path, mode="w")
    for seed in range(4):
        writer.append_episode(make_episode(seed), make_meta(seed))
    head = EpisodeStore(path, mode="r", max_episodes=2)
    lengths = [episode_length(s) for s in range(2)]
    assert head.num_episodes == 2 and len(head) == 2 and head.num_steps == sum(lengths)
    np.testing.assert_array_equal(head.episode_ends, np.cumsum(lengths))
    assert [m["seed"] for m in head.all_meta()] == [0, 1]
    assert_episode_equal(head.episode(-1), make_episode(1))
    with pytest.raises(EpisodeStoreError, match="episode index"):
        head.episode(2)
    with pytest.raises(EpisodeStoreError, match="step range"):
        head.read("proprio", 0, sum(lengths) + 1)  # the third episode's steps are not in the view
    writer.append_episode(make_episode(4), make_meta(4))
    head.refresh()  # newer episodes stay outside the view
    assert head.num_episodes == 2 and head.num_steps == sum(lengths)
    assert EpisodeStore(path, mode="r", max_episodes=5).num_episodes == 5  # exactly all of them
    with pytest.raises(EpisodeStoreError, match="holds 5 episodes, fewer than the 6"):
        EpisodeStore(path, mode="r", max_episodes=6)
    with pytest.raises(KeyGenError, match="mode='r'"):
        EpisodeStore(path, mode="a", max_episodes=2)
    for bad in (0, -1, 1.5, True):
        with pytest.raises(KeyGenError, match="positive int"):
            EpisodeStore(path, mode="r", max_episodes=bad)


def test_validate_detects_corruption(tmp_path: Path) -> None:
    path = tmp_path / "s.zarr"
    store = EpisodeStore(path, mode="w")
    store.append_episode(make_episode(0), make_meta(0))
    commit = json.loads((path / "commit.json").read_text())
    commit["steps"] += 3  # claims steps that were never written
    (path / "commit.json").write_text(json.dumps(commit))
    with pytest.raises(StoreCorruptedError, match="episode_ends"):
        EpisodeStore(path, mode="r").validate()


# ------------------------------------------------------------------------------------- crash safety

CHILD = textwrap.dedent(
    """
    import os, signal, sys
    sys.path.insert(0, {tests_dir!r})
    import keygen.data.store as store_module
    from test_store import make_episode, make_meta

    path, target, die_before_commit = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    store = store_module.EpisodeStore(path, mode="a")
    if die_before_commit >= 0:
        real_commit = store_module.atomic_write_text
        def commit_or_die(file, text, **kw):
            # Arrays and meta of this episode are on disk; die right before the commit.
            if store.num_episodes == die_before_commit and file.name == "commit.json":
                os.kill(os.getpid(), signal.SIGKILL)
            real_commit(file, text, **kw)
        store_module.atomic_write_text = commit_or_die
    while store.num_episodes < target:
        seed = store.num_episodes  # episode i is always make_episode(i): resumable and checkable
        store.append_episode(make_episode(seed), make_meta(seed))
    """
)


def _run_child(tmp_path: Path, path: Path, target: int, die_before_commit: int = -1) -> subprocess.Popen:
    script = tmp_path / "append_loop.py"
    script.write_text(CHILD.format(tests_dir=str(Path(__file__).parent)))
    return subprocess.Popen([sys.executable, str(script), str(path), str(target), str(die_before_commit)])


def _check_committed_episodes(path: Path) -> int:
    store = EpisodeStore(path, mode="a")  # a writable open cuts away the unfinished append
    store.validate()
    for i in range(store.num_episodes):
        assert_episode_equal(store.episode(i), make_episode(i))
        assert store.episode_meta(i)["seed"] == i
    for key in store.keys():
        assert store._root[f"data/{key}"].shape[0] == store.num_steps
    return store.num_episodes


def test_sigkill_before_commit_keeps_exactly_the_committed_episodes(tmp_path: Path) -> None:
    path = tmp_path / "s.zarr"
    child = _run_child(tmp_path, path, target=8, die_before_commit=3)
    assert child.wait(timeout=60) == -signal.SIGKILL
    # The fourth episode's arrays were written past the end; a reader ignores them.
    assert EpisodeStore(path, mode="r").num_episodes == 3
    assert _check_committed_episodes(path) == 3
    # Resuming appends until the requested count, and the store holds exactly that.
    child = _run_child(tmp_path, path, target=6)
    assert child.wait(timeout=60) == 0
    assert _check_committed_episodes(path) == 6


def test_sigkill_at_a_random_moment_then_resume(tmp_path: Path) -> None:
    path = tmp_path / "s.zarr"
    rng = np.random.default_rng(1)
    child = _run_child(tmp_path, path, target=10_000)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:  # wait until a few episodes are in, then kill mid-flight
        commit = path / "commit.json"
        if commit.exists() and json.loads(commit.read_text())["episodes"] >= 2:
            break
        time.sleep(0.01)
    time.sleep(float(rng.uniform(0.0, 0.05)))
    os.kill(child.pid, signal.SIGKILL)
    child.wait(timeout=10)
    committed = _check_committed_episodes(path)
    assert committed >= 2
    child = _run_child(tmp_path, path, target=committed + 2)
    assert child.wait(timeout=60) == 0
    assert _check_committed_episodes(path) == committed + 2
