"""keygen eval: human lines, the JSON last line, resume, bad arguments."""

import argparse
import json

import pytest

from keygen.cli import eval as eval_cli
from keygen.errors import InvalidParameterError


class HoldRunner:
    last_keypoints = None

    def reset(self):
        pass

    def act(self, obs):
        return obs["proprio"]


def hold_factory(run_dir):
    return HoldRunner()


def parse(argv):
    p = argparse.ArgumentParser()
    sub = p.add_subparsers()
    eval_cli.register(sub)
    args = p.parse_args(argv)
    args.runner_factory = hold_factory  # a fake policy instead of a trained one
    return args


def make_run(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(
        json.dumps({"policy": "hold", "task": "stack", "image_size": 32, "num_points": 128})
    )
    return run


def test_eval_prints_per_object_and_ends_with_json(tmp_path, capsys):
    run = make_run(tmp_path)
    argv = ["eval", str(run), "--split", "test", "--setting", "hard", "--episodes-per-object", "1"]
    argv += ["--object-ids", "2,3", "--seed", "1", "--max-steps", "2"]
    args = parse(argv)
    assert args.func(args) == 0
    out = capsys.readouterr().out.strip().splitlines()
    summary = json.loads(out[-1])
    assert {"episodes", "success_rate", "ci95", "by_object"} <= set(summary)
    assert summary["episodes"] == 2 and set(summary["by_object"]) == {"2", "3"}
    assert out[0].startswith("object   2: 0/1") and "95% CI" in out[2]
    jsonl = run / "eval" / "test_hard_scale1_seed1.jsonl"
    assert len(jsonl.read_text().splitlines()) == 2

    args = parse([*argv, "--json"])
    args.func(args)
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and json.loads(out[0])["new_episodes"] == 0  # resumed: nothing new


def test_bad_object_ids(tmp_path):
    args = parse(["eval", str(tmp_path), "--object-ids", "a,b"])
    with pytest.raises(InvalidParameterError, match="object-ids"):
        args.func(args)


def test_overridden_sampling_settings_get_their_own_results_file(tmp_path, capsys):
    run = make_run(tmp_path)
    argv = ["eval", str(run), "--episodes-per-object", "1", "--object-ids", "2", "--seed", "1"]
    argv += ["--max-steps", "2", "--execute-steps", "4", "--num-inference-steps", "5", "--json"]
    args = parse(argv)
    assert args.func(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["execute_steps"] == 4 and summary["num_inference_steps"] == 5
    assert summary["out"].endswith("test_hard_scale1_seed1_denoise5_exec4.jsonl")
    assert not (run / "eval" / "test_hard_scale1_seed1.jsonl").exists()
    args = parse([*argv[:-3], "--execute-steps", "0"])
    with pytest.raises(InvalidParameterError, match="execute_steps"):
        args.func(args)


def test_size_normalize_gets_its_own_results_file(tmp_path, capsys):
    run = make_run(tmp_path)
    argv = ["eval", str(run), "--episodes-per-object", "1", "--object-ids", "2", "--seed", "1"]
    args = parse([*argv, "--max-steps", "2", "--size-normalize", "--json"])
    assert args.func(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["size_normalize"] is True and summary["size_frame"] == "uniform"
    assert summary["out"].endswith("test_hard_scale1_seed1_sizenorm.jsonl")
    assert not (run / "eval" / "test_hard_scale1_seed1.jsonl").exists()
    # The per-axis frame is another setting: a file of its own, named in the summary.
    args = parse([*argv, "--max-steps", "2", "--size-normalize", "axes", "--json"])
    assert args.func(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["size_frame"] == "axes" and summary["new_episodes"] == 1
    assert summary["out"].endswith("test_hard_scale1_seed1_sizenorm_axes.jsonl")
    with pytest.raises(SystemExit):
        parse([*argv, "--size-normalize", "sideways"])
    capsys.readouterr()
