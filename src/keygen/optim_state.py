"""Flat tensor dictionaries for module and optimizer state, so both go into one safetensors file.

safetensors stores a flat ``name -> tensor`` map; an optimizer's ``state_dict`` is nested
(parameter index -> buffer name -> tensor) with hyper-parameters beside it. These helpers flatten
the tensors under a key prefix and hand the hyper-parameters (``param_groups``, plain JSON) back to
the caller, which stores them in its own metadata. The separator is a parameter because the policy
and keypoint checkpoints already on disk use ``.`` and ``/`` respectively.
"""

from __future__ import annotations

from typing import Any

import torch

__all__ = ["optimizer_tensors", "prefixed", "restore_optimizer", "unprefixed"]


def prefixed(tensors: dict[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    """``{prefix + name: tensor}``, detached and contiguous on the CPU, ready to save."""
    return {f"{prefix}{k}": v.detach().cpu().contiguous() for k, v in tensors.items()}


def unprefixed(tensors: dict[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    """The entries whose names start with ``prefix``, with the prefix removed."""
    return {k[len(prefix) :]: v for k, v in tensors.items() if k.startswith(prefix)}


def optimizer_tensors(
    optimizer: torch.optim.Optimizer, prefix: str = "opt", sep: str = "."
) -> tuple[dict[str, torch.Tensor], list[dict[str, Any]]]:
    """The optimizer's buffers as ``{prefix}{sep}{index}{sep}{buffer}`` tensors, and its param_groups."""
    state = optimizer.state_dict()
    tensors = {
        f"{prefix}{sep}{index}{sep}{name}": torch.as_tensor(value).detach().cpu().contiguous()
        for index, buffers in state["state"].items()
        for name, value in buffers.items()
    }
    return tensors, state["param_groups"]


def restore_optimizer(
    optimizer: torch.optim.Optimizer,
    tensors: dict[str, torch.Tensor],
    param_groups: list[dict[str, Any]],
    prefix: str = "opt",
    sep: str = ".",
) -> None:
    """Load what :func:`optimizer_tensors` produced (other entries in ``tensors`` are ignored)."""
    state: dict[int, dict[str, torch.Tensor]] = {}
    for key, value in unprefixed(tensors, prefix + sep).items():
        index, name = key.split(sep, 1)
        state.setdefault(int(index), {})[name] = value
    optimizer.load_state_dict({"state": state, "param_groups": param_groups})
