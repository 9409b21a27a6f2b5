"""Tiny policy training configurations shared by the policy tests (a module, not a conftest, so that
module-level helpers can import it)."""

from __future__ import annotations

from keygen.policies import TrainConfig

# A policy small enough to train a few steps in well under a second on one core.
TINY_POLICY = {"num_points": 48, "width": 32, "depth": 2, "pc_dims": (16, 32), "pc_out": 32}


def tiny_train_config(
    policy: str, store, out, keypoints=None, *, steps: int = 5, model: dict | None = None, **kw
) -> TrainConfig:
    """The quick preset on :data:`TINY_POLICY`: ``steps`` steps of batch 8, logging every step,
    validating and checkpointing every ``min(steps, 5)``. ``model`` adds to or replaces the tiny
    policy's settings (DP3-style gets a smaller U-Net); other keywords replace training fields."""
    overrides = (
        dict(TINY_POLICY) | ({"unet_channels": (16, 32, 64)} if policy == "dp3" else {}) | (model or {})
    )
    every = min(steps, 5)
    base = dict(
        policy=policy,
        dataset=store,
        out=out,
        keypoints=keypoints,
        steps=steps,
        batch_size=8,
        val_every=every,
        ckpt_every=every,
        log_every=1,
        policy_overrides=overrides,
    )
    return TrainConfig.from_preset("quick", **(base | kw))


def tiny_model(policy: str = "keygen", **overrides):
    """A tiny DiT policy (4 keypoints, 32 points) with a fitted normaliser, in eval mode, seeded."""
    import numpy as np
    import torch

    from keygen.policies.config import make_policy_config
    from keygen.policies.diffusion import DiffusionPolicy

    torch.manual_seed(0)
    cfg = make_policy_config(
        policy, num_keypoints=4, num_objects=1, num_points=32, width=32, depth=2, heads=4,
        pc_dims=(16, 32), pc_out=32, **overrides,
    )  # fmt: skip
    model = DiffusionPolicy(cfg)
    model.normalizer.fit(np.random.default_rng(0).uniform(-0.5, 0.5, (50, 10)), np.zeros((50, 10)))
    return model.eval()


def with_all_weights_drawn(model):
    """``model`` with every parameter drawn from N(0, 0.2) (seeded by its size), in place. The DiT's
    output layers start at zero (adaLN-zero); drawn weights let the conditioning show in a prediction."""
    import torch

    with torch.no_grad():
        for param in model.parameters():
            param.normal_(0.0, 0.2, generator=torch.Generator().manual_seed(param.numel()))
    return model


def tiny_inputs(**extra):
    """One seeded observation for :func:`tiny_model`; ``extra`` entries (lists) become (1, n) tensors."""
    import torch

    g = torch.Generator().manual_seed(1)
    out = {
        "cloud": torch.rand((1, 1, 32, 3), generator=g),
        "proprio": torch.rand((1, 2, 10), generator=g),
        "keypoints": torch.rand((1, 2, 4, 3), generator=g),
    }
    return out | {key: torch.tensor([value]) for key, value in extra.items()}
