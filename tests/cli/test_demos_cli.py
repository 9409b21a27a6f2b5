"""keygen expert / demos / data on the stacking task, including a SIGKILL in the middle of a run."""

import json
import os
import signal
import subprocess
import sys
import time

from keygen.cli.main import main
from keygen.data.store import EpisodeStore

SMALL = ["--image-size", "32", "--num-points", "64"]


def last_json(capsys) -> dict:
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_expert_reports_success_by_object_and_failures(capsys):
    code = main(
        [
            "expert",
            "--task",
            "stack",
            "--split",
            "test",
            "--object-ids",
            "1,2",
            "--episodes",
            "2",
            "--setting",
            "hard",
            "--seed",
            "7",
            "--json",
            *SMALL,
        ]
    )
    assert code == 0
    summary = last_json(capsys)
    assert summary["episodes"] == 2 and set(summary["by_object"]) == {"1", "2"}
    assert {"success_rate", "ci95", "failures"} <= set(summary)
    assert summary["success_rate"] == 1.0


def test_demos_record_resume_info_and_video(tmp_path, capsys):
    out = tmp_path / "stack.zarr"
    args = [
        "demos",
        "--task",
        "stack",
        "--split",
        "policy",
        "--object-ids",
        "0",
        "--setting",
        "easy",
        "--out",
        str(out),
        *SMALL,
    ]
    assert main([*args, "--episodes", "1"]) == 0
    first = last_json(capsys)
    assert first["episodes"] == 1 and {"success_rate", "seconds"} <= set(first)
    assert main([*args, "--episodes", "2"]) == 0  # resumes: one more
    assert last_json(capsys)["new_episodes"] == 1
    store = EpisodeStore(out, mode="r")
    store.validate()
    assert store.num_episodes == 2
    seeds = [m["seed"] for m in store.all_meta()]
    assert len(set(seeds)) == 2, "a resumed run uses new seeds"
    ep = store.episode(1, keys=["action", "object_cloud", "proprio"])
    assert ep["action"].shape[1] == 10 and ep["object_cloud"].shape[1:] == (64, 3)
    assert main(["data", "info", str(out)]) == 0
    assert last_json(capsys)["episodes"] == 2
    assert main(["data", "video", str(out), "--episode", "1", "--out", str(tmp_path / "ep.mp4")]) == 0
    assert (tmp_path / "ep.mp4").stat().st_size > 0


def test_killed_generation_resumes_to_exactly_the_requested_count(tmp_path):
    out = tmp_path / "killed.zarr"
    cmd = [
        sys.executable,
        "-m",
        "keygen.cli.main",
        "demos",
        "--task",
        "stack",
        "--split",
        "policy",
        "--object-ids",
        "0",
        "--episodes",
        "3",
        "--setting",
        "easy",
        "--out",
        str(out),
        *SMALL,
    ]
    proc = subprocess.Popen(
        cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env={**os.environ, "MUJOCO_GL": "egl"}
    )
    deadline = time.time() + 120
    while time.time() < deadline:  # kill it once the first episode is committed, mid-way through the next
        if (out / "commit.json").exists() and EpisodeStore(out, mode="r").num_episodes >= 1:
            time.sleep(1.0)
            break
        time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    partial = EpisodeStore(out, mode="r")
    assert 1 <= partial.num_episodes < 3
    assert subprocess.run(cmd, capture_output=True, timeout=300).returncode == 0
    store = EpisodeStore(out, mode="r")
    store.validate()
    assert store.num_episodes == 3
    for i in range(3):
        assert store.episode_meta(i)["success"] is True
        assert store.episode_length(i) == len(store.episode(i, keys=["action"])["action"])


def test_pour_grasp_option_reaches_the_expert_and_is_logged(tmp_path, capsys):
    out = tmp_path / "episodes.jsonl"
    argv = ["expert", "--task", "pour", "--split", "policy", "--object-ids", "0", "--episodes", "1"]
    assert main([*argv, "--pour-grasp", "pinch", "--seed", "3", "--json", "--out", str(out), *SMALL]) == 0
    assert last_json(capsys)["episodes"] == 1
    assert json.loads(out.read_text().splitlines()[0])["expert_options"] == {"grasp": "pinch"}


def test_pour_grasp_option_is_refused_for_other_tasks(capsys):
    argv = ["expert", "--task", "stack", "--episodes", "1", "--pour-grasp", "pinch", *SMALL]
    assert main(argv) != 0
    assert "--pour-grasp applies to --task pour only" in capsys.readouterr().err


def test_knife_plan_option_reaches_the_run_spec_and_is_refused_for_other_tasks(capsys):
    import argparse

    from keygen.cli.expert import _spec

    args = argparse.Namespace(
        task="knife", split="policy", object_ids="0", episodes=1, setting="hard", scale=1.0, seed=0,
        image_size=32, num_points=64, pour_grasp="auto", knife_plan="first",
    )  # fmt: skip
    assert _spec(args, record=False).expert_options == (("plan_choice", "first"),)
    assert main(["expert", "--task", "pour", "--episodes", "1", "--knife-plan", "first", *SMALL]) != 0
    assert "--knife-plan applies to --task knife only" in capsys.readouterr().err
