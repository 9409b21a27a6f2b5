"""Flattened optimizer state: a save/restore round trip continues training exactly."""

import copy

import pytest
import torch
from safetensors.torch import load_file, save_file

from keygen.optim_state import optimizer_tensors, prefixed, restore_optimizer, unprefixed


def _trained(seed: int = 0):
    torch.manual_seed(seed)
    model = torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.ReLU(), torch.nn.Linear(8, 2))
    opt = torch.optim.AdamW(model.parameters(), lr=1e-2, weight_decay=0.1)
    for _ in range(3):
        opt.zero_grad()
        model(torch.randn(16, 4)).pow(2).mean().backward()
        opt.step()
    return model, opt


def _step(model, opt, x):
    opt.zero_grad()
    model(x).pow(2).mean().backward()
    opt.step()


@pytest.mark.parametrize("sep", [".", "/"])
def test_restored_optimizer_takes_the_same_next_step(tmp_path, sep):
    model, opt = _trained()
    opt_tensors, groups = optimizer_tensors(opt, "opt", sep)
    path = tmp_path / "state.safetensors"
    save_file(prefixed(model.state_dict(), f"model{sep}") | opt_tensors, str(path))

    # A fresh model and optimizer, restored from the file.
    torch.manual_seed(99)
    model2 = torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.ReLU(), torch.nn.Linear(8, 2))
    opt2 = torch.optim.AdamW(model2.parameters(), lr=0.5)
    tensors = load_file(str(path))
    model2.load_state_dict(unprefixed(tensors, f"model{sep}"))
    restore_optimizer(opt2, tensors, copy.deepcopy(groups), "opt", sep)

    assert opt2.param_groups[0]["lr"] == pytest.approx(1e-2)
    x = torch.randn(16, 4, generator=torch.Generator().manual_seed(5))
    _step(model, opt, x)
    _step(model2, opt2, x)
    for a, b in zip(model.parameters(), model2.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_keys_and_prefix_helpers():
    model, opt = _trained()
    tensors, groups = optimizer_tensors(opt, "opt", "/")
    # AdamW keeps step, exp_avg and exp_avg_sq per parameter (4 parameters here).
    assert len(tensors) == 4 * 3
    assert all(k.startswith("opt/") and k.count("/") == 2 for k in tensors)
    assert isinstance(groups, list) and groups[0]["weight_decay"] == 0.1
    flat = prefixed({"w": torch.ones(2, 3).t()}, "m.")
    assert flat["m.w"].is_contiguous()
    assert unprefixed(flat | {"other": torch.zeros(1)}, "m.").keys() == {"w"}
