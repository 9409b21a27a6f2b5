"""The package's exceptions: one base class, specific subclasses.

Messages say what was expected, what came, and what to do about it.
"""

from __future__ import annotations


class KeyGenError(Exception):
    """Base class of every error raised on purpose by keygen."""


class InvalidParameterError(KeyGenError, ValueError):
    """A parameter or argument is outside its documented range."""


class MeshImportError(KeyGenError):
    """A mesh file cannot be read or repaired into a usable asset."""


class AssetError(KeyGenError):
    """An asset folder is missing, malformed, or lacks what a caller needs."""


class MissingAnchorsError(AssetError):
    """A task needs semantic anchors that this asset does not have."""
