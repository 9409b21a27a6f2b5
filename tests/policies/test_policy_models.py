"""Networks of the policies: shapes, normaliser, losses and sampling, the batch left untouched, EMA."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from keygen.errors import InvalidParameterError
from keygen.policies import EMA, POLICY_NAMES, DiffusionPolicy, Normalizer, make_policy_config
from keygen.policies.normalizer import workspace_frame

SMALL = {"num_points": 64, "width": 32, "heads": 4, "depth": 2, "pc_dims": (16, 32), "pc_out": 32}


def small_config(name: str):
    kp = {"num_keypoints": 3, "num_objects": 2} if make_policy_config(name).use_keypoints else {}
    extra = {"unet_channels": (16, 32, 64)} if name == "dp3" else {}
    return make_policy_config(name, **SMALL, **kp, **extra)


def make_model(name: str) -> DiffusionPolicy:
    torch.manual_seed(0)
    model = DiffusionPolicy(small_config(name))
    rng = np.random.default_rng(0)
    model.normalizer.fit(rng.uniform(0, 1, (50, 10)), rng.uniform(0, 1, (50, 10)))
    return model


def make_inputs(model: DiffusionPolicy, b: int = 3, seed: int = 0) -> dict[str, torch.Tensor]:
    c, g = model.config, torch.Generator().manual_seed(seed)
    inputs = {
        "cloud": torch.rand(b, c.cloud_frames, c.num_points, 3, generator=g),
        "proprio": torch.rand(b, c.obs_horizon, 10, generator=g),
        "action": torch.rand(b, c.horizon, 10, generator=g),
    }
    if c.use_keypoints:
        inputs["keypoints"] = torch.rand(b, c.obs_horizon, c.num_keypoint_tokens, 3, generator=g)
    return inputs


@pytest.mark.parametrize("name", POLICY_NAMES)
def test_loss_and_prediction_shapes_and_no_mutation(name: str) -> None:
    model = make_model(name)
    inputs = make_inputs(model)
    before = {k: v.clone() for k, v in inputs.items()}
    loss = model.compute_loss(inputs, generator=torch.Generator().manual_seed(1))
    assert loss.shape == () and torch.isfinite(loss)
    loss.backward()
    assert all(p.grad is not None for p in model.noise_net.parameters())
    plan = model.eval().predict(inputs, generator=torch.Generator().manual_seed(2))
    assert plan.shape == (3, 16, 10) and torch.isfinite(plan).all()
    again = model.predict(inputs, generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close(plan, again)  # DDIM with the same initial noise is deterministic
    assert set(inputs) == set(before)
    for key in before:
        assert torch.equal(inputs[key], before[key]), key


def test_ddpm_sampling_and_step_count_checks() -> None:
    model = make_model("keygen_no_kp").eval()
    model.sampler = __import__("keygen.policies.diffusion", fromlist=["x"]).make_scheduler(
        model.config, "ddpm"
    )
    plan = model.predict(
        make_inputs(model, b=2), generator=torch.Generator().manual_seed(0), num_inference_steps=20
    )
    assert plan.shape == (2, 16, 10) and torch.isfinite(plan).all()
    with pytest.raises(InvalidParameterError, match="num_inference_steps"):
        model.predict(make_inputs(model), num_inference_steps=500)


def test_bad_inputs_name_what_was_expected() -> None:
    model = make_model("keygen")
    inputs = make_inputs(model)
    with pytest.raises(InvalidParameterError, match="keypoints"):
        model.compute_loss({k: v for k, v in inputs.items() if k != "keypoints"})
    with pytest.raises(InvalidParameterError, match="cloud"):
        model.compute_loss(inputs | {"cloud": torch.rand(3, 1, 10, 3)})
    with pytest.raises(InvalidParameterError, match="num_keypoints"):
        DiffusionPolicy(make_policy_config("keygen"))


def test_normalizer_maps_ranges_to_unit_interval_and_back() -> None:
    rng = np.random.default_rng(3)
    actions = rng.uniform(-2, 5, (100, 10))
    actions[:, 9] = 0.04  # a constant gripper must not divide by zero
    norm = Normalizer().fit(actions, actions)
    x = torch.as_tensor(actions, dtype=torch.float32)
    n = norm.normalize_action(x)
    assert torch.all(n[:, [0, 1, 2]].abs() <= 1 + 1e-5)
    torch.testing.assert_close(n[:, 3:9], x[:, 3:9])  # 6D columns untouched
    torch.testing.assert_close(n[:, 9], torch.zeros(100))
    torch.testing.assert_close(norm.unnormalize_action(n), x)
    centre, scale = workspace_frame()
    torch.testing.assert_close(
        norm.normalize_points(torch.tensor(centre, dtype=torch.float32)), torch.zeros(3)
    )
    assert scale > 0
    with pytest.raises(InvalidParameterError, match="never fitted"):
        Normalizer().normalize_action(x)
    with pytest.raises(InvalidParameterError, match="NaN"):
        Normalizer().fit(np.full((3, 10), np.nan), actions)


def test_ema_tracks_weights_with_warmup() -> None:
    model = make_model("keygen_no_kp")
    ema = EMA(model, decay=0.9)
    assert ema.current_decay(0) == pytest.approx(0.1) and ema.current_decay(10**6) == 0.9
    target = copy.deepcopy(model)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(1.0)
    ema.update(model, step=0)  # decay 0.1: 90% of the way to the new weights
    for e, old, new in zip(ema.model.parameters(), target.parameters(), model.parameters(), strict=True):
        torch.testing.assert_close(e, old + 0.9 * (new - old))
    assert not any(p.requires_grad for p in ema.model.parameters())


def test_dit_cached_query_work_matches_the_plain_forward() -> None:
    """Cross-attention keys / values and adaLN modulations cached per query change nothing."""
    model = make_model("keygen").eval()
    inputs = make_inputs(model, b=2)
    with torch.no_grad():
        for p in model.parameters():  # leave the zero init: every path must matter
            p.add_(0.05 * torch.randn_like(p))
        cond = model.encode(inputs)
        ctx = model.noise_net.context(cond)
        model.noise_net.precompute(ctx, torch.tensor([90, 45, 0]))
        x = torch.randn(2, 16, 10)
        for t in (90, 45, 0):
            plain = model.noise_net(x, torch.full((2,), t), cond)
            torch.testing.assert_close(model.noise_net(x, torch.tensor(t), ctx), plain, rtol=1e-5, atol=1e-5)
        assert set(ctx.modulations) == {90, 45, 0}


def test_point_max_pool_matches_amax_in_value_and_gradient() -> None:
    from keygen.policies.encoders import max_pool_points

    g = torch.Generator().manual_seed(0)
    x = torch.randn(3, 2, 50, 8, generator=g)
    a, b = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
    up = torch.randn(3, 2, 8, generator=g)
    pooled = max_pool_points(a)
    assert pooled.shape == (3, 2, 8)
    assert torch.equal(pooled, b.amax(dim=-2))
    pooled.backward(up)
    b.amax(dim=-2).backward(up)
    assert torch.equal(a.grad, b.grad)  # unique maxima: the gradient lands on the same points
    assert int((a.grad != 0).sum()) == 3 * 2 * 8


def _object_frame_model(name: str = "keygen") -> DiffusionPolicy:
    torch.manual_seed(0)
    model = DiffusionPolicy(small_config(name).with_updates(frame="object"))
    rng = np.random.default_rng(0)
    model.normalizer.fit(rng.uniform(-0.5, 0.5, (50, 10)), rng.uniform(-0.5, 0.5, (50, 10)))
    return model


@pytest.mark.parametrize("name", ["keygen", "keygen_no_kp"])
def test_object_frame_policy_trains_predicts_and_leaves_inputs_alone(name: str) -> None:
    model = _object_frame_model(name)
    inputs = make_inputs(model)
    before = {k: v.clone() for k, v in inputs.items()}
    loss = model.compute_loss(inputs, generator=torch.Generator().manual_seed(1))
    loss.backward()
    assert torch.isfinite(loss) and model.obs_encoder.origin[0].weight.grad is not None
    plan = model.eval().predict(inputs, generator=torch.Generator().manual_seed(2))
    assert plan.shape == (3, 16, 10) and torch.isfinite(plan).all()
    assert set(inputs) == set(before) and all(torch.equal(inputs[k], before[k]) for k in before)


def test_object_frame_moves_the_plan_with_the_scene_when_the_origin_input_is_silenced() -> None:
    # With the origin's own input zeroed, the network sees only relative positions: shifting the
    # whole scene (cloud, keypoints, proprioception) shifts the predicted positions by the same amount
    # and leaves rotations and the gripper as they were.
    model = _object_frame_model().eval()
    for p in model.obs_encoder.origin.parameters():
        torch.nn.init.zeros_(p)
    inputs = {k: v for k, v in make_inputs(model).items() if k != "action"}
    shift = torch.tensor([0.07, -0.04, 0.02])
    moved = {
        "cloud": inputs["cloud"] + shift,
        "keypoints": inputs["keypoints"] + shift,
        "proprio": torch.cat([inputs["proprio"][..., :3] + shift, inputs["proprio"][..., 3:]], dim=-1),
    }
    plan = model.predict(inputs, generator=torch.Generator().manual_seed(3))
    plan_moved = model.predict(moved, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(plan_moved[..., :3], plan[..., :3] + shift, atol=1e-5, rtol=0)
    torch.testing.assert_close(plan_moved[..., 3:], plan[..., 3:], atol=1e-5, rtol=0)


def test_object_frame_needs_the_dit_and_a_known_frame() -> None:
    with pytest.raises(InvalidParameterError, match="DiT"):
        make_policy_config("dp3", frame="object")
    with pytest.raises(InvalidParameterError, match="frame"):
        make_policy_config("keygen", frame="camera")
