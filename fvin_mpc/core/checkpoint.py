"""Checkpoints: safetensors weights + a JSON sidecar, loaded without unpickling code.

A checkpoint ``name`` is two files: ``name.safetensors`` (float64 tensors, read with
``safetensors.numpy`` so the control runtime needs no torch) and ``name.json``::

    {"format": "fvin_mpc.checkpoint/1", "model": {ModelConfig fields}, "weights_sha256": "…",
     "configuration_space": "S3", "scene": "pendulum", "body": "pole", "data": {...},
     "training": {...}, "versions": {...}}

``configuration_space`` names the registered space the weights belong to
(:func:`fvin_mpc.core.space.get_space`), which gives the config type: ``"S3"`` (a pivoted body; also
what a sidecar without the field means), ``"SO3"`` (the paper's SO3FVIN baseline) or ``"R3xS3"`` (a
free body). Sidecars written before the field existed for free bodies carry it inside ``model``.

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

from fvin_mpc.core.errors import FvinMpcError
from fvin_mpc.core.space import ConfigurationSpace, get_space, require, space_of_config

#: A checkpoint's model configuration: the config type of one registered configuration space.
AnyConfig = Any

FORMAT = "fvin_mpc.checkpoint/1"
_PACKAGE = Path(__file__).resolve().parents[1]
#: Where the shipped checkpoints live: ``fvin_mpc/checkpoints`` in an installed wheel (package data),
#: the repository's ``checkpoints/`` beside the package in a source checkout.
CHECKPOINT_DIR = next((d for d in (_PACKAGE / "checkpoints", _PACKAGE.parent / "checkpoints") if d.is_dir()),
                      _PACKAGE.parent / "checkpoints")


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
    def space(self) -> ConfigurationSpace:
        """The configuration space of the model (the config's)."""
        return space_of_config(self.config)

    @property
    def configuration_space(self) -> str:
        """The space's name, as written in the sidecar."""
        return self.space.name

    def require(self, *supported: ConfigurationSpace, by: str) -> None:
        """``ValueError`` unless the model is on one of ``supported`` (code written for some spaces
        refuses the others' checkpoints this way)."""
        require(self.space, supported, by, f"checkpoint {self.path.name if self.path else '(unsaved)'!r}")


def configuration_space(config: AnyConfig) -> str:
    """The name of ``config``'s configuration space."""
    return space_of_config(config).name


def _config_from_dict(model: Mapping[str, Any], space_name: Any) -> AnyConfig:
    # R³ × S³ configs once carried the space among their own fields too; it is the sidecar's now.
    fields = dict(model)
    inner = fields.pop("configuration_space", None)
    return get_space(space_name if space_name is not None else inner).config_from_dict(fields)


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

    space_of_config(config).check_weights(weights, config)
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
        raise CheckpointError(
            f"{sidecar_path}: not a {FORMAT} sidecar (format field is "
            f"{sidecar.get('format') if isinstance(sidecar, dict) else None!r})"
        )
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
        raise CheckpointError(
            f"{weights_path}: SHA-256 differs from the sidecar's weights_sha256 (corrupted or replaced)"
        )
    try:
        space_of_config(config).check_weights(weights, config)
    except ValueError as error:
        raise CheckpointError(f"{weights_path}: {error}") from None
    for name, value in weights.items():
        if value.dtype != np.float64:
            raise CheckpointError(f"{weights_path}: weight {name!r} has dtype {value.dtype}, expected float64")
        if not np.all(np.isfinite(value)):
            raise CheckpointError(f"{weights_path}: weight {name!r} contains NaN or inf")
    metadata = {key: value for key, value in sidecar.items() if key not in ("format", "model")}
    return Checkpoint(config=config, weights=weights, metadata=metadata, path=stem)
