"""The diffusion policy: observation encoder + noise network + diffusers scheduler, and EMA weights.

Training (paper, "Diffusion Process"): a clean normalised trajectory a0 (B, T, 10), a step
n ~ U{0..N-1}, noise eps; the network predicts eps from sqrt(abar_n) a0 + sqrt(1 - abar_n) eps and
the loss is the mean squared error. Sampling starts from Gaussian noise and runs the scheduler's
update (DDIM by default, 10 steps; DDPM available) with the observation encoded once per query.

Model inputs are dicts of tensors built by ``keygen.policies.features``, in world units:
``cloud`` (B, F, P, 3) (the latest F = cloud_frames of the history), ``proprio`` (B, H, 10),
``keypoints`` (B, H, M, 3) when the policy uses them, ``target`` (B, 5) for a target token
(``keygen.policies.target_token``: position 3, half extents 2), ``base`` (B, 4) for the robot-base
input (``keygen.policies.robot_base``: position x, y in metres, heading cos, sin), and ``action``
(B, T, 10) for the loss.
Nothing is modified in place.
"""

from __future__ import annotations

import copy

import torch
from diffusers import DDIMScheduler, DDPMScheduler
from torch import nn

from keygen.errors import InvalidParameterError
from keygen.policies.coherence import check_samples
from keygen.policies.config import ACTION_DIM, PolicyConfig
from keygen.policies.dit import DiTNoiseNet
from keygen.policies.encoders import GlobalObsEncoder, TokenObsEncoder
from keygen.policies.normalizer import Normalizer
from keygen.policies.robot_base import BASE_DIM
from keygen.policies.target_token import TARGET_DIM
from keygen.policies.unet1d import ConditionalUnet1D


def make_scheduler(config: PolicyConfig, kind: str | None = None) -> DDPMScheduler | DDIMScheduler:
    kind = kind or config.scheduler
    common = dict(
        num_train_timesteps=config.train_timesteps,
        beta_schedule=config.beta_schedule,
        clip_sample=True,  # normalised actions live in [-1, 1]
        prediction_type="epsilon",
    )
    if kind == "ddim":
        return DDIMScheduler(**common, set_alpha_to_one=True, steps_offset=0)
    if kind == "ddpm":
        return DDPMScheduler(**common, variance_type="fixed_small")
    raise InvalidParameterError(f"scheduler must be 'ddim' or 'ddpm', got {kind!r}")


