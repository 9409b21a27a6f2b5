"""The interface every category generator implements.

A generator is a parametric family: ``sample_params`` draws one parameter dict from a seeded
generator (optionally forcing a style, e.g. a handle shape, so that splits can cover every
style), and ``build`` turns a parameter dict into an :class:`~keygen.objects.asset.Asset` at
nominal scale 1. ``build`` is a pure function of the parameters: same dict, same asset.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

import numpy as np

from keygen.objects.asset import Asset


class CategoryGenerator(ABC):
    #: category name, one of keygen.objects.asset.CATEGORIES
    category: str
    #: the discrete styles of the family (e.g. handle shapes); splits cycle through them
    styles: tuple[str, ...]

    @abstractmethod
    def sample_params(self, rng: np.random.Generator, style: str | None = None) -> dict[str, Any]:
        """Draw one JSON-serialisable parameter dict (floats in metres, a ``style`` string)."""

    @abstractmethod
    def build(self, params: dict[str, Any], instance_id: str) -> Asset:
        """Build the asset for ``params`` in the category's canonical frame, at scale 1."""

    @abstractmethod
    def main_dimensions(self, params: dict[str, Any]) -> dict[str, float]:
        """The category's main dimensions in metres (reported as ranges in docs/objects.md)."""

    def validate(self, asset: Asset) -> list[str]:
        """Problems found with ``asset`` (empty when it is sound).

        Common checks here (watertight visual mesh, convex collision parts, positive mass);
        each category adds the placement of its anchors in :meth:`validate_anchors`.
        Works on assets at any scale, generated or imported with anchors.
        """
        problems: list[str] = []
        if not asset.visual.is_watertight:
            problems.append("visual mesh is not watertight")
        for i, part in enumerate(asset.collision):
            mesh = part.to_trimesh()
            if not mesh.is_convex:
                problems.append(f"collision part {i} ({part.kind}) is not convex")
        if not asset.mass > 0:
            problems.append(f"mass must be positive, got {asset.mass}")
        if asset.anchors is not None:
            problems += self.validate_anchors(asset)
        return problems

    @abstractmethod
    def validate_anchors(self, asset: Asset) -> list[str]:
        """Category-specific checks that each anchor sits where its definition says."""
