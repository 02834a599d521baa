"""Trajectory data sets of any configuration space: ``.npz`` files of states and controls with metadata.

Arrays (``N`` trajectories of ``T`` steps, ``m`` controls, states of ``n`` entries in the layout of
the data's configuration space, :mod:`fvin_mpc.core.space`): ``state (N, T+1, n)`` and
``u (N, T, m)``; ``metadata`` is a JSON string (scene, body, control period, seed, counts, control
modes, and ``configuration_space``: the space's name — files without it are S³ data).

Files written before states were stored whole hold a pivoted body's ``q (N, T+1, 4)`` and
``omega (N, T+1, 3)`` instead of ``state``; :func:`load_data` reads both.
"""

from __future__ import annotations

import json
import math
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from fvin_mpc.core.errors import DataFileError, DataFileNotFound
from fvin_mpc.core.space import ConfigurationSpace, get_space

#: The command that makes a data file (named in the error for a missing one).
HOW_TO_MAKE = "python -m fvin_mpc.collect"


@dataclass(frozen=True)
class Trajectories:
    """``N`` trajectories of one configuration space: ``state (N, T+1, n)``, ``u (N, T, m)`` and
    ``metadata`` (``control_period`` at least; ``configuration_space`` names the space, default S³).

    The *training layout* splits a state into its quaternion ``q`` and the ``rest`` (every other
    entry, in state order: ``ω`` for a pivoted body, ``(x, v, ω)`` for a free one):
    :meth:`windows` yields it and :meth:`from_parts` builds data from it.
    """

    state: np.ndarray
    u: np.ndarray
    metadata: dict[str, Any]

    def __post_init__(self) -> None:
        n = self.space.state_dim
        if self.state.ndim != 3 or self.state.shape[2] != n or self.u.ndim != 3 \
                or self.u.shape[:2] != (self.state.shape[0], self.state.shape[1] - 1):
            raise ValueError(f"inconsistent trajectory shapes for {self.space.description}: state {self.state.shape} "
                             f"(expected (N, T+1, {n})), u {self.u.shape} (expected (N, T, m))")

    @classmethod
    def from_parts(cls, q: np.ndarray, rest: np.ndarray, u: np.ndarray, metadata: Mapping[str, Any],
                   space: ConfigurationSpace | str | None = None) -> "Trajectories":
        """Data from the training layout ``q (N, T+1, 4)``, ``rest (N, T+1, n − 4)`` (a pivoted body's
        ``rest`` is ``ω``); ``space`` defaults to the metadata's (S³ if it names none)."""
        space = get_space(space if space is not None else metadata.get("configuration_space"))
        q, rest = np.asarray(q, dtype=np.float64), np.asarray(rest, dtype=np.float64)
        return cls(space.layout.join(q, rest), np.asarray(u, dtype=np.float64),
                   {**metadata, "configuration_space": space.name})

    @property
    def space(self) -> ConfigurationSpace:
        return get_space(self.metadata.get("configuration_space"))

    @property
    def q(self) -> np.ndarray:
        """The orientations ``(N, T+1, 4)`` of a single body."""
        return self.state[..., self.space.layout.attitude(by="Trajectories.q").quaternion]

    @property
    def omega(self) -> np.ndarray:
        """The body angular velocities ``(N, T+1, 3)`` of a single body."""
        return self.state[..., self.space.layout.attitude(by="Trajectories.omega").omega]

    @property
    def rest(self) -> np.ndarray:
        """Every entry but the quaternions ``(N, T+1, n − 4k)`` (the training layout)."""
        return self.space.layout.split(self.state)[1]

    @property
    def num_trajectories(self) -> int:
        return self.u.shape[0]

    @property
    def num_transitions(self) -> int:
        return self.u.shape[0] * self.u.shape[1]

    @property
    def control_period(self) -> float:
        return float(self.metadata["control_period"])

    def subset(self, indices: np.ndarray) -> "Trajectories":
        """The trajectories ``indices`` (a copy of the metadata)."""
        return Trajectories(self.state[indices], self.u[indices], dict(self.metadata))

    def windows(self, length: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All overlapping windows of ``length`` steps in the training layout: ``q (W, length+1, 4)``,
        ``rest (W, length+1, n − 4)`` and ``u (W, length, m)``."""
        steps = self.u.shape[1]
        if not 1 <= length <= steps:
            raise ValueError(f"window length {length} must be in [1, {steps}]")
        starts = range(steps - length + 1)
        states = np.concatenate([self.state[:, s : s + length + 1] for s in starts])
        q, rest = self.space.layout.split(states)
        return q, rest, np.concatenate([self.u[:, s : s + length] for s in starts])


def save_data(path: str | Path, data: Trajectories) -> Path:
    """Write ``data`` to a compressed ``.npz`` (the metadata as a JSON string, naming the space), whole or not
    at all: written beside the target and renamed onto it, so an interrupted write leaves no partial file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    metadata = {**data.metadata, "configuration_space": data.space.name}
    partial = path.with_name(f".{path.name}.partial.npz")
    try:
        np.savez_compressed(partial, state=data.state, u=data.u, metadata=json.dumps(metadata))
        os.replace(partial, path)
    finally:
        partial.unlink(missing_ok=True)
    return path


#: How far from unit norm a recorded quaternion may be: data are MuJoCo's normalized quaternions (unit to
#: 1e-12; a float32 copy to 1e-7). A file past it was not recorded by the package, or was edited.
DATA_UNIT_NORM_TOLERANCE = 1e-6
#: The suffixes of a checkpoint's two files, which a data option is sometimes given by mistake.
_CHECKPOINT_SUFFIXES = (".safetensors", ".json")


def _refused(path: Path, reason: str) -> DataFileError:
    return DataFileError(f"{path}: {reason} (a data file is an .npz written by `{HOW_TO_MAKE}`)")


def load_data(path: str | Path) -> Trajectories:
    """Read a file written by :func:`save_data` (or an older pivoted ``q``/``omega`` file), checked whole
    before anyone uses it: an archive of the package's arrays, metadata that names a known configuration
    space and a control period (finite, > 0), at least one trajectory of at least one step, consistent
    shapes, finite states and controls, unit quaternions (:data:`DATA_UNIT_NORM_TOLERANCE`).

    Raises:
        DataFileNotFound: (a ``FileNotFoundError``) no such file (the message says how to make one).
        DataFileError: (a ``ValueError``) a folder, an empty or unreadable file, a checkpoint, or data that
            fail one of the checks above (the message names the first entry that does).
    """
    path = Path(path)
    if not path.exists():
        raise DataFileNotFound(f"data file not found: {path} (make one with `{HOW_TO_MAKE}`)")
    if path.is_dir():
        raise _refused(path, "a folder, not a data file")
    if path.suffix.lower() in _CHECKPOINT_SUFFIXES:
        raise _refused(path, "a checkpoint's file, not data (give it as --checkpoint)")
    if path.stat().st_size == 0:
        raise _refused(path, "the file is empty")
    try:
        with np.load(path, allow_pickle=False) as archive:
            files = set(archive.files)
            if "metadata" not in files or "u" not in files or not ("state" in files or {"q", "omega"} <= files):
                raise _refused(path, f"not an fvin_mpc data file (arrays {sorted(files)})")
            metadata = json.loads(str(archive["metadata"]))
            u = archive["u"].astype(np.float64)
            arrays = ((archive["state"].astype(np.float64),) if "state" in files
                      else (archive["q"].astype(np.float64), archive["omega"].astype(np.float64)))
    except DataFileError:
        raise
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, KeyError, TypeError) as error:
        reason = str(error).splitlines()[0] if str(error) else type(error).__name__
        if "pickle" in reason:  # NumPy's guess for bytes that are no archive: what it suggests would run them
            reason = "its bytes are no .npz archive"
        raise _refused(path, f"not a NumPy archive of trajectories ({reason[:120]})") from None
    if not isinstance(metadata, dict):
        raise _refused(path, "its metadata is not a JSON object")
    try:
        data = (Trajectories(arrays[0], u, metadata) if len(arrays) == 1
                else Trajectories.from_parts(arrays[0], arrays[1], u, metadata))
    except ValueError as error:
        raise _refused(path, str(error)) from None
    check_trajectories(data, str(path))
    return data


