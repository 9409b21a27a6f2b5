"""keygen benchmark with fake stages: table on stdout, benchmark.md/json, overrides, reuse."""

import argparse
import json

import pytest

from keygen.cli import benchmark
from keygen.errors import InvalidParameterError
from keygen.evaluation.pipeline import StageFunctions, get_preset


def fake_functions():
    def demos(task, preset, path, progress):
        path.mkdir(parents=True, exist_ok=True)
        return {"path": str(path), "episodes": preset.demos}

    def train(*args):
        out_dir = args[-2]
        out_dir.mkdir(parents=True, exist_ok=True)
        return {"run_dir": str(out_dir)}

    def evaluate(run_dir, split, setting, object_ids, preset, jsonl, progress):
        n = len(object_ids) * preset.episodes_per_object
        return {"episodes": n, "successes": n, "success_rate": 1.0, "ci95": [0.5, 1.0], "failures": {}}

    return StageFunctions(demos, train, train, evaluate)


def parse(argv):
    p = argparse.ArgumentParser()
    sub = p.add_subparsers()
    benchmark.register(sub)
    args = p.parse_args(argv)
    args.stage_functions = fake_functions()
    return args


def test_quick_stack_keygen(tmp_path, capsys):
    argv = [
        "benchmark",
        "--preset",
        "quick",
        "--tasks",
        "stack",
        "--policies",
        "keygen",
        "--out",
        str(tmp_path),
    ]
    args = parse([*argv, "--episodes-per-object", "2", "--demos", "3", "--workers", "1"])
    assert args.func(args) == 0
    out = capsys.readouterr().out.strip().splitlines()
    report = json.loads(out[-1])
    rows = report["results"]
    assert len(rows) == 4 and {(r["split"], r["setting"]) for r in rows} == {
        (s, st) for s in ("seen", "unseen") for st in ("easy", "hard")
    }
    assert all({"task", "policy", "split", "setting", "success_rate", "ci95"} <= set(r) for r in rows)
    unseen = len(get_preset("quick").unseen_ids)
    assert next(r for r in rows if r["split"] == "unseen")["episodes"] == unseen * 2
    assert report["preset"]["demos"] == 3 and report["preset"]["workers"] == 1
    assert any(line.startswith("| Method | Stacking easy | Stacking hard |") for line in out)
    assert (tmp_path / "benchmark.md").exists() and (tmp_path / "benchmark.json").exists()

    args = parse([*argv, "--episodes-per-object", "2", "--demos", "3", "--workers", "1", "--json"])
    args.func(args)
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and all(s["reused"] for s in json.loads(out[0])["stages"])


def test_bad_names(tmp_path):
    for flag, value in (("--tasks", "stack,fly"), ("--policies", "act")):
        args = parse(["benchmark", flag, value, "--out", str(tmp_path)])
        with pytest.raises(InvalidParameterError, match=flag):
            args.func(args)


def test_demo_has_a_skip_benchmark_flag():
    from keygen.cli import demo

    p = argparse.ArgumentParser()
    demo.register(p.add_subparsers())
    assert p.parse_args(["demo", "--skip-benchmark"]).skip_benchmark is True
    assert p.parse_args(["demo"]).skip_benchmark is False
