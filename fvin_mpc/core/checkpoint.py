"""Checkpoints: safetensors weights + a JSON sidecar, loaded without unpickling code.

A checkpoint ``name`` is two files: ``name.safetensors`` (float64 tensors, read with
``safetensors.numpy`` so the control runtime needs no torch) and ``name.json``::

    {"format": "fvin_mpc.checkpoint/1", "model": {ModelConfig fields}, "weights_sha256": "…",
     "configuration_space": "S3", "scene": "pendulum", "body": "pole", "data": {...},
     "training": {...}, "versions": {...}}

``configuration_space`` says which model the weights belong to: ``"S3"`` (a pivoted body,
:class:`~fvin_mpc.core.networks.ModelConfig`; also what a sidecar without the field means),
``"R3xS3"`` (a free body, :class:`~fvin_mpc.core.networks_r3s3.R3S3Config`, whose ``model`` fields
repeat it) or ``"SO3"`` (the paper's SO3FVIN baseline on a pivoted body,
:class:`~fvin_mpc.core.networks_so3.SO3ModelConfig`).

Every problem (missing file, truncated or malformed weights, bad JSON, weights that do
not match the config) raises :class:`CheckpointError` with a one-line message naming it.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from fvin_mpc.core import networks, networks_r3s3, networks_so3
from fvin_mpc.core.errors import FvinMpcError
from fvin_mpc.core.networks import ModelConfig

#: A checkpoint's model configuration: pivoted (S³), free body (R³ × S³) or the SO(3) baseline.
AnyConfig = ModelConfig | networks_r3s3.R3S3Config | networks_so3.SO3ModelConfig

FORMAT = "fvin_mpc.checkpoint/1"
#: Where the shipped checkpoints live (next to the package in a source checkout or
#: installed as package data).
CHECKPOINT_DIR = Path(__file__).resolve().parents[2] / "checkpoints"


class CheckpointError(FvinMpcError, ValueError):
    """A checkpoint could not be read; the message says which file and why."""


@dataclass(frozen=True)
class Checkpoint:
    """A trained model: its config, NumPy float64 weights and free-form metadata."""

    config: AnyConfig
    weights: Mapping[str, np.ndarray]
    metadata: Mapping[str, Any] = field(default_factory=dict)
    path: Path | None = None

    @property
    def scene(self) -> str | None:
        return self.metadata.get("scene")

    @property
    def configuration_space(self) -> str:
        """``"S3"``, ``"R3xS3"`` or ``"SO3"``."""
        return configuration_space(self.config)


def configuration_space(config: AnyConfig) -> str:
    """``"R3xS3"`` for a free-body config, ``"SO3"`` for an SO3FVIN one, ``"S3"`` for a pivoted one."""
    if isinstance(config, networks_r3s3.R3S3Config):
        return networks_r3s3.CONFIGURATION_SPACE
    if isinstance(config, networks_so3.SO3ModelConfig):
        return networks_so3.CONFIGURATION_SPACE
    return "S3"


def _check_weights(weights: Mapping[str, Any], config: AnyConfig) -> None:
    if isinstance(config, networks_r3s3.R3S3Config):
        networks_r3s3.check_weights(weights, config)
    elif isinstance(config, networks_so3.SO3ModelConfig):
        networks_so3.check_weights(weights, config)
    else:
        networks.check_weights(weights, config)


def _config_from_dict(model: Mapping[str, Any], space: Any) -> AnyConfig:
    if space == networks_r3s3.CONFIGURATION_SPACE or model.get("configuration_space") == networks_r3s3.CONFIGURATION_SPACE:
        return networks_r3s3.R3S3Config.from_dict(model)
    if space == networks_so3.CONFIGURATION_SPACE:
        return networks_so3.SO3ModelConfig.from_dict(model)
    if space not in (None, "S3"):
        raise ValueError(f"unknown configuration_space {space!r}")
    return ModelConfig.from_dict(model)


_SUFFIXES = (".safetensors", ".json")


def _stem(path: str | Path) -> Path:
    """``path`` without a ``.safetensors``/``.json`` suffix. Other dots stay part of the name
    (``pendulum-h0.02_sign-invariant``), which is why ``Path.with_suffix`` is not used."""
    path = Path(path)
    return path.with_suffix("") if path.suffix in _SUFFIXES else path


def _with(stem: Path, suffix: str) -> Path:
    return stem.parent / (stem.name + suffix)


def resolve_checkpoint_path(name_or_path: str | Path) -> Path:
    """``name_or_path`` as a path stem: a shipped name (``pendulum_sign-invariant``), or a
    path with or without the ``.safetensors``/``.json`` suffix."""
    path = _stem(name_or_path)
    if not _with(path, ".json").exists() and not path.is_absolute() and len(path.parts) == 1:
        shipped = CHECKPOINT_DIR / path
        if _with(shipped, ".json").exists():
            return shipped
    return path


def checkpoint_exists(name_or_path: str | Path) -> bool:
    """Whether a checkpoint's sidecar is there (it may still be corrupted: :func:`load_checkpoint` says)."""
    return _with(resolve_checkpoint_path(name_or_path), ".json").exists()


