"""evaluate(): one JSON line per episode, resume after an interruption, workers, run-dir reading."""

import json

import numpy as np
import pytest

from keygen.data.store import EpisodeStore
from keygen.errors import InvalidParameterError
from keygen.evaluation.evaluate import RunDirError, evaluate, load_results, read_run_info
from keygen.sim import PHYSICS_VERSION


class HoldRunner:
    task, policy_name, execute_steps, last_keypoints = "stack", "hold", 1, None

    def reset(self):
        pass

    def act(self, obs):
        return obs["proprio"]


def hold_factory(run_dir):  # module level: picklable for spawned workers
    return HoldRunner()


def fake_run(tmp_path, **cfg):
    run = tmp_path / "run"
    run.mkdir(parents=True)
    cfg = {"policy": "hold", "task": "stack", "image_size": 32, "num_points": 128} | cfg
    (run / "config.json").write_text(json.dumps(cfg))
    return run


def ev(run, out, **kw):
    args = dict(split="test", setting="easy", episodes_per_object=2, seed=3, workers=1, out_jsonl=out)
    args |= dict(object_ids=[0, 1], runner_factory=hold_factory, max_steps=2, progress=False) | kw
    return evaluate(run, **args)


def test_writes_one_line_per_episode_and_resumes(tmp_path):
    run, out = fake_run(tmp_path), tmp_path / "eval.jsonl"
    summary = ev(run, out)
    assert summary["episodes"] == 4 and summary["new_episodes"] == 4 and summary["success_rate"] == 0.0
    assert set(summary["by_object"]) == {"0", "1"} and summary["ci95"][0] == 0.0
    assert (
        summary["failures"] == {"timeout": 4} and summary["policy"] == "hold" and summary["task"] == "stack"
    )
    lines = out.read_text().splitlines()
    assert len(lines) == 4 and all(json.loads(line)["steps"] == 2 for line in lines)
    # Episode-major order: both objects' episode 0 come first.
    assert [(r["object_id"], r["episode"]) for r in map(json.loads, lines)][:2] == [(0, 0), (1, 0)]

    again = ev(run, out)  # nothing left to do
    assert again["new_episodes"] == 0 and len(out.read_text().splitlines()) == 4
    assert again["by_object"] == summary["by_object"]

    # An interruption: the last episode lost and a torn line left behind.
    out.write_text("\n".join(lines[:3]) + "\n" + lines[3][:20])
    resumed = ev(run, out)
    assert resumed["new_episodes"] == 1 and resumed["episodes"] == 4
    assert len(load_results(out)) == 4

    more = ev(run, out, episodes_per_object=3)  # extends the same file with the new episodes only
    assert more["new_episodes"] == 2 and more["episodes"] == 6


def test_rows_of_another_physics_revision_run_again(tmp_path):
    run, out = fake_run(tmp_path), tmp_path / "eval.jsonl"
    ev(run, out, episodes_per_object=1)
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert {r["physics"] for r in rows} == {PHYSICS_VERSION}
    old = rows[0] | {"physics": PHYSICS_VERSION - 1}
    legacy = {k: v for k, v in rows[1].items() if k != "physics"}  # written before revisions existed
    out.write_text("".join(json.dumps(r) + "\n" for r in (old, legacy)))
    assert load_results(out) == {}
    again = ev(run, out, episodes_per_object=1)
    assert again["new_episodes"] == 2 and again["episodes"] == 2
    assert len(load_results(out)) == 2 and len(out.read_text().splitlines()) == 4  # old rows kept


def test_another_seed_gives_other_episodes(tmp_path):
    run, out = fake_run(tmp_path), tmp_path / "eval.jsonl"
    a, b = ev(run, out, episodes_per_object=1), ev(run, out, episodes_per_object=1, seed=4)
    assert a["new_episodes"] == b["new_episodes"] == 2
    seeds = {r["seed"] for r in load_results(out).values()}
    assert len(seeds) == 4


def test_two_workers_give_the_same_episodes(tmp_path):
    run = fake_run(tmp_path)
    one = ev(run, tmp_path / "one.jsonl", episodes_per_object=1)
    two = ev(run, tmp_path / "two.jsonl", episodes_per_object=1, workers=2)
    assert one["episodes"] == two["episodes"] == 2

    def strip(path):
        return {k: (r["steps"], r["success"]) for k, r in load_results(path).items()}

    assert strip(tmp_path / "one.jsonl") == strip(tmp_path / "two.jsonl")


def test_videos_of_the_first_episodes(tmp_path):
    run, out = fake_run(tmp_path), tmp_path / "eval.jsonl"
    summary = ev(run, out, object_ids=[0], episodes_per_object=2, videos=1)
    assert len(summary["videos"]) == 1
    assert (tmp_path / "eval_videos" / "test_easy_obj00_ep00.mp4").stat().st_size > 0


def test_run_info_from_the_dataset(tmp_path):
    store = EpisodeStore(tmp_path / "demos.zarr", mode="a")
    t = 3
    steps = {
        "depth": np.zeros((t, 4, 40, 40), np.float32),
        "object_cloud": np.zeros((t, 200, 3), np.float32),
        "proprio": np.zeros((t, 10), np.float32),
        "action": np.zeros((t, 10), np.float32),
    }
    for obj in (0, 2):
        store.append_episode(steps, {"task": "knife", "split": "policy", "object_id": obj, "success": True})
    run = fake_run(
        tmp_path, task=None, image_size=None, num_points=None, dataset=str(tmp_path / "demos.zarr")
    )
    info = read_run_info(run)
    assert (info.task, info.image_size, info.num_points) == ("knife", 40, 200)
    assert (info.train_split, info.train_object_ids, info.policy) == ("policy", (0, 2), "hold")


def test_errors_say_what_is_wrong(tmp_path):
    with pytest.raises(RunDirError, match="config.json"):
        read_run_info(tmp_path)
    keypoint_run = tmp_path / "kp"
    keypoint_run.mkdir()
    (keypoint_run / "train_config.json").write_text("{}")
    with pytest.raises(RunDirError, match="is a keypoint run.*keygen keypoints eval"):
        read_run_info(keypoint_run)
    run = fake_run(tmp_path, dataset=str(tmp_path / "missing.zarr"))
    with pytest.raises(RunDirError, match="does not exist"):
        read_run_info(run)
    (run / "config.json").write_text(json.dumps({"policy": "hold"}))
    with pytest.raises(RunDirError, match="task"):
        read_run_info(run)
    for text, message in (("{not json", "not valid JSON"), ("[1, 2]", "list")):
        (run / "config.json").write_text(text)
        with pytest.raises(RunDirError, match=message):
            read_run_info(run)
    good = fake_run(tmp_path / "g")
    with pytest.raises(InvalidParameterError, match="episodes_per_object"):
        ev(good, tmp_path / "x.jsonl", episodes_per_object=0)
    with pytest.raises(InvalidParameterError, match="split"):
        ev(good, tmp_path / "x.jsonl", split="validation")


def test_worker_initializer_pins_an_already_imported_torch_to_one_thread(monkeypatch):
    # spawn re-imports the user's main module before the initializer: torch may be loaded already.
    import torch

    from keygen.evaluation import evaluate as evaluate_module

    previous = torch.get_num_threads()
    monkeypatch.setenv("OMP_NUM_THREADS", "8")
    try:
        torch.set_num_threads(2)
        evaluate_module._init_worker(1)
        assert torch.get_num_threads() == 1
        assert evaluate_module.os.environ["OMP_NUM_THREADS"] == "1"
    finally:
        torch.set_num_threads(previous)
