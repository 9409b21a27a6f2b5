"""Domain randomisation: each part switchable, every draw from the episode's seeded generator.

Parts: ``lighting`` (direction, intensity, ambient), ``colors`` (object and table colours and a
table texture), ``camera`` (per-camera position jitter and field of view), ``physics`` (object
mass and friction). ``Randomization.parse`` accepts a bool (all or none), a comma-separated
string of part names, a dict, or an instance.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from keygen.errors import InvalidParameterError

PARTS = ("lighting", "colors", "camera", "physics")


@dataclass(frozen=True)
class Randomization:
    lighting: bool = False
    colors: bool = False
    camera: bool = False
    physics: bool = False
    camera_position_std: float = 0.01  # metres
    camera_fovy_std_deg: float = 1.5
    mass_range: tuple[float, float] = (0.8, 1.25)  # multiplier
    friction_range: tuple[float, float] = (0.7, 1.3)  # multiplier

    @staticmethod
    def parse(value: bool | str | dict | Randomization | None) -> Randomization:
        if isinstance(value, Randomization):
            return value
        if value is None or value is False:
            return Randomization()
        if value is True:
            return Randomization(**{p: True for p in PARTS})
        if isinstance(value, str):
            names = [v.strip() for v in value.split(",") if v.strip()]
            if names == ["all"]:
                return Randomization.parse(True)
            if names == ["none"]:
                return Randomization()
            unknown = sorted(set(names) - set(PARTS))
            if unknown:
                raise InvalidParameterError(f"unknown randomisation parts {unknown}; choose from {PARTS}")
            return Randomization(**{p: True for p in names})
        if isinstance(value, dict):
            known = {f.name for f in fields(Randomization)}
            unknown = sorted(set(value) - known)
            if unknown:
                raise InvalidParameterError(f"unknown randomisation keys {unknown}; known: {sorted(known)}")
            return Randomization(**value)
        raise InvalidParameterError(
            f"randomize must be a bool, str, dict or Randomization, got {type(value)}"
        )

    @property
    def any(self) -> bool:
        return any(getattr(self, p) for p in PARTS)


def object_color(
    rng: np.random.Generator, randomize: bool, default: tuple[float, float, float]
) -> list[float]:
    """An RGBA colour: the default, or a random saturated-enough colour."""
    if not randomize:
        return [*default, 1.0]
    hue = rng.uniform(0, 1)
    sat, val = rng.uniform(0.25, 0.85), rng.uniform(0.45, 0.95)
    i = int(hue * 6) % 6
    f = hue * 6 - int(hue * 6)
    p, q, t = val * (1 - sat), val * (1 - f * sat), val * (1 - (1 - f) * sat)
    rgb = [(val, t, p), (q, val, p), (p, val, t), (p, q, val), (t, p, val), (val, p, q)][i]
    return [*rgb, 1.0]
