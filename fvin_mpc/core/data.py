"""Trajectory data sets: ``.npz`` files of ``(q, ω, u)`` with their metadata.

Arrays (``N`` trajectories of ``T`` steps, ``m`` controls):
``q (N, T+1, 4)``, ``omega (N, T+1, 3)``, ``u (N, T, m)``; ``metadata`` is a JSON
string (scene, body, control period, seed, counts, control modes).

:class:`Trajectories` is what every layout shares (counts, control period, subsets, windows, the
``.npz`` files); the free-body layout is :class:`fvin_mpc.core.free_body_data.FreeBodyData`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from fvin_mpc.core.errors import DataFileError, DataFileNotFound


class Trajectories:
    """Base of the trajectory data sets (frozen dataclasses): per-trajectory arrays whose first
    axis counts trajectories — states ``(N, T+1, …)`` and the controls ``u (N, T, m)`` — and
    ``metadata`` (``control_period`` at least)."""

    u: np.ndarray
    metadata: dict[str, Any]

    def _state_arrays(self) -> tuple[np.ndarray, ...]:
        """The state arrays ``(N, T+1, …)`` in field order."""
        return tuple(getattr(self, f.name) for f in fields(self) if f.name not in ("u", "metadata"))  # type: ignore[arg-type]

    @property
    def num_trajectories(self) -> int:
        return self.u.shape[0]

    @property
    def num_transitions(self) -> int:
        return self.u.shape[0] * self.u.shape[1]

    @property
    def control_period(self) -> float:
        return float(self.metadata["control_period"])

    def subset(self, indices: np.ndarray) -> Any:
        """The trajectories ``indices`` (same type, a copy of the metadata)."""
        arrays = {f.name: getattr(self, f.name)[indices] for f in fields(self) if f.name != "metadata"}  # type: ignore[arg-type]
        return type(self)(**arrays, metadata=dict(self.metadata))

    def windows(self, length: int) -> tuple[np.ndarray, ...]:
        """All overlapping windows of ``length`` steps: each state array ``(W, length+1, …)`` in field
        order, then ``u (W, length, m)``."""
        steps = self.u.shape[1]
        if not 1 <= length <= steps:
            raise ValueError(f"window length {length} must be in [1, {steps}]")
        starts = range(steps - length + 1)
        states = tuple(np.concatenate([a[:, s : s + length + 1] for s in starts]) for a in self._state_arrays())
        return (*states, np.concatenate([self.u[:, s : s + length] for s in starts]))


def save_arrays(path: str | Path, arrays: Mapping[str, np.ndarray], metadata: Mapping[str, Any]) -> Path:
    """Write ``arrays`` and ``metadata`` (as a JSON string) to a compressed ``.npz``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays, metadata=json.dumps(metadata))
    return path


def load_arrays(path: str | Path, names: tuple[str, ...], kind: str, how_to_make: str) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The float64 arrays ``names`` and the metadata of a file written by :func:`save_arrays`;
    ``DataFileNotFound`` (a ``FileNotFoundError``) saying ``how_to_make`` one, ``DataFileError`` (a
    ``ValueError``) when one is missing."""
    path = Path(path)
    if not path.exists():
        raise DataFileNotFound(f"data file not found: {path} (make one with `{how_to_make}`)")
    with np.load(path, allow_pickle=False) as archive:
        missing = {*names, "metadata"} - set(archive.files)
        if missing:
            raise DataFileError(f"{path}: not a {kind} file (missing {sorted(missing)})")
        return ({name: archive[name].astype(np.float64) for name in names},
                json.loads(str(archive["metadata"])))


@dataclass(frozen=True)
class TrajectoryData(Trajectories):
    q: np.ndarray
    omega: np.ndarray
    u: np.ndarray
    metadata: dict[str, Any]

    def __post_init__(self) -> None:
        n, t1 = self.q.shape[:2]
        if self.q.shape != (n, t1, 4) or self.omega.shape != (n, t1, 3) or self.u.shape[:2] != (n, t1 - 1):
            raise ValueError(
                f"inconsistent trajectory shapes q {self.q.shape}, omega {self.omega.shape}, u {self.u.shape}"
            )

    def windows(self, length: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # type: ignore[override]
        """All overlapping windows of ``length`` steps: ``q (W, length+1, 4)``, ``ω``, ``u (W, length, m)``."""
        return super().windows(length)  # type: ignore[return-value]


def save_data(path: str | Path, data: TrajectoryData) -> Path:
    return save_arrays(path, {"q": data.q, "omega": data.omega, "u": data.u}, data.metadata)


def load_data(path: str | Path) -> TrajectoryData:
    arrays, metadata = load_arrays(path, ("q", "omega", "u"), "fvin_mpc data", "python -m fvin_mpc.collect")
    return TrajectoryData(**arrays, metadata=metadata)
