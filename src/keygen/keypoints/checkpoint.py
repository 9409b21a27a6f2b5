"""Resumable training state as safetensors: model weights, Adam state and the step, never pickle.

``save_state(path, model, optimizer, step, extra)`` writes ``<path>.safetensors`` (tensors) and
``<path>.json`` (step, optimizer hyper-parameters, anything in ``extra``) atomically (temporary file,
then rename; the JSON last, so a JSON file always describes complete weights).
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from keygen.atomic import atomic_write, atomic_write_json
from keygen.keypoints.models import CheckpointError
from keygen.optim_state import optimizer_tensors, prefixed, restore_optimizer, unprefixed

__all__ = ["load_state", "save_state"]


def save_state(
    path: str | Path,
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    step: int,
    extra: dict | None = None,
) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    opt_tensors, groups = optimizer_tensors(optimizer, "opt", "/")
    tensors = prefixed(model.state_dict(), "model/") | opt_tensors
    atomic_write(path.with_suffix(".safetensors"), lambda tmp: save_file(tensors, str(tmp)))
    meta = {"step": int(step), "param_groups": groups, "extra": extra or {}}
    atomic_write_json(path.with_suffix(".json"), meta, indent=None)


def load_state(
    path: str | Path, model: torch.nn.Module, optimizer: torch.optim.Optimizer
) -> tuple[int, dict]:
    """Restore what :func:`save_state` wrote; returns ``(step, extra)``; ``(0, {})`` when nothing is there."""
    path = Path(path)
    meta_path, weights_path = path.with_suffix(".json"), path.with_suffix(".safetensors")
    if not meta_path.is_file() or not weights_path.is_file():
        return 0, {}
    try:
        meta = json.loads(meta_path.read_text())
        tensors = load_file(str(weights_path))
        model.load_state_dict(unprefixed(tensors, "model/"), strict=True)
        restore_optimizer(optimizer, tensors, meta["param_groups"], "opt", "/")
    except (OSError, RuntimeError, ValueError, KeyError) as exc:
        raise CheckpointError(
            f"cannot resume from {path}.*: {exc}; delete {weights_path.name} and {meta_path.name} to restart "
            "this stage"
        ) from exc
    return int(meta["step"]), dict(meta.get("extra", {}))
