"""One trainer for every policy: data, normaliser, DDPM loss, EMA, validation, checkpoints, resume.

Run directory (``TrainConfig.out``)::

    config.json               policy + task + training config; ``finished``, ``step``, ``result``
    model.safetensors         EMA weights + normaliser (what ``load_runner`` uses)
    train_state.safetensors   raw weights, EMA, optimizer state, step: resume point
    metrics.jsonl             one line per log interval: step, loss, val_loss, lr, seconds
    keypoints/<category>/     copies of the keypoint runs' checkpoint files (self-contained run)
    keypoint_cache.npz        keypoints of every dataset step, keyed by dataset + extractor fingerprints,
                              and the dataset's episode boundaries

Per-step features (resampled clouds, keypoints) are computed once up front; a training step is then
fancy indexing plus the network. Batches and noise are drawn from generators seeded by
(seed, step), so a resumed run draws exactly what an uninterrupted one would have.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import MISSING, asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load_file, safe_open
from tqdm import tqdm

from keygen.data.store import EpisodeStore
from keygen.data.windows import train_val_split
from keygen.errors import InvalidParameterError
from keygen.optim_state import optimizer_tensors, prefixed, restore_optimizer, unprefixed
from keygen.policies import checkpoint as ckpt
from keygen.policies.config import POLICY_NAMES, make_policy_config
from keygen.policies.data import PolicyData, load_policy_data
from keygen.policies.diffusion import EMA, DiffusionPolicy

PRESETS: dict[str, dict[str, Any]] = {
    # ~1-2 min on 2 cores for a 20-episode dataset: a smoke run that already moves the loss.
    # lr: 1e-3 reached in 500 steps the plan error 3e-4 needed ~1100 steps for (docs/policies.md).
    "quick": {
        "steps": 300,
        "batch_size": 32,
        "lr": 1e-3,
        "val_every": 100,
        "ckpt_every": 100,
        "warmup_steps": 50,
    },
    # Sized for <= 20 minutes per policy per task on 2 cores (docs/policies.md has the measured step times).
    "default": {
        "steps": 2500,
        "batch_size": 64,
        "lr": 5e-4,
        "val_every": 500,
        "ckpt_every": 250,
        "warmup_steps": 200,
    },
}
METRICS_FILE = "metrics.jsonl"
VAL_SAMPLES = 256
# Fields that may change when a run is continued (the rest must match the run's config.json).
_RESUMABLE_CHANGES = {"steps", "val_every", "ckpt_every", "log_every", "device", "num_threads", "out"}


@dataclass
class TrainConfig:
    policy: str
    dataset: Path
    out: Path
    keypoints: dict[str, Path] | None = None  # category -> `keygen keypoints train` run directory
    steps: int = 2500
    batch_size: int = 64
    lr: float = 5e-4
    seed: int = 0
    val_fraction: float = 0.1
    val_every: int = 500
    ckpt_every: int = 250
    preset: str = "default"
    device: str = "cpu"
    weight_decay: float = 1e-4
    warmup_steps: int = 200
    log_every: int = 25
    grad_clip: float = 1.0
    num_threads: int | None = None  # torch threads while training (None: auto_threads())
    policy_overrides: dict[str, Any] = field(default_factory=dict)  # e.g. {"num_points": 128}
    max_episodes: int | None = None  # train on the dataset's first N episodes only (data-efficiency)
    # Std (metres) of a random offset added to each keypoint of each training window, the same over
    # the window's history: keypoints of an unseen instance sit a little elsewhere on its parts, and
    # one training instance alone never shows the network such a spread. 0 turns it off.
    keypoint_noise: float = 0.0
    # Std (metres) of a random offset added to the hand's position in the proprioception of each
    # training window, the same over its history, while the demonstrated actions stay put: a policy
    # that drifts a little off the demonstrations then sees states it was never shown, and this shows
    # it such states with the way back. 0 turns it off.
    proprio_noise: float = 0.0

    def __post_init__(self) -> None:
        self.dataset, self.out = Path(self.dataset), Path(self.out)
        if self.keypoints is not None:
            self.keypoints = {str(k): Path(v) for k, v in self.keypoints.items()}
        if self.policy not in POLICY_NAMES:
            raise InvalidParameterError(f"policy must be one of {POLICY_NAMES}, got {self.policy!r}")
        if self.preset not in PRESETS:
            raise InvalidParameterError(f"preset must be one of {sorted(PRESETS)}, got {self.preset!r}")
        for name in ("steps", "batch_size", "val_every", "ckpt_every", "log_every"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise InvalidParameterError(f"{name} must be a positive int, got {value!r}")
        if not self.lr > 0 or self.weight_decay < 0 or self.warmup_steps < 0 or not self.grad_clip > 0:
            raise InvalidParameterError("lr and grad_clip must be > 0, weight_decay and warmup_steps >= 0")
        if not 0.0 <= self.val_fraction < 1.0:
            raise InvalidParameterError(f"val_fraction must be in [0, 1), got {self.val_fraction}")
        if self.max_episodes is not None and (
            isinstance(self.max_episodes, bool)
            or not isinstance(self.max_episodes, int)
            or self.max_episodes < 1
        ):
            raise InvalidParameterError(
                f"max_episodes must be a positive int or None, got {self.max_episodes!r}"
            )
        for name in ("keypoint_noise", "proprio_noise"):
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, (int, float)) and 0.0 <= value < 0.1):
                raise InvalidParameterError(f"{name} is a std in metres in [0, 0.1), got {value!r}")
            setattr(self, name, float(value))
        policy_config = make_policy_config(self.policy, **self.policy_overrides)  # validates early
        if self.keypoint_noise > 0 and not policy_config.use_keypoints:
            raise InvalidParameterError(
                f"keypoint_noise needs a policy with keypoint inputs; {self.policy!r} has none"
            )

    @classmethod
    def from_preset(cls, preset: str = "default", **overrides: Any) -> TrainConfig:
        if preset not in PRESETS:
            raise InvalidParameterError(f"preset must be one of {sorted(PRESETS)}, got {preset!r}")
        values = {k: v for k, v in overrides.items() if v is not None}
        return cls(**(PRESETS[preset] | {"preset": preset} | values))

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data["dataset"], data["out"] = str(self.dataset), str(self.out)
        data["keypoints"] = None if self.keypoints is None else {k: str(v) for k, v in self.keypoints.items()}
        return data


def auto_threads() -> int:
    """Torch threads for training: the cores not already busy, at least one.

    OpenMP threads that wait for each other on an oversubscribed machine make small models many
    times slower than one thread (measured here: 3 s instead of 0.3 s per step with 2 threads on
    2 cores at load 7), while on idle cores more threads help.
    """
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    busy = os.getloadavg()[0] if hasattr(os, "getloadavg") else 0.0
    return max(1, min(cores, int(cores - busy + 0.5)))


def lr_at(config: TrainConfig, step: int) -> float:
    """Linear warm-up, then cosine decay to 10% of the peak."""
    if step < config.warmup_steps:
        return config.lr * (step + 1) / config.warmup_steps
    progress = (step - config.warmup_steps) / max(1, config.steps - config.warmup_steps)
    return config.lr * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * min(1.0, progress))))


def _check_compatible(run_dir: Path, config: TrainConfig) -> dict[str, Any]:
    meta = ckpt.read_config(run_dir)
    # A field added after the run was written counts as its default, so older runs still resume.
    defaults = {f.name: f.default for f in fields(TrainConfig) if f.default is not MISSING}
    old = defaults | meta["train"]
    new = json.loads(json.dumps(config.to_dict()))  # tuples -> lists, as stored
    diff = sorted(
        k for k in {f.name for f in fields(TrainConfig)} - _RESUMABLE_CHANGES if old.get(k) != new.get(k)
    )
    if diff:
        changes = ", ".join(f"{k}: {old.get(k)!r} -> {new.get(k)!r}" for k in diff)
        raise InvalidParameterError(
            f"{run_dir} holds a run with a different configuration ({changes}); choose a new --out to "
            f"train afresh"
        )
    return meta


def _save_state(run_dir: Path, model, ema: EMA, opt, step: int, seconds: float) -> None:
    tensors = prefixed(model.state_dict(), "model.") | prefixed(ema.model.state_dict(), "ema.")
    opt_tensors, groups = optimizer_tensors(opt, "opt", ".")
    meta = {"step": str(step), "seconds": f"{seconds:.3f}", "param_groups": json.dumps(groups)}
    ckpt.save_tensors(run_dir / ckpt.STATE_FILE, tensors | opt_tensors, meta)
    ckpt.save_model(run_dir, ema.model)


def _load_state(run_dir: Path, model, ema: EMA, opt) -> tuple[int, float]:
    path = run_dir / ckpt.STATE_FILE
    tensors = load_file(str(path))
    with safe_open(str(path), framework="pt") as f:
        meta = f.metadata()
    model.load_state_dict(unprefixed(tensors, "model."))
    ema.model.load_state_dict(unprefixed(tensors, "ema."))
    restore_optimizer(opt, tensors, json.loads(meta["param_groups"]), "opt", ".")
    return int(meta["step"]), float(meta["seconds"])


def _trim_metrics(path: Path, step: int) -> None:
    """Drop metric lines past the resume point (they would be logged again)."""
    if path.is_file():
        lines = [ln for ln in path.read_text().splitlines() if ln.strip() and json.loads(ln)["step"] <= step]
        path.write_text("".join(ln + "\n" for ln in lines))


def perturb_keypoints(
    batch: dict[str, torch.Tensor], rng: np.random.Generator, std: float
) -> dict[str, torch.Tensor]:
    """A copy of ``batch`` whose keypoints (B, H, M, 3) are moved by one Gaussian offset per window
    and keypoint, shared by the window's history frames (a keypoint that sits elsewhere on an unseen
    instance sits there at every step, so the motion the history shows is kept)."""
    keypoints = batch.get("keypoints")
    if std == 0.0 or keypoints is None:
        return batch
    b, _, m, _ = keypoints.shape
    offset = torch.from_numpy(rng.normal(0.0, std, size=(b, 1, m, 3)).astype(np.float32))
    return dict(batch, keypoints=keypoints + offset.to(keypoints.device, keypoints.dtype))


def perturb_proprio(
    batch: dict[str, torch.Tensor], rng: np.random.Generator, std: float
) -> dict[str, torch.Tensor]:
    """A copy of ``batch`` whose proprioceptive hand positions (B, H, :3) are moved by one Gaussian
    offset per window, shared by its history frames; rotation, gripper and the actions are kept, so
    the demonstrated actions lead back from the displaced hand."""
    if std == 0.0:
        return batch
    proprio = batch["proprio"]
    offset = torch.zeros((proprio.shape[0], 1, proprio.shape[-1]), dtype=proprio.dtype)
    offset[..., :3] = torch.from_numpy(rng.normal(0.0, std, size=(proprio.shape[0], 1, 3)))
    return dict(batch, proprio=proprio + offset.to(proprio.device))


@torch.no_grad()
def validation_loss(
    model: DiffusionPolicy, data: PolicyData, samples: np.ndarray, seed: int, device: str
) -> float | None:
    """Mean noise loss on fixed validation samples with fixed noise: comparable across steps."""
    if len(samples) == 0:
        return None
    gen = torch.Generator().manual_seed(seed + 7919)
    total = 0.0
    for start in range(0, len(samples), 64):
        chunk = samples[start : start + 64]
        batch = {k: v.to(device) for k, v in data.batch(chunk).items()}
        total += float(model.compute_loss(batch, generator=gen)) * len(chunk)
    return total / len(samples)


def train_policy(config: TrainConfig, progress: bool = True) -> Path:
    """Train (or resume, or reuse) the policy run ``config.out``; returns the run directory."""
    threads = torch.get_num_threads()
    torch.set_num_threads(config.num_threads or auto_threads())
    try:
        return _train(config, progress)
    finally:
        torch.set_num_threads(threads)


def _train(config: TrainConfig, progress: bool) -> Path:
    run_dir = config.out
    meta = _check_compatible(run_dir, config) if (run_dir / ckpt.CONFIG_FILE).is_file() else None
    if meta is not None and meta.get("finished") and meta.get("step", 0) >= config.steps:
        return run_dir  # a finished run is reused
    store = EpisodeStore(config.dataset, mode="r", max_episodes=config.max_episodes)
    data = load_policy_data(store, config, run_dir, progress)
    policy_cfg = data.policy_config
    if meta is None:
        run_dir.mkdir(parents=True, exist_ok=True)
        meta = ckpt.make_run_config(policy_cfg, data.task, list(data.categories), config.to_dict())
        ckpt.write_json(run_dir / ckpt.CONFIG_FILE, meta)
    meta["train"] = config.to_dict()

    train_eps, val_eps = train_val_split(store, config.val_fraction, config.seed)
    train_idx, val_idx = data.samples(train_eps), data.samples(val_eps)
    val_idx = val_idx[np.random.default_rng(config.seed).permutation(len(val_idx))[:VAL_SAMPLES]]
    torch.manual_seed(config.seed)  # the initial weights
    model = DiffusionPolicy(policy_cfg)
    model.normalizer.fit(*data.fit_arrays(train_eps))
    model.to(config.device)
    ema = EMA(model, policy_cfg.ema_decay)
    opt = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    start, seconds = 0, 0.0
    if (run_dir / ckpt.STATE_FILE).is_file():
        start, seconds = _load_state(run_dir, model, ema, opt)
    _trim_metrics(run_dir / METRICS_FILE, start)

    bar = tqdm(
        total=config.steps, initial=start, desc=f"train {config.policy}", unit="step", disable=not progress
    )
    losses: list[float] = []
    last_loss = last_val = None
    t0 = time.perf_counter() - seconds
    model.train()
    with (run_dir / METRICS_FILE).open("a") as metrics:
        for step in range(start, config.steps):
            rng = np.random.default_rng([config.seed, step])
            batch = data.batch(train_idx[rng.integers(len(train_idx), size=config.batch_size)])
            batch = perturb_keypoints(batch, rng, config.keypoint_noise)  # validation stays clean
            batch = perturb_proprio(batch, rng, config.proprio_noise)
            batch = {k: v.to(config.device) for k, v in batch.items()}
            gen = torch.Generator().manual_seed(config.seed * 1_000_003 + step)
            for group in opt.param_groups:
                group["lr"] = lr_at(config, step)
            loss = model.compute_loss(batch, generator=gen)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
            opt.step()
            ema.update(model, step)
            losses.append(loss.item())
            done = step + 1
            val = None
            if done % config.val_every == 0 or done == config.steps:
                val = last_val = validation_loss(ema.model, data, val_idx, config.seed, config.device)
            if done % config.log_every == 0 or val is not None or done == config.steps:
                last_loss = float(np.mean(losses))
                row = {
                    "step": done,
                    "loss": last_loss,
                    "val_loss": val,
                    "lr": lr_at(config, step),
                    "seconds": round(time.perf_counter() - t0, 2),
                }
                metrics.write(json.dumps(row) + "\n")
                metrics.flush()
                losses.clear()
                bar.set_postfix(loss=f"{last_loss:.4f}", val="-" if last_val is None else f"{last_val:.4f}")
            if done % config.ckpt_every == 0 or done == config.steps:
                _save_state(run_dir, model, ema, opt, done, time.perf_counter() - t0)
                meta["step"] = done
                ckpt.write_json(run_dir / ckpt.CONFIG_FILE, meta)
            bar.update(1)
    bar.close()
    if last_loss is None:  # resumed exactly at the end: report the last logged values
        rows = [json.loads(ln) for ln in (run_dir / METRICS_FILE).read_text().splitlines() if ln.strip()]
        last_loss = rows[-1]["loss"] if rows else None
        last_val = next((r["val_loss"] for r in reversed(rows) if r["val_loss"] is not None), None)
    meta.update(finished=True, step=config.steps)
    meta["result"] = {
        "final_loss": last_loss,
        "val_loss": last_val,
        "seconds": round(time.perf_counter() - t0, 1),
        "train_episodes": len(train_eps),
        "val_episodes": len(val_eps),
    }
    ckpt.write_json(run_dir / ckpt.CONFIG_FILE, meta)
    return run_dir
