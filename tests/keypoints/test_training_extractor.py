"""A tiny training run end to end: files, resume, reuse, the extractor's contract, the baselines."""

import json
import shutil

import numpy as np
import pytest
import torch

from keygen.errors import InvalidParameterError
from keygen.geometry.rotations import octahedral_group, yaw_matrix
from keygen.keypoints.baselines import FPSCanonicalBaseline
from keygen.keypoints.dataset import ScanSet, resample
from keygen.keypoints.extractor import KeypointExtractor, KeypointPrediction
from keygen.keypoints.models import CheckpointError
from keygen.keypoints.training import KeypointTrainConfig, TrainingError, consistency_error, train_keypoints


@pytest.fixture
def run(tiny_run):
    return tiny_run


def test_run_directory_layout_and_metrics(run):
    for name in ("canonicalizer", "detector", "detector_nocanon"):
        assert (run / name / "config.json").is_file() and (run / name / "model.safetensors").is_file()
    settings = json.loads((run / "inference.json").read_text())  # mugs: asymmetric, table poses
    assert settings["refine_iters"] == 2 and len(settings["template"]) == 6
    assert settings["axial_copies"] == 6 and settings["ensemble"] == 3  # completion: a smaller ensemble
    assert ScanSet.exists(run / "data") and len(ScanSet.load(run / "data")) == 6
    lines = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert {line["stage"] for line in lines} == {"canonicalizer", "detector", "detector_nocanon"}
    assert all(np.isfinite(line["loss"]) for line in lines)
    assert not list(run.rglob("*.pt")) and not list(run.rglob("*.pkl"))


def test_finished_run_is_reused_and_other_config_refused(run, tiny_config):
    before = (run / "metrics.jsonl").read_text()
    train_keypoints(tiny_config(), run, progress=False)
    assert (run / "metrics.jsonl").read_text() == before
    with pytest.raises(TrainingError, match="canon_steps"):
        train_keypoints(tiny_config(canon_steps=13), run)


def test_interrupted_stage_resumes_from_its_checkpoint(run, tmp_path, tiny_config):
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    # Simulate a crash during the ablation detector after its step-10 checkpoint.
    shutil.rmtree(copy / "detector_nocanon")
    (copy / "train_summary.json").unlink()
    from keygen.keypoints.checkpoint import save_state
    from keygen.keypoints.models import KeypointDetector

    model = KeypointDetector(6, width=32, hidden=16)
    save_state(copy / "state" / "detector_nocanon", model, torch.optim.Adam(model.parameters()), 10)
    train_keypoints(tiny_config(), copy, progress=False)
    lines = [json.loads(x) for x in (copy / "metrics.jsonl").read_text().splitlines()]
    resumed = [x["step"] for x in lines if x["stage"] == "detector_nocanon"][3:]
    assert resumed == [12]  # only steps 11-12 were run again and logged
    assert (copy / "detector_nocanon" / "model.safetensors").is_file()


def test_extractor_contract(run):
    ex = KeypointExtractor.load(run, ensemble=1, refine_iters=0)  # the paper's single pass
    assert (ex.category, ex.num_keypoints, ex.num_points) == ("mug", 6, 64)
    data = ScanSet.load(run / "data")
    cloud = data.scans[0].points[:500]
    one = ex(cloud)
    assert isinstance(one, KeypointPrediction)
    assert one.keypoints.shape == (6, 3) and one.keypoints.dtype == np.float32
    assert one.rotation.shape == (3, 3) and one.confidence.shape == () and 0 < one.confidence <= 1
    assert np.min(np.abs(octahedral_group() - one.rotation).max(axis=(1, 2))) < 1e-6
    again = ex(cloud.copy())
    np.testing.assert_array_equal(one.keypoints, again.keypoints)  # deterministic
    # convex combinations of the resampled input: inside its bounding box
    sub = resample(cloud, 64)
    assert (one.keypoints >= sub.min(0) - 1e-6).all() and (one.keypoints <= sub.max(0) + 1e-6).all()
    ragged = ex.batch([cloud, data.scans[1].points[:100], data.scans[2].points[:9]])
    assert (
        ragged.keypoints.shape == (3, 6, 3)
        and ragged.rotation.shape == (3, 3, 3)
        and ragged.confidence.shape == (3,)
    )
    np.testing.assert_allclose(ragged.keypoints[0], one.keypoints, atol=1e-6)
    stacked = ex(np.stack([cloud, cloud]))
    assert stacked.keypoints.shape == (2, 6, 3)
    for bad in (np.zeros((7, 3)), np.zeros((20, 2)), np.full((20, 3), np.nan)):
        with pytest.raises(InvalidParameterError):
            ex(bad)
    with pytest.raises(InvalidParameterError):
        ex.batch([])


