"""Test-time refinements: the closed-form yaw fit, the rotation refinement, settings, and the extractor."""

import json
import shutil

import numpy as np
import pytest
import torch

from keygen.errors import InvalidParameterError
from keygen.geometry.rotations import axis_angle_to_matrix, octahedral_group, yaw_matrix
from keygen.keypoints.extractor import KeypointExtractor
from keygen.keypoints.refine import INFERENCE_FILE, InferenceSettings, refine_rotation, yaw_about_axis
from keygen.keypoints.training import train_keypoints


@pytest.mark.parametrize("axis", [(0, 0, 1), (1, 0, 0), (0.6, 0.0, 0.8)])
@pytest.mark.parametrize("angle", [0.0, 0.4, -2.5])
def test_yaw_about_axis_recovers_a_known_rotation(axis, angle):
    rng = np.random.default_rng(0)
    p = rng.normal(size=(2, 7, 3))
    R = axis_angle_to_matrix(np.asarray(axis, float) / np.linalg.norm(axis), angle)
    q = p @ R.T + rng.normal(size=(1, 1, 3))  # turned and shifted: the fit centres both sets
    a = torch.tensor([axis, axis], dtype=torch.float64)
    fit = yaw_about_axis(torch.from_numpy(p), torch.from_numpy(q), a).numpy()
    np.testing.assert_allclose(fit, np.stack([R, R]), atol=1e-9)


def test_yaw_about_axis_is_the_least_squares_angle_under_noise():
    rng = np.random.default_rng(1)
    p = rng.normal(size=(1, 9, 3))
    q = p @ yaw_matrix(0.7).T + 0.05 * rng.normal(size=(1, 9, 3))
    z = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    fit = yaw_about_axis(torch.from_numpy(p), torch.from_numpy(q), z).numpy()[0]
    cost = lambda R: float(np.sum(((p[0] - p[0].mean(0)) @ R.T - (q[0] - q[0].mean(0))) ** 2))  # noqa: E731
    best = min(cost(yaw_matrix(t)) for t in np.linspace(-np.pi, np.pi, 3601))
    assert cost(fit) <= best + 1e-9


def _pick_points(x, R):
    """An exactly equivariant 'detector': fixed input points (B, m, K, 3), whatever R is."""
    return x[:, :, [0, 3, 5, 8]]


@pytest.mark.parametrize("tilt", [0, 4])  # 4: a group element that maps the canonical -y axis up
def test_refinement_removes_a_yaw_residual_in_one_round(tilt):
    rng = np.random.default_rng(2)
    canonical = rng.normal(size=(10, 3))
    G = octahedral_group()[tilt]
    true = yaw_matrix(0.6) @ G  # canonical -> observation: the classifier's G, 0.6 rad of yaw left over
    x = torch.from_numpy((canonical @ true.T)[None, None])  # (1, 1, 10, 3)
    template = canonical[[0, 3, 5, 8]]
    settings = InferenceSettings(1, 1, template)
    R0 = torch.from_numpy(G[None].copy())
    R = refine_rotation(_pick_points, x, R0, _pick_points(x, R0), settings, 1).numpy()[0]
    np.testing.assert_allclose(R, true, atol=1e-9)


