"""Networks of the keypoint stage (paper, "3D Keypoint Detection"), CPU-sized.

- :class:`PointNetEncoder`: shared per-point MLP + max pool (Qi et al. 2017); a global feature per
  cloud, or a local+global feature per point.
- :class:`Canonicalizer`: classifies a cloud's orientation over the 24 rotations of
  :func:`keygen.geometry.rotations.octahedral_group` (same order, so indices are interchangeable).
- :class:`KeypointDetector`: K keypoints as convex combinations of the input points.
- :func:`canonicalize` / :func:`reproject`: ``P_can = R^-1 P`` and ``K_obs = R K``.
- :func:`save_model` / :func:`load_model`: a checkpoint directory with ``config.json`` and
  ``model.safetensors`` (never pickle).

Conventions: points are ROW vectors, clouds (B, N, 3) in metres. ``R`` is the canonical ->
observation rotation acting on column vectors (``p_obs = R @ p_can``), so for rows
``P_can = P @ R`` (R^-1 = R^T) and ``K_obs = K @ R^T``. Networks have no batch norm or dropout:
their outputs do not depend on the other samples of a batch nor on train/eval mode.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import nn

from keygen.errors import InvalidParameterError, KeyGenError
from keygen.geometry.rotations import octahedral_group

__all__ = [
    "Canonicalizer",
    "CheckpointError",
    "KeypointDetector",
    "PointNetEncoder",
    "canonicalize",
    "detect_keypoints",
    "load_model",
    "reproject",
    "save_model",
]

CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"
# Clouds smaller than this RMS radius (m) are not rescaled: it would only amplify noise.
_MIN_SCALE = 1e-6


class CheckpointError(KeyGenError):
    """A model checkpoint directory is missing, malformed, or holds a different model."""


# -- helpers ----------------------------------------------------------------------------------
def _check_positive_int(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise InvalidParameterError(f"{name} must be a positive int, got {value!r}")
    return value


def _check_cloud(cloud: torch.Tensor, name: str = "cloud", dim: int = 3) -> None:
    if not isinstance(cloud, torch.Tensor) or cloud.ndim != 3 or cloud.shape[-1] != dim or cloud.shape[1] < 1:
        shape = tuple(cloud.shape) if isinstance(cloud, torch.Tensor) else type(cloud).__name__
        raise InvalidParameterError(
            f"{name} must be a torch tensor of shape (B, N, {dim}) with N >= 1, got {shape}; "
            "add a batch axis with cloud[None] for a single cloud"
        )


def _mlp(sizes: list[int]) -> nn.Sequential:
    """Linear + ReLU layers on the last axis, so it is shared across points of a (B, N, C) input."""
    layers: list[nn.Module] = []
    for fan_in, fan_out in zip(sizes[:-1], sizes[1:], strict=True):
        layers += [nn.Linear(fan_in, fan_out), nn.ReLU()]
    return nn.Sequential(*layers)


def normalize_cloud(cloud: torch.Tensor, scale: bool) -> torch.Tensor:
    """Centre each cloud on its mean and, with ``scale``, divide by its RMS radius: (B, N, 3) -> same.

    Makes the networks' input independent of where the object is and (optionally) of its size;
    returns a new tensor.
    """
    centred = cloud - cloud.mean(dim=1, keepdim=True)  # (B, N, 3)
    if not scale:
        return centred
    rms = centred.pow(2).sum(-1).mean(-1).sqrt()  # (B,)
    return centred / rms.clamp(min=_MIN_SCALE)[:, None, None]


class _Configurable(nn.Module):
    """``to_config`` / ``from_config`` on top of a module whose constructor takes only JSON values."""

    _config_keys: tuple[str, ...] = ()

    def to_config(self) -> dict[str, Any]:
        """JSON-serialisable constructor arguments, with the class name under ``"type"``."""
        return {"type": type(self).__name__, **{key: getattr(self, key) for key in self._config_keys}}

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> _Configurable:
        """A fresh (randomly initialised) model from :meth:`to_config`'s output."""
        config = dict(config)
        kind = config.pop("type", cls.__name__)
        if kind != cls.__name__:
            raise CheckpointError(f"config describes a {kind}, not a {cls.__name__}; use the matching class")
        unknown = set(config) - set(cls._config_keys)
        if unknown:
            raise CheckpointError(
                f"unknown {cls.__name__} config keys {sorted(unknown)}; "
                f"expected a subset of {list(cls._config_keys)}"
            )
        return cls(**config)


