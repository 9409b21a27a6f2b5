"""`keygen keypoints train | eval | show` on a tiny run (a few steps, two instances)."""

import argparse
import json

import pytest
from PIL import Image

from keygen.cli import keypoints as kp_cli


def _run(argv):
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    kp_cli.register(sub)
    args = parser.parse_args(argv)
    return args.func(args)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "kp-knife"
    argv = [
        "keypoints",
        "train",
        "--category",
        "knife",
        "--out",
        str(out),
        "--preset",
        "quick",
        "--num-instances",
        "2",
        "--scans-per-instance",
        "3",
        "--canon-steps",
        "6",
        "--detector-steps",
        "6",
        "--no-ablation",
        "--json",
    ]
    assert _run(argv) == 0
    return out


def test_train_prints_a_json_summary_and_writes_the_run(run_dir, capsys):
    argv = [
        "keypoints",
        "train",
        "--category",
        "knife",
        "--out",
        str(run_dir),
        "--preset",
        "quick",
        "--num-instances",
        "2",
        "--scans-per-instance",
        "3",
        "--canon-steps",
        "6",
        "--detector-steps",
        "6",
        "--no-ablation",
        "--json",
    ]
    assert _run(argv) == 0  # a finished run is reused
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["category"] == "knife" and summary["scans"] == 6
    assert (run_dir / "detector" / "model.safetensors").is_file()


def test_eval_json_has_the_headline_metrics(run_dir, capsys):
    argv = [
        "keypoints",
        "eval",
        str(run_dir),
        "--split",
        "test",
        "--pairs",
        "1",
        "--instances",
        "2",
        "--json",
    ]
    assert _run(argv) == 0
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("canon_acc_top1", "canon_acc_sym", "repeatability", "das", "ms_per_object"):
        assert isinstance(last[key], float)
    assert 0 <= last["canon_acc_top1"] <= last["canon_acc_sym"] <= 1
    assert set(last["methods"]) == {"keygen", "keygen_single_pass", "fps_canonical"}
    assert json.loads((run_dir / "eval_test.json").read_text())["scans"] == 4


def test_show_writes_a_png_grid(run_dir, tmp_path):
    out = tmp_path / "grid.png"
    assert (
        _run(["keypoints", "show", str(run_dir), "--out", str(out), "--instances", "2", "--views", "2"]) == 0
    )
    with Image.open(out) as im:
        assert im.size == (4 * 256, 256)


def test_bad_category_is_rejected():
    with pytest.raises(SystemExit):
        _run(["keypoints", "train", "--category", "cup", "--out", "x"])
