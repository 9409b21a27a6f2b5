"""Keypoint networks: shapes, convex weights, frames, group membership, determinism, checkpoints."""

import json

import numpy as np
import pytest
import torch

from keygen.errors import InvalidParameterError
from keygen.geometry.rotations import octahedral_group
from keygen.keypoints.losses import keypoint_loss, symmetric_rotation_loss
from keygen.keypoints.models import (
    Canonicalizer,
    CheckpointError,
    KeypointDetector,
    PointNetEncoder,
    canonicalize,
    detect_keypoints,
    load_model,
    reproject,
    save_model,
)

GROUP = torch.tensor(octahedral_group().copy(), dtype=torch.float32)
SMALL = {"width": 64, "hidden": 32}


def _clouds(batch: int = 3, n: int = 128, seed: int = 0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    # An elongated box-like object 0.2 x 0.1 x 0.05 m, away from the origin.
    return torch.rand(batch, n, 3, generator=gen) * torch.tensor([0.2, 0.1, 0.05]) + torch.tensor(
        [0.5, -0.2, 0.1]
    )


def _model(cls, seed: int = 0, **kwargs):
    torch.manual_seed(seed)
    return cls(**SMALL, **kwargs)


def test_encoder_shapes_and_permutation_invariance():
    enc = _model(PointNetEncoder)
    x = _clouds()
    glob = enc(x)
    assert glob.shape == (3, 64)
    perm = torch.randperm(x.shape[1], generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(enc(x[:, perm]), glob)
    per_point = enc.point_features(x)
    assert per_point.shape == (3, 128, enc.point_dim) and enc.point_dim == 32 + 64
    torch.testing.assert_close(per_point[:, :, 32:], glob[:, None].expand(-1, 128, -1))


def test_detector_weights_are_convex_and_keypoints_inside_the_cloud():
    det = _model(KeypointDetector, num_keypoints=7)
    x = _clouds()
    kp, w = det(x)
    assert kp.shape == (3, 7, 3) and w.shape == (3, 7, 128)
    assert (w >= 0).all()
    torch.testing.assert_close(w.sum(-1), torch.ones(3, 7))
    torch.testing.assert_close(kp, w @ x)
    lo, hi = x.min(dim=1).values[:, None], x.max(dim=1).values[:, None]
    assert ((kp >= lo - 1e-6) & (kp <= hi + 1e-6)).all()


def test_detector_is_translation_equivariant():
    # Features see the centred cloud, so shifting the input shifts the keypoints by the same amount.
    det = _model(KeypointDetector)
    x = _clouds()
    shift = torch.tensor([0.3, -0.1, 0.2])
    kp, w = det(x)
    kp_shifted, w_shifted = det(x + shift)
    torch.testing.assert_close(w_shifted, w, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(kp_shifted, kp + shift, atol=1e-5, rtol=1e-4)


def test_canonicalize_then_reproject_is_identity_and_matches_column_convention():
    x = _clouds()
    R = GROUP[[4, 11, 20]]
    torch.testing.assert_close(reproject(canonicalize(x, R), R), x)
    # Row form of p_can = R^T p (column vectors), one sample at a time.
    for b in range(3):
        torch.testing.assert_close(canonicalize(x[b], R[b]), (R[b].T @ x[b].T).T)
        torch.testing.assert_close(reproject(x[b], R[b]), (R[b] @ x[b].T).T)
    with pytest.raises(InvalidParameterError, match="rotations for a batch"):
        canonicalize(x, R[:2])


def test_canonicalizer_predicts_a_group_element():
    can = _model(Canonicalizer)
    x = _clouds(batch=4)
    logits = can(x)
    assert logits.shape == (4, 24)
    R, index, confidence = can.predict(x)
    assert R.shape == (4, 3, 3) and index.shape == (4,) and index.dtype == torch.long
    torch.testing.assert_close(R, GROUP[index])
    torch.testing.assert_close(confidence, torch.softmax(logits, -1).max(-1).values)
    assert ((confidence > 0) & (confidence <= 1)).all()


def test_canonicalizer_ignores_position_and_optionally_scale():
    can = _model(Canonicalizer)
    x = _clouds()
    centred = x - x.mean(dim=1, keepdim=True)
    torch.testing.assert_close(can(centred * 2.0 + 1.0), can(x), atol=1e-5, rtol=1e-4)
    unscaled = _model(Canonicalizer, normalize_scale=False)
    assert not torch.allclose(unscaled(centred * 2.0), unscaled(centred))


def test_canonicalizer_only_accepts_the_octahedral_group():
    with pytest.raises(InvalidParameterError, match="24"):
        Canonicalizer(num_rotations=12)


def test_pipeline_and_a_training_step_reduce_the_losses():
    can, det = _model(Canonicalizer), _model(KeypointDetector, num_keypoints=5)
    x = _clouds(batch=2)
    kp_obs, R = detect_keypoints(can, det, x)
    assert kp_obs.shape == (2, 5, 3)
    lo, hi = x.min(dim=1).values[:, None], x.max(dim=1).values[:, None]
    assert ((kp_obs >= lo - 1e-6) & (kp_obs <= hi + 1e-6)).all()  # R keeps the hull: same cloud

    # A few optimiser steps on both losses, to show gradients reach every parameter.
    opt = torch.optim.Adam([*can.parameters(), *det.parameters()], lr=1e-3)
    first = None
    for _ in range(5):
        R_a, R_b = GROUP[[0, 5]], GROUP[[7, 2]]
        ca, cb = canonicalize(x, R_a), canonicalize(x, R_b)
        kp_a, _ = det(ca)
        kp_b, _ = det(cb)
        total, _ = keypoint_loss(kp_a, ca, R_a, kp_b, cb, R_b)
        total = total + symmetric_rotation_loss(can(x), [[0], [0, 1]])
        opt.zero_grad()
        total.backward()
        for p in [*can.parameters(), *det.parameters()]:
            assert p.grad is not None and torch.isfinite(p.grad).all()
        opt.step()
        first = total.item() if first is None else first
    assert total.item() < first


def test_same_seed_same_model():
    a, b, c = _model(KeypointDetector, 0), _model(KeypointDetector, 0), _model(KeypointDetector, 1)
    x = _clouds()
    torch.testing.assert_close(a(x)[0], b(x)[0], rtol=0, atol=0)
    assert not torch.allclose(a(x)[1], c(x)[1])


def test_parameter_counts_are_cpu_sized():
    for cls in (Canonicalizer, KeypointDetector):
        assert sum(p.numel() for p in cls().parameters()) < 300_000


@pytest.mark.parametrize("cls", [Canonicalizer, KeypointDetector, PointNetEncoder])
def test_save_load_round_trip_gives_identical_outputs(tmp_path, cls):
    model = _model(cls)
    x = _clouds()
    path = save_model(model, tmp_path / "ckpt")
    assert sorted(p.name for p in path.iterdir()) == ["config.json", "model.safetensors"]
    config = json.loads((path / "config.json").read_text())
    assert config == model.to_config() and config["type"] == cls.__name__
    loaded = load_model(path, expected=cls)
    assert type(loaded) is cls and loaded.to_config() == model.to_config()
    out, out_loaded = model(x), loaded(x)
    if isinstance(out, tuple):
        out, out_loaded = out[0], out_loaded[0]
    torch.testing.assert_close(out_loaded, out, rtol=0, atol=0)


def test_from_config_and_checkpoint_errors(tmp_path):
    det = _model(KeypointDetector, num_keypoints=4)
    assert KeypointDetector.from_config(det.to_config()).num_keypoints == 4
    with pytest.raises(CheckpointError, match="not a Canonicalizer"):
        Canonicalizer.from_config(det.to_config())
    with pytest.raises(CheckpointError, match="unknown"):
        KeypointDetector.from_config({**det.to_config(), "depth": 3})
    with pytest.raises(CheckpointError, match="missing"):
        load_model(tmp_path / "nothing")
    path = save_model(det, tmp_path / "det")
    with pytest.raises(CheckpointError, match="Canonicalizer was asked"):
        load_model(path, expected=Canonicalizer)
    config = json.loads((path / "config.json").read_text())
    (path / "config.json").write_text(json.dumps({**config, "num_keypoints": 6}))
    with pytest.raises(CheckpointError, match="do not fit"):
        load_model(path)


def test_bad_arguments_are_rejected():
    with pytest.raises(InvalidParameterError, match="num_keypoints"):
        KeypointDetector(num_keypoints=0)
    det = _model(KeypointDetector)
    with pytest.raises(InvalidParameterError, match=r"\(B, N, 3\)"):
        det(torch.zeros(128, 3))


def test_inputs_are_not_mutated():
    can, det = _model(Canonicalizer), _model(KeypointDetector)
    x = _clouds()
    before = x.clone()
    R = GROUP[[1, 2, 3]]
    R_before = R.clone()
    can(x)
    can.predict(x)
    det(x)
    reproject(canonicalize(x, R), R)
    detect_keypoints(can, det, x)
    assert torch.equal(x, before) and torch.equal(R, R_before)
    np.testing.assert_array_equal(octahedral_group(), GROUP.numpy())