# -- networks ---------------------------------------------------------------------------------
class PointNetEncoder(_Configurable):
    """Shared per-point MLP, then max pooling over points (order invariant).

    ``forward(points (B, N, in_dim)) -> (B, width)`` global features;
    ``point_features(points) -> (B, N, hidden + width)``: each point's local feature (the layer
    before the last) concatenated with the global feature, for per-point heads.
    """

    _config_keys = ("in_dim", "width", "hidden")

    def __init__(self, in_dim: int = 3, width: int = 256, hidden: int = 64) -> None:
        super().__init__()
        self.in_dim = _check_positive_int(in_dim, "in_dim")
        self.width = _check_positive_int(width, "width")
        self.hidden = _check_positive_int(hidden, "hidden")
        self.local = _mlp([in_dim, hidden, hidden])
        self.lift = _mlp([hidden, 2 * hidden, width])

    @property
    def point_dim(self) -> int:
        """Size of the per-point feature of :meth:`point_features`."""
        return self.hidden + self.width

    def _features(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        _check_cloud(points, "points", self.in_dim)
        local = self.local(points)  # (B, N, hidden)
        pooled = self.lift(local).max(dim=1).values  # (B, width)
        return local, pooled

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self._features(points)[1]

    def point_features(self, points: torch.Tensor) -> torch.Tensor:
        local, pooled = self._features(points)
        glob = pooled[:, None, :].expand(-1, local.shape[1], -1)  # (B, N, width)
        return torch.cat([local, glob], dim=-1)  # (B, N, hidden + width)


class Canonicalizer(_Configurable):
    """Orientation classifier over the 24 cube rotations (the paper's canonical form matching).

    ``forward(cloud (B, N, 3)) -> logits (B, 24)``; class ``c`` means the cloud is the canonical
    object rotated by ``octahedral_group()[c]`` (canonical -> observation), so
    ``canonicalize(cloud, R)`` brings it back. The cloud is centred on its mean (and, with
    ``normalize_scale``, divided by its RMS radius) first, so only its orientation and shape matter.
    """

    _config_keys = ("num_rotations", "width", "hidden", "normalize_scale")

    def __init__(
        self, num_rotations: int = 24, width: int = 256, hidden: int = 64, normalize_scale: bool = True
    ) -> None:
        super().__init__()
        # A copy: the group array is read-only and torch warns about wrapping it.
        group = torch.tensor(octahedral_group().copy(), dtype=torch.float32)  # (24, 3, 3)
        if num_rotations != group.shape[0]:
            raise InvalidParameterError(
                f"num_rotations must be {group.shape[0]} (the octahedral group), got {num_rotations!r}"
            )
        self.num_rotations = num_rotations
        self.width = _check_positive_int(width, "width")
        self.hidden = _check_positive_int(hidden, "hidden")
        self.normalize_scale = bool(normalize_scale)
        self.encoder = PointNetEncoder(3, width, hidden)
        self.head = nn.Sequential(*_mlp([width, width // 2 or 1]), nn.Linear(width // 2 or 1, num_rotations))
        # Derived from keygen.geometry, not learned: kept out of the state dict (persistent=False).
        self.register_buffer("rotations", group, persistent=False)

    def forward(self, cloud: torch.Tensor) -> torch.Tensor:
        _check_cloud(cloud)
        return self.head(self.encoder(normalize_cloud(cloud, self.normalize_scale)))  # (B, 24)

    @torch.no_grad()
    def predict(self, cloud: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Most probable rotation: ``(R (B, 3, 3), index (B,) long, confidence (B,) in (0, 1])``.

        ``R`` is an exact group element (canonical -> observation), in the cloud's dtype.
        """
        probs = torch.softmax(self(cloud), dim=-1)  # (B, 24)
        confidence, index = probs.max(dim=-1)
        R = self.rotations.to(device=cloud.device, dtype=cloud.dtype)[index]  # (B, 3, 3)
        return R, index, confidence


class KeypointDetector(_Configurable):
    """K keypoints as convex combinations of the input points (the paper's detector F).

    ``forward(cloud (B, N, 3)) -> (keypoints (B, K, 3), weights (B, K, N))`` with weights a softmax
    over points (non-negative, each row sums to one) and ``keypoints = weights @ cloud``, so every
    keypoint lies in the cloud's convex hull. Features see the centred (optionally scale-normalised)
    cloud; the combination uses the points as given, so keypoints are in the input's frame.
    """

    _config_keys = ("num_keypoints", "width", "hidden", "normalize_scale")

    def __init__(
        self, num_keypoints: int = 10, width: int = 256, hidden: int = 64, normalize_scale: bool = True
    ) -> None:
        super().__init__()
        self.num_keypoints = _check_positive_int(num_keypoints, "num_keypoints")
        self.width = _check_positive_int(width, "width")
        self.hidden = _check_positive_int(hidden, "hidden")
        self.normalize_scale = bool(normalize_scale)
        self.encoder = PointNetEncoder(3, width, hidden)
        self.head = nn.Sequential(
            *_mlp([self.encoder.point_dim, 2 * hidden]), nn.Linear(2 * hidden, num_keypoints)
        )

    def forward(self, cloud: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        _check_cloud(cloud)
        features = self.encoder.point_features(normalize_cloud(cloud, self.normalize_scale))  # (B, N, F)
        scores = self.head(features).transpose(1, 2)  # (B, K, N)
        weights = torch.softmax(scores, dim=-1)  # (B, K, N), rows sum to one
        return weights @ cloud, weights  # (B, K, 3), (B, K, N)


# -- frames -----------------------------------------------------------------------------------
def _check_frame_args(x: torch.Tensor, R: torch.Tensor, name: str) -> None:
    if not isinstance(x, torch.Tensor) or x.ndim not in (2, 3) or x.shape[-1] != 3:
        raise InvalidParameterError(f"{name} must be a (N, 3) or (B, N, 3) tensor of row-vector points")
    if not isinstance(R, torch.Tensor) or R.ndim not in (2, 3) or R.shape[-2:] != (3, 3):
        raise InvalidParameterError("R must be a (3, 3) or (B, 3, 3) rotation tensor")
    if x.ndim == 3 and R.ndim == 3 and R.shape[0] != x.shape[0]:
        raise InvalidParameterError(f"R holds {R.shape[0]} rotations for a batch of {x.shape[0]} {name}s")


def canonicalize(cloud: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """``P_can = R^-1 P`` for row-vector points: ``cloud @ R`` ((B,) N, 3), R ((B,) 3, 3)."""
    _check_frame_args(cloud, R, "cloud")
    return cloud @ R


def reproject(kp: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """``K_obs = R K`` for row-vector points: ``kp @ R^T`` ((B,) K, 3), R ((B,) 3, 3)."""
    _check_frame_args(kp, R, "kp")
    return kp @ R.transpose(-1, -2)


@torch.no_grad()
def detect_keypoints(
    canonicalizer: Canonicalizer, detector: KeypointDetector, cloud: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The paper's inference: align, detect in the canonical frame, reproject.

    ``cloud`` (B, N, 3) -> ``(keypoints (B, K, 3) in the cloud's frame, R (B, 3, 3))``.
    """
    R, _, _ = canonicalizer.predict(cloud)
    kp_can, _ = detector(canonicalize(cloud, R))
    return reproject(kp_can, R), R


# -- checkpoints ------------------------------------------------------------------------------
_MODEL_TYPES: dict[str, type[_Configurable]] = {
    cls.__name__: cls for cls in (PointNetEncoder, Canonicalizer, KeypointDetector)
}


def save_model(model: _Configurable, directory: str | Path) -> Path:
    """Write ``config.json`` and ``model.safetensors`` into ``directory`` (created); returns it."""
    if not isinstance(model, _Configurable):
        raise InvalidParameterError(
            f"save_model takes one of {sorted(_MODEL_TYPES)}, got {type(model).__name__}"
        )
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    (directory / CONFIG_FILE).write_text(json.dumps(model.to_config(), indent=2, sort_keys=True) + "\n")
    tensors = {name: t.detach().cpu().contiguous() for name, t in model.state_dict().items()}
    save_file(tensors, str(directory / WEIGHTS_FILE), metadata={"type": type(model).__name__})
    return directory


def load_model(directory: str | Path, expected: type[_Configurable] | None = None) -> _Configurable:
    """Rebuild a model saved by :func:`save_model` (on the CPU, in eval mode).

    ``expected``: the class the caller needs; a checkpoint of another class is an error.
    """
    directory = Path(directory)
    config_path, weights_path = directory / CONFIG_FILE, directory / WEIGHTS_FILE
    for path in (config_path, weights_path):
        if not path.is_file():
            raise CheckpointError(
                f"{path} is missing; a keypoint model checkpoint is a directory with {CONFIG_FILE} and "
                f"{WEIGHTS_FILE} written by save_model"
            )
    try:
        config = json.loads(config_path.read_text())
    except json.JSONDecodeError as exc:
        raise CheckpointError(f"{config_path} is not valid JSON ({exc}); re-save the model") from exc
    kind = config.get("type") if isinstance(config, dict) else None
    if kind not in _MODEL_TYPES:
        raise CheckpointError(
            f"{config_path} names model type {kind!r}; expected one of {sorted(_MODEL_TYPES)}"
        )
    cls = _MODEL_TYPES[kind]
    if expected is not None and cls is not expected:
        raise CheckpointError(f"{directory} holds a {kind}, but a {expected.__name__} was asked for")
    model = cls.from_config(config)
    try:
        model.load_state_dict(load_file(str(weights_path)), strict=True)
    except (RuntimeError, OSError, SafetensorError) as exc:
        raise CheckpointError(
            f"weights in {weights_path} do not fit a {kind} with config {config}: {exc}; "
            "the two files must come from the same save_model call"
        ) from exc
    return model.eval()
