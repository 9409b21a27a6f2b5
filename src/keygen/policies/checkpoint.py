"""Policy checkpoints: a directory with ``config.json`` and ``model.safetensors`` (never pickle).

``config.json`` holds the policy config, the task, the keypoint categories (their checkpoints are
copied under ``keypoints/<category>/``) and the training config; ``model.safetensors`` the EMA
weights with the normaliser's statistics (buffers). ``train_state.safetensors`` (written during
training) adds the raw weights, the optimizer state and the step, for resuming. Every file is
written to a temporary sibling and renamed, so an interruption never leaves half a file.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from keygen.atomic import atomic_write, atomic_write_json
from keygen.errors import KeyGenError
from keygen.policies.config import PolicyConfig
from keygen.policies.diffusion import DiffusionPolicy

CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"
STATE_FILE = "train_state.safetensors"
KEYPOINTS_DIR = "keypoints"
FORMAT = "keygen-policy"
FORMAT_VERSION = 1


class PolicyCheckpointError(KeyGenError):
    """A policy run directory is missing, incomplete or malformed."""


def write_json(path: Path, data: dict[str, Any]) -> None:
    atomic_write_json(path, data, sort_keys=True)


def save_tensors(
    path: Path, tensors: dict[str, torch.Tensor], metadata: dict[str, str] | None = None
) -> None:
    tensors = {k: v.detach().cpu().contiguous() for k, v in tensors.items()}
    atomic_write(path, lambda tmp: save_file(tensors, str(tmp), metadata=metadata))


def read_config(run_dir: str | Path) -> dict[str, Any]:
    path = Path(run_dir) / CONFIG_FILE
    if not path.is_file():
        raise PolicyCheckpointError(
            f"{path} is missing; a policy run directory (written by `keygen train`) holds {CONFIG_FILE} "
            f"and {WEIGHTS_FILE}"
        )
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise PolicyCheckpointError(f"{path} is not valid JSON ({exc}); retrain or restore the file") from exc
    if data.get("format") != FORMAT or data.get("version") != FORMAT_VERSION:
        raise PolicyCheckpointError(
            f"{path} is not a {FORMAT} v{FORMAT_VERSION} config (format={data.get('format')!r}, "
            f"version={data.get('version')!r})"
        )
    return data


def make_run_config(
    policy: PolicyConfig, task: str, keypoint_categories: list[str], train: dict[str, Any]
) -> dict[str, Any]:
    return {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "policy": policy.to_dict(),
        "task": task,
        "keypoint_categories": list(keypoint_categories),
        "train": train,
        "finished": False,
        "step": 0,
    }


def save_model(run_dir: Path, model: DiffusionPolicy) -> None:
    save_tensors(run_dir / WEIGHTS_FILE, model.state_dict(), {"policy": model.config.name})


def load_policy(run_dir: str | Path, device: str = "cpu") -> tuple[DiffusionPolicy, dict[str, Any]]:
    """The trained (EMA) policy of a run directory, in eval mode, and its config.json contents."""
    run_dir = Path(run_dir)
    meta = read_config(run_dir)
    weights = run_dir / WEIGHTS_FILE
    if not weights.is_file():
        raise PolicyCheckpointError(
            f"{weights} is missing: the run has not saved a model yet; train it (a rerun resumes) first"
        )
    model = DiffusionPolicy(PolicyConfig.from_dict(meta["policy"]))
    try:
        model.load_state_dict(load_file(str(weights)), strict=True)
    except (RuntimeError, OSError, SafetensorError) as exc:
        raise PolicyCheckpointError(
            f"weights in {weights} do not fit the policy in {CONFIG_FILE}: {exc}"
        ) from exc
    return model.to(device).eval(), meta