def weights_digest(weights_path: Path) -> str:
    """SHA-256 of the weights file: a flipped bit inside the float data parses fine, this does not."""
    return hashlib.sha256(weights_path.read_bytes()).hexdigest()


def save_checkpoint(path: str | Path, config: AnyConfig, weights: Mapping[str, np.ndarray], **metadata: Any) -> Path:
    """Write ``path.safetensors`` and ``path.json``; returns the stem."""
    from safetensors.numpy import save_file

    _check_weights(weights, config)
    stem = _stem(path)
    stem.parent.mkdir(parents=True, exist_ok=True)
    arrays = {name: np.ascontiguousarray(np.asarray(value, dtype=np.float64)) for name, value in weights.items()}
    save_file(arrays, str(_with(stem, ".safetensors")))
    sidecar = {"format": FORMAT, "model": config.to_dict(),
               "weights_sha256": weights_digest(_with(stem, ".safetensors")),
               "configuration_space": configuration_space(config), **metadata}
    _with(stem, ".json").write_text(json.dumps(sidecar, indent=2, sort_keys=False) + "\n")
    return stem


def load_checkpoint(name_or_path: str | Path) -> Checkpoint:
    """Read a checkpoint written by :func:`save_checkpoint`; see the module docstring."""
    stem = resolve_checkpoint_path(name_or_path)
    sidecar_path, weights_path = _with(stem, ".json"), _with(stem, ".safetensors")
    for required in (sidecar_path, weights_path):
        if not required.exists():
            raise CheckpointError(f"checkpoint file not found: {required}")
    try:
        sidecar = json.loads(sidecar_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise CheckpointError(f"{sidecar_path}: not valid JSON ({error})") from None
    if not isinstance(sidecar, dict) or sidecar.get("format") != FORMAT:
        raise CheckpointError(f"{sidecar_path}: not a {FORMAT} sidecar (format field is {sidecar.get('format') if isinstance(sidecar, dict) else None!r})")
    try:
        config = _config_from_dict(sidecar["model"], sidecar.get("configuration_space"))
    except (KeyError, TypeError, ValueError) as error:
        raise CheckpointError(f"{sidecar_path}: invalid model config ({error})") from None
    from safetensors import SafetensorError
    from safetensors.numpy import load_file

    try:
        weights = load_file(str(weights_path))
    except (SafetensorError, OSError, ValueError) as error:
        raise CheckpointError(f"{weights_path}: unreadable or truncated safetensors file ({error})") from None
    expected_digest = sidecar.get("weights_sha256")
    if expected_digest is not None and expected_digest != weights_digest(weights_path):
        raise CheckpointError(f"{weights_path}: SHA-256 differs from the sidecar's weights_sha256 (corrupted or replaced)")
    try:
        _check_weights(weights, config)
    except ValueError as error:
        raise CheckpointError(f"{weights_path}: {error}") from None
    for name, value in weights.items():
        if value.dtype != np.float64:
            raise CheckpointError(f"{weights_path}: weight {name!r} has dtype {value.dtype}, expected float64")
        if not np.all(np.isfinite(value)):
            raise CheckpointError(f"{weights_path}: weight {name!r} contains NaN or inf")
    metadata = {key: value for key, value in sidecar.items() if key not in ("format", "model")}
    return Checkpoint(config=config, weights=weights, metadata=metadata, path=stem)
