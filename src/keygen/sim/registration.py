"""Registers the gymnasium ids; kept free of heavy imports so ``import keygen`` stays fast."""

from __future__ import annotations

ENV_IDS = {"pour": "keygen/Pour-v0", "knife": "keygen/CollectKnife-v0", "stack": "keygen/StackBowl-v0"}


def register_envs() -> None:
    """Register ``keygen/Pour-v0``, ``keygen/CollectKnife-v0`` and ``keygen/StackBowl-v0`` (idempotent)."""
    try:
        import gymnasium as gym
    except ImportError:  # pragma: no cover - gymnasium is a dependency; keep the objects usable without it
        return
    for task, env_id in ENV_IDS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point="keygen.sim.env:KeyGenEnv", kwargs={"task": task})
