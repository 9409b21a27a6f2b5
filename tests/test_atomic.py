"""Atomic writes: the target holds the old content or the whole new one, and no temporary file is left."""

import json

import numpy as np
import pytest

from keygen.atomic import atomic_write, atomic_write_json, atomic_write_text


@pytest.mark.parametrize("durable", [False, True])
def test_text_and_json_round_trip_into_new_folders(tmp_path, durable):
    path = atomic_write_text(tmp_path / "a" / "b.txt", "hello", durable=durable)
    assert path.read_text() == "hello"
    js = atomic_write_json(tmp_path / "c.json", {"x": np.float64(1.5), "p": tmp_path}, sort_keys=True)
    assert json.loads(js.read_text()) == {"p": str(tmp_path), "x": 1.5} and js.read_text().endswith("\n")
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["a", "b.txt", "c.json"]


def test_a_failing_writer_keeps_the_old_file_and_cleans_up(tmp_path):
    path = atomic_write_text(tmp_path / "state.json", "old")

    def torn(tmp):
        tmp.write_text("half")
        raise KeyboardInterrupt  # an interruption mid-write

    with pytest.raises(KeyboardInterrupt):
        atomic_write(path, torn)
    assert path.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["state.json"]


def test_the_temporary_file_keeps_the_suffix_so_numpy_writes_the_target(tmp_path):
    path = atomic_write(tmp_path / "cache.npz", lambda tmp: np.savez(tmp, a=np.arange(3)))
    with np.load(path) as data:
        np.testing.assert_array_equal(data["a"], [0, 1, 2])
    assert [p.name for p in tmp_path.iterdir()] == ["cache.npz"]