def check_trajectories(data: Trajectories, name: str = "the data") -> None:
    """``DataFileError`` unless ``data`` hold trajectories every consumer can use (:func:`load_data`'s checks)."""
    period = data.metadata.get("control_period")
    if not isinstance(period, (int, float)) or isinstance(period, bool) or not (math.isfinite(period) and period > 0):
        raise DataFileError(f"{name}: the metadata's control_period must be finite seconds > 0, got {period!r}")
    if data.u.shape[0] < 1 or data.u.shape[1] < 1 or data.u.shape[2] < 1:
        raise DataFileError(f"{name}: no transitions (u has shape {data.u.shape}: trajectories, steps, controls)")
    for label, values in (("state", data.state), ("u", data.u)):
        bad = np.argwhere(~np.isfinite(values))
        if bad.size:
            where = tuple(int(i) for i in bad[0])
            count = f"{len(bad)} entries are" if len(bad) > 1 else "the only entry that is"
            raise DataFileError(f"{name}: {label}{list(where)} is {values[where]} ({count} NaN or infinite); every "
                                "state and control must be finite")
    for entries in data.space.layout.quaternions:
        error = np.abs(np.linalg.norm(data.state[..., entries], axis=-1) - 1.0)
        if float(error.max()) > DATA_UNIT_NORM_TOLERANCE:
            where = tuple(int(i) for i in np.unravel_index(int(np.argmax(error)), error.shape))
            raise DataFileError(f"{name}: the quaternion of trajectory {where[0]}, step {where[1]} has norm "
                                f"{1.0 + float(error[where]):.6g} (unit quaternions to {DATA_UNIT_NORM_TOLERANCE:g} "
                                "expected): not data the package recorded")