def test_settings_round_trip_and_errors(tmp_path):
    s = InferenceSettings(4, 2, np.arange(15.0).reshape(5, 3))
    s.save(tmp_path)
    back = InferenceSettings.load(tmp_path)
    assert (back.ensemble, back.refine_iters, back.up) == (4, 2, (0.0, 0.0, 1.0))
    np.testing.assert_allclose(back.template.mean(0), 0.0, atol=1e-12)  # stored centred
    assert InferenceSettings.load(tmp_path / "missing") is None
    assert s.replace(refine_iters=0).refine_iters == 0 and s.replace(ensemble=1).ensemble == 1
    for bad in (dict(ensemble=0), dict(refine_iters=-1), dict(refine_iters=1, template=None)):
        with pytest.raises(InvalidParameterError):
            InferenceSettings(**(dict(ensemble=1, refine_iters=0, template=np.zeros((5, 3))) | bad))
    with pytest.raises(InvalidParameterError, match="template"):
        InferenceSettings(1, 0, np.zeros((5, 2)))
    with pytest.raises(InvalidParameterError, match="up"):
        InferenceSettings(1, 0, None, (0.0, 0.0, 2.0))
    (tmp_path / INFERENCE_FILE).write_text(json.dumps({"ensemble": 2, "oops": 1}))
    with pytest.raises(InvalidParameterError, match="oops"):
        InferenceSettings.load(tmp_path)


@pytest.fixture
def run(tiny_run):
    return tiny_run


def test_refined_ensemble_extractor_contract(run):
    from keygen.keypoints.dataset import ScanSet

    # a mug run: axial completion on, with a smaller ensemble (completion is tested on its own below)
    assert KeypointExtractor.load(run).settings.axial_copies == 6
    ex = KeypointExtractor.load(run, axial_copies=0)
    assert (ex.settings.ensemble, ex.settings.refine_iters) == (3, 2)
    cloud = ScanSet.load(run / "data").scans[0].points
    pred = ex(cloud)
    np.testing.assert_array_equal(pred.keypoints, ex(cloud.copy()).keypoints)  # seeded: deterministic
    # means of convex combinations of input points: inside the input's bounding box
    assert (pred.keypoints >= cloud.min(0) - 1e-6).all() and (pred.keypoints <= cloud.max(0) + 1e-6).all()
    # the yaw fix turns about the up axis only: the label's up mapping is kept, R stays a rotation
    G = octahedral_group()[int(pred.label)]
    np.testing.assert_allclose(pred.rotation @ pred.rotation.T, np.eye(3), atol=1e-5)
    np.testing.assert_allclose(pred.rotation.T @ [0, 0, 1], G.T @ [0, 0, 1], atol=1e-5)
    batch = ex.batch([cloud, cloud[:50]])
    np.testing.assert_allclose(batch.keypoints[0], pred.keypoints, atol=1e-5)
    single = KeypointExtractor.load(run, ensemble=1, refine_iters=0)(cloud)
    np.testing.assert_allclose(single.rotation, G, atol=1e-6)  # the paper's pass: an exact group element
    with pytest.raises(InvalidParameterError, match="canonicaliser"):
        KeypointExtractor(ex.category, None, ex.detector, ex.num_points, settings=ex.settings)


def test_old_runs_gain_settings_when_their_command_is_rerun(run, tmp_path, tiny_config):
    run = shutil.copytree(run, tmp_path / "run")
    (run / INFERENCE_FILE).unlink()
    assert KeypointExtractor.load(run).settings.ensemble == 1  # no file: the single pass
    train_keypoints(tiny_config(), run, progress=False)
    assert KeypointExtractor.load(run).settings.refine_iters == 2


def test_axial_completion_is_an_inference_setting(run):
    from keygen.keypoints.dataset import ScanSet

    cloud = ScanSet.load(run / "data").scans[0].points
    plain = KeypointExtractor.load(run, axial_copies=0)
    completed = KeypointExtractor.load(run, axial_copies=6)
    assert completed.settings.axial_copies == 6 and plain.settings.axial_copies == 0
    a, b = plain(cloud), completed(cloud)
    assert b.keypoints.shape == a.keypoints.shape and np.isfinite(b.keypoints).all()
    np.testing.assert_array_equal(b.keypoints, completed(cloud.copy()).keypoints)  # still deterministic
    # turned copies stay within the body's radius about its axis: inside the input's height range
    assert (b.keypoints[:, 2] >= cloud[:, 2].min() - 1e-6).all()
    assert (b.keypoints[:, 2] <= cloud[:, 2].max() + 1e-6).all()