def shift_positions(x: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
    """(B, L, 10) actions or proprioception with ``offset`` (B, 3) added to the position columns."""
    return torch.cat([x[..., :3] + offset[:, None], x[..., 3:]], dim=-1)


def _repeat_batch(cond, n: int):
    """The encoder's conditioning (a tensor, or a tuple of tensors) with each batch row repeated ``n``
    times in place."""
    if isinstance(cond, torch.Tensor):
        return cond.repeat_interleave(n, dim=0)
    return type(cond)(_repeat_batch(c, n) for c in cond)


class DiffusionPolicy(nn.Module):
    def __init__(self, config: PolicyConfig):
        super().__init__()
        if config.use_keypoints and config.num_keypoint_tokens == 0:
            raise InvalidParameterError(
                f"policy {config.name!r} uses keypoints but its config has num_keypoints="
                f"{config.num_keypoints}, num_objects={config.num_objects}; set them from the task's "
                f"keypoint extractors"
            )
        self.config = config
        self.normalizer = Normalizer()
        if config.backbone == "dit":
            self.obs_encoder: nn.Module = TokenObsEncoder(config)
            self.noise_net: nn.Module = DiTNoiseNet(config)
        else:
            self.obs_encoder = GlobalObsEncoder(config)
            self.noise_net = ConditionalUnet1D(config, self.obs_encoder.out_dim)
        self.train_scheduler = make_scheduler(config, "ddpm")
        self.sampler = make_scheduler(config)

    # ------------------------------------------------------------------------------------ inputs
    def _check_inputs(self, inputs: dict[str, torch.Tensor], need_action: bool) -> None:
        c = self.config
        want = {"cloud": (c.cloud_frames, c.num_points, 3), "proprio": (c.obs_horizon, 10)}
        if c.use_keypoints:
            want["keypoints"] = (c.obs_horizon, c.num_keypoint_tokens, 3)
        if c.target_token:
            want["target"] = (TARGET_DIM,)
        if c.robot_base:
            want["base"] = (BASE_DIM,)
        if need_action:
            want["action"] = (c.horizon, ACTION_DIM)
        for key, shape in want.items():
            if key not in inputs:
                raise InvalidParameterError(
                    f"policy {c.name!r} needs input {key!r}; got keys {sorted(inputs)}"
                )
            got = tuple(inputs[key].shape[1:])
            if got != shape:
                raise InvalidParameterError(
                    f"input {key!r} must be (B, {', '.join(map(str, shape))}), got {tuple(inputs[key].shape)}"
                )

    def frame_origin(self, inputs: dict[str, torch.Tensor]) -> torch.Tensor | None:
        """(B, 3) origin of the policy's frame in world units: the centroid of the latest cloud for
        ``frame="object"``, None for ``"world"``."""
        if self.config.frame == "world":
            return None
        return inputs["cloud"][:, -1].mean(dim=1)

    @staticmethod
    def to_frame(inputs: dict[str, torch.Tensor], origin: torch.Tensor | None) -> dict[str, torch.Tensor]:
        """A new dict with every position made relative to ``origin`` (B, 3), which it adds as
        ``"origin"``; rotations and the gripper are unchanged. ``origin=None``: ``inputs`` itself."""
        if origin is None:
            return inputs
        out = dict(inputs, origin=origin, cloud=inputs["cloud"] - origin[:, None, None])
        if "keypoints" in inputs:
            out["keypoints"] = inputs["keypoints"] - origin[:, None, None]
        if "target" in inputs:
            out["target"] = torch.cat([inputs["target"][:, :3] - origin, inputs["target"][:, 3:]], dim=-1)
        if "base" in inputs:
            out["base"] = torch.cat([inputs["base"][:, :2] - origin[:, :2], inputs["base"][:, 2:]], dim=-1)
        for key in ("proprio", "action"):
            if key in inputs:
                out[key] = shift_positions(inputs[key], -origin)
        return out

    def encode(self, inputs: dict[str, torch.Tensor]):
        """Normalise the observation (already in the policy's frame) and encode it: conditioning
        for the noise network."""
        norm = self.normalizer
        points = norm.normalize_offsets if "origin" in inputs else norm.normalize_points
        obs = {
            "cloud": points(inputs["cloud"]),
            "proprio": norm.normalize_proprio(inputs["proprio"]),
        }
        if self.config.use_keypoints:
            obs["keypoints"] = points(inputs["keypoints"])
        if self.config.target_token:
            target = inputs["target"]
            # Position as a point, half extents as lengths (same scale, no offset).
            obs["target"] = torch.cat([points(target[:, :3]), norm.normalize_offsets(target[:, 3:])], dim=-1)
        if self.config.robot_base:
            # Metres and a unit vector as they are: the base lies 0.3-0.9 m from the object, well
            # outside the cloud whose spread the point normaliser is fitted on.
            obs["base"] = inputs["base"]
        if "origin" in inputs:
            obs["origin"] = norm.normalize_points(inputs["origin"])
        return self.obs_encoder(obs)

    # ---------------------------------------------------------------------------------- training
    def compute_loss(
        self, inputs: dict[str, torch.Tensor], generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """The l2 noise-prediction loss of one batch (mean over batch, horizon and action dims)."""
        self._check_inputs(inputs, need_action=True)
        inputs = self.to_frame(inputs, self.frame_origin(inputs))
        a0 = self.normalizer.normalize_action(inputs["action"])  # (B, T, 10)
        b = a0.shape[0]
        noise = torch.randn(a0.shape, generator=generator, device=a0.device)
        steps = torch.randint(0, self.config.train_timesteps, (b,), generator=generator, device=a0.device)
        noisy = self.train_scheduler.add_noise(a0, noise, steps)
        pred = self.noise_net(noisy, steps, self.encode(inputs))
        return torch.mean((pred - noise) ** 2)

    # ---------------------------------------------------------------------------------- sampling
    @torch.no_grad()
    def predict(
        self,
        inputs: dict[str, torch.Tensor],
        generator: torch.Generator | None = None,
        num_inference_steps: int | None = None,
        num_samples: int = 1,
    ) -> torch.Tensor:
        """Sample action trajectories (B, T, 10) in world units; with ``num_samples`` > 1, that many per
        observation, (B * num_samples, T, 10) with each observation's samples consecutive. The
        observation is encoded once whatever the number of samples."""
        self._check_inputs(inputs, need_action=False)
        check_samples(num_samples, "num_samples")
        steps = num_inference_steps or self.config.inference_steps
        if not 1 <= steps <= self.config.train_timesteps:
            raise InvalidParameterError(
                f"num_inference_steps must be in [1, {self.config.train_timesteps}], got {steps}"
            )
        device = inputs["proprio"].device
        self.sampler.set_timesteps(steps)
        origin = self.frame_origin(inputs)
        cond = self.encode(self.to_frame(inputs, origin))
        if num_samples > 1:
            cond = _repeat_batch(cond, num_samples)
            origin = None if origin is None else origin.repeat_interleave(num_samples, dim=0)
        if isinstance(self.noise_net, DiTNoiseNet):
            # Observation-only work, once per query: cross-attention keys / values, adaLN modulations.
            cond = self.noise_net.context(cond)
            self.noise_net.precompute(cond, self.sampler.timesteps.to(device))
        b = inputs["proprio"].shape[0] * num_samples
        x = torch.randn((b, self.config.horizon, ACTION_DIM), generator=generator, device=device)
        for t in self.sampler.timesteps:
            eps = self.noise_net(x, t.to(x.device), cond)
            x = self.sampler.step(eps, t, x, generator=generator).prev_sample
        actions = self.normalizer.unnormalize_action(x)
        return actions if origin is None else shift_positions(actions, origin)  # back to the world frame


class EMA:
    """Exponential moving average of a model's weights, with the usual warm-up of the decay
    (min(decay, (1 + step) / (10 + step))) so early averages do not cling to random weights."""

    def __init__(self, model: nn.Module, decay: float):
        self.decay = decay
        self.model = copy.deepcopy(model).eval().requires_grad_(False)

    def current_decay(self, step: int) -> float:
        return min(self.decay, (1 + step) / (10 + step))

    @torch.no_grad()
    def update(self, model: nn.Module, step: int) -> None:
        d = self.current_decay(step)
        for ema_p, p in zip(self.model.parameters(), model.parameters(), strict=True):
            ema_p.lerp_(p.detach(), 1.0 - d)
        for ema_b, b in zip(self.model.buffers(), model.buffers(), strict=True):
            ema_b.copy_(b)  # normaliser statistics are copied, not averaged
