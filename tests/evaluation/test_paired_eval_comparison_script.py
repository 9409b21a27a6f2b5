"""benchmarks/paired_eval_comparison.py: pairing by (object, episode), the exact McNemar p-value,
groups, pooling several pairs, and refusing evaluations whose scenes differ."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


@pytest.fixture(scope="module")
def m(load_benchmark_script):
    return load_benchmark_script("paired_eval_comparison")


def _write(path: Path, successes: dict[tuple[int, int], bool], seed_offset: int = 0) -> Path:
    lines = [
        json.dumps(
            {
                "object_id": o,
                "episode": e,
                "seed": 100 * o + e + seed_offset,
                "success": s,
                "failure": None if s else "timeout",
            }
        )  # fmt: skip
        for (o, e), s in successes.items()
    ]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_mcnemar_matches_hand_computed_values(m) -> None:
    assert m.mcnemar_exact(0, 0) == 1.0
    assert m.mcnemar_exact(3, 3) == 1.0
    assert m.mcnemar_exact(0, 5) == pytest.approx(2 / 32)  # 2 * (1/2)^5
    assert m.mcnemar_exact(1, 4) == pytest.approx(2 * 6 / 32)  # 2 * (C(5,0) + C(5,1)) / 2^5
    assert m.mcnemar_exact(4, 16) == m.mcnemar_exact(16, 4)


def test_pairs_by_object_and_episode_with_groups(m, tmp_path: Path) -> None:
    a = {(o, e): e < 2 for o in range(3) for e in range(4)}  # 2 of 4 per object
    b = {(o, e): (e < 3 if o == 2 else e < 2) for o in range(3) for e in range(4)}  # object 2: one more
    b[(0, 0)] = False  # and one fewer on object 0
    b[(0, 3)] = True
    first = m.read_episodes(_write(tmp_path / "a.jsonl", a))
    res = m.compare(first, m.read_episodes(_write(tmp_path / "b.jsonl", b)), {"last": [2]})
    assert res["overall"]["successes"] == [6, 7]
    assert (res["overall"]["only_first"], res["overall"]["only_second"]) == (1, 2)
    assert res["by_object"]["0"]["successes"] == [2, 2] and res["by_object"]["0"]["only_first"] == 1
    assert res["groups"]["last"]["successes"] == [2, 3] and res["groups"]["last"]["episodes"] == 4
    assert res["failures"] == [{"timeout": 6}, {"timeout": 5}]


def test_refuses_evaluations_of_different_scenes(m, tmp_path: Path) -> None:
    a = m.read_episodes(_write(tmp_path / "a.jsonl", {(0, 0): True}))
    b = m.read_episodes(_write(tmp_path / "b.jsonl", {(0, 0): True}, seed_offset=1))
    with pytest.raises(SystemExit, match="different seeds"):
        m.compare(a, b, {})
    c = m.read_episodes(_write(tmp_path / "c.jsonl", {(1, 0): True}))
    with pytest.raises(SystemExit, match="share no"):
        m.compare(a, c, {})
    (tmp_path / "bad.jsonl").write_text("{}\n")
    with pytest.raises(SystemExit, match="not a `keygen eval` episode record"):
        m.read_episodes(tmp_path / "bad.jsonl")


def test_pools_pairs_without_pairing_across_them(m, tmp_path: Path) -> None:
    # Two pairs on the same scenes (say two training seeds): A wins twice in the first, B once in the
    # second; pooled, the disagreements add up and nothing pairs across the pairs.
    a1 = {(0, 0): True, (0, 1): True, (1, 0): False}
    b1 = {(0, 0): False, (0, 1): False, (1, 0): False}
    a2 = {(0, 0): False, (0, 1): True, (1, 0): True}
    b2 = {(0, 0): True, (0, 1): True, (1, 0): True}
    read = [
        m.read_episodes(_write(tmp_path / f"{n}.jsonl", d))
        for n, d in zip("wxyz", (a1, b1, a2, b2), strict=True)
    ]
    first, second = m.pool([(read[0], read[1]), (read[2], read[3])])
    res = m.compare(first, second, {})
    assert res["overall"]["episodes"] == 6
    assert res["overall"]["successes"] == [4, 3]
    assert (res["overall"]["only_first"], res["overall"]["only_second"]) == (2, 1)
    assert res["overall"]["mcnemar_p"] == pytest.approx(m.mcnemar_exact(2, 1))
    assert res["by_object"]["0"]["episodes"] == 4 and res["by_object"]["1"]["successes"] == [1, 1]
    # One pair is the plain comparison.
    assert m.pool([(read[0], read[1])]) == (read[0], read[1])


def test_command_line_takes_files_in_pairs(m, tmp_path: Path, monkeypatch, capsys) -> None:
    a = _write(tmp_path / "a.jsonl", {(0, 0): True, (0, 1): False})
    b = _write(tmp_path / "b.jsonl", {(0, 0): False, (0, 1): False})
    out = tmp_path / "r.json"
    argv = ["paired_eval_comparison.py", str(a), str(b), str(a), str(b), "--names", "x,y", "--out", str(out)]
    monkeypatch.setattr("sys.argv", argv)
    m.main()
    res = json.loads(out.read_text())
    assert res["pairs"] == 2 and res["overall"]["episodes"] == 4 and res["overall"]["only_first"] == 2
    assert "| all | 4 | 2 | 0 | 2 | 0 |" in capsys.readouterr().out
    monkeypatch.setattr("sys.argv", argv[:4])
    with pytest.raises(SystemExit, match="in pairs"):
        m.main()
