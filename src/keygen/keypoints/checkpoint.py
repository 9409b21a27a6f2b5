"""Resumable training state as safetensors: model weights, Adam state and the step, never pickle.

``save_state(path, model, optimizer, step, extra)`` writes ``<path>.safetensors`` (tensors) and
``<path>.json`` (step, optimizer hyper-parameters, anything in ``extra``) atomically (temporary file,
then rename; the JSON last, so a JSON file always describes complete weights).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file

from keygen.atomic import atomic_write, atomic_write_json
from keygen.keypoints.models import CheckpointError

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
    tensors = {f"model/{k}": v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    opt = optimizer.state_dict()
    for index, state in opt["state"].items():
        for name, value in state.items():
            tensors[f"opt/{index}/{name}"] = torch.as_tensor(value).detach().cpu().contiguous()
    atomic_write(path.with_suffix(".safetensors"), lambda tmp: save_file(tensors, str(tmp)))
    meta = {"step": int(step), "param_groups": opt["param_groups"], "extra": extra or {}}
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
        model.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("model/")}, strict=True)
        state: dict[int, dict[str, Any]] = {}
        for key, value in tensors.items():
            if key.startswith("opt/"):
                _, index, name = key.split("/", 2)
                state.setdefault(int(index), {})[name] = value
        optimizer.load_state_dict({"state": state, "param_groups": meta["param_groups"]})
    except (OSError, RuntimeError, ValueError, KeyError) as exc:
        raise CheckpointError(
            f"cannot resume from {path}.*: {exc}; delete {weights_path.name} and {meta_path.name} to restart "
            "this stage"
        ) from exc
    return int(meta["step"]), dict(meta.get("extra", {}))