def test_extractor_ablation_and_missing_runs(run, tmp_path):
    ab = KeypointExtractor.load(run, detector="detector_nocanon")
    pred = ab(ScanSet.load(run / "data").scans[0].points)
    np.testing.assert_array_equal(pred.rotation, np.eye(3))
    with pytest.raises(CheckpointError, match="train_config.json"):
        KeypointExtractor.load(tmp_path)
    (tmp_path / "config.json").write_text("{}")  # a policy run's layout
    with pytest.raises(CheckpointError, match="is a policy run.*keygen eval"):
        KeypointExtractor.load(tmp_path)


def test_fps_baseline_picks_input_points(run):
    ex = KeypointExtractor.load(run)
    base = FPSCanonicalBaseline(ex.canonicalizer, 6, 64)
    clouds = [s.points for s in ScanSet.load(run / "data").scans[:2]]
    kp, cls = base(clouds)
    assert kp.shape == (2, 6, 3) and cls.shape == (2,)
    for c, k in zip(clouds, kp, strict=True):
        assert np.min(np.linalg.norm(c[:, None] - k[None], axis=-1), axis=0).max() < 1e-6


def test_consistency_error_known_values():
    xa = torch.tensor([[[0.1, 0.0, 0.0], [0.0, 0.0, 0.1]]])
    eye = torch.eye(3).expand(1, 1, 3, 3)
    assert consistency_error(
        xa, xa + torch.tensor([0.0, 0.0, 0.1]), eye, torch.tensor([False])
    ).item() == pytest.approx(0.01)
    turned = xa @ torch.tensor(yaw_matrix(1.0), dtype=torch.float32).T
    assert consistency_error(xa, turned, eye, torch.tensor([False])).item() > 1e-3
    assert consistency_error(xa, turned, eye, torch.tensor([True])).item() == pytest.approx(0.0, abs=1e-10)
    flip = torch.tensor(octahedral_group()[[0, 1]], dtype=torch.float32)[None]  # identity, half-turn about x
    flipped = xa @ flip[0, 1].T
    assert consistency_error(xa, flipped, flip, torch.tensor([False])).item() == pytest.approx(0.0, abs=1e-10)


def test_config_validation_and_presets():
    assert (
        KeypointTrainConfig.preset("quick", "knife").canon_steps
        < KeypointTrainConfig.preset("default", "knife").canon_steps
    )
    for kwargs in (
        {"category": "cup"},
        {"category": "mug", "num_keypoints": 1},
        {"category": "mug", "pose_mode": "up"},
        {"category": "mug", "scans_per_instance": 1},
        {"category": "mug", "lr": -1.0},
        {"category": "mug", "spread_floor": 1.5},
        {"category": "mug", "canon_lr": 0.0},
    ):
        with pytest.raises(InvalidParameterError):
            KeypointTrainConfig(**kwargs)
    with pytest.raises(InvalidParameterError):
        KeypointTrainConfig.preset("slow", "mug")
    cfg = KeypointTrainConfig.preset("default", "bowl")
    assert KeypointTrainConfig.from_json(json.loads(json.dumps(cfg.to_json()))) == cfg


def test_knife_default_preset_departs_and_others_keep_the_shared_default():
    knife = KeypointTrainConfig.preset("default", "knife")
    assert knife.lambda_spread > 0 and 0 < knife.spread_floor <= 1 and knife.lambda_sep > 1
    assert knife.num_keypoints < KeypointTrainConfig(category="knife").num_keypoints  # six along the knife
    assert KeypointTrainConfig.preset("quick", "knife").num_keypoints == 10  # quick runs keep the shared K
    for category in ("mug", "bowl"):
        assert KeypointTrainConfig.preset("default", category) == KeypointTrainConfig(category=category)
    # An explicit override still wins over the category default.
    assert KeypointTrainConfig.preset("default", "knife", canon_steps=7).canon_steps == 7


def test_run_written_before_new_fields_is_still_reused(run, tmp_path, tiny_config):
    copy = tmp_path / "old"
    shutil.copytree(run, copy)
    config = json.loads((copy / "train_config.json").read_text())
    for key in ("lambda_spread", "spread_floor"):
        config.pop(key)  # as written before these fields existed
    (copy / "train_config.json").write_text(json.dumps(config))
    train_keypoints(tiny_config(), copy, progress=False)


def test_spread_term_trains_and_is_logged(tmp_path, tiny_config):
    torch.set_num_threads(1)
    out = tmp_path / "spread"
    cfg = tiny_config("knife", lambda_spread=10.0, spread_floor=0.5)
    train_keypoints(cfg, out, progress=False)
    lines = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    spread = [r["spread"] for r in lines if r["stage"] == "detector"]
    assert spread and all(np.isfinite(spread))
