"""Trajectory data sets: ``.npz`` files of ``(q, ω, u)`` with their metadata.

Arrays (``N`` trajectories of ``T`` steps, ``m`` controls):
``q (N, T+1, 4)``, ``omega (N, T+1, 3)``, ``u (N, T, m)``; ``metadata`` is a JSON
string (scene, body, control period, seed, counts, control modes).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np


@dataclass(frozen=True)
class TrajectoryData:
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

    @property
    def num_trajectories(self) -> int:
        return self.q.shape[0]

    @property
    def num_transitions(self) -> int:
        return self.u.shape[0] * self.u.shape[1]

    @property
    def control_period(self) -> float:
        return float(self.metadata["control_period"])

    def subset(self, indices: np.ndarray) -> "TrajectoryData":
        return TrajectoryData(self.q[indices], self.omega[indices], self.u[indices], dict(self.metadata))

    def windows(self, length: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All overlapping windows of ``length`` steps: ``q (W, length+1, 4)``, ``ω``, ``u (W, length, m)``."""
        steps = self.u.shape[1]
        if not 1 <= length <= steps:
            raise ValueError(f"window length {length} must be in [1, {steps}]")
        starts = range(steps - length + 1)
        q = np.concatenate([self.q[:, s : s + length + 1] for s in starts])
        omega = np.concatenate([self.omega[:, s : s + length + 1] for s in starts])
        u = np.concatenate([self.u[:, s : s + length] for s in starts])
        return q, omega, u


def save_data(path: str | Path, data: TrajectoryData) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, q=data.q, omega=data.omega, u=data.u, metadata=json.dumps(data.metadata))
    return path


def load_data(path: str | Path) -> TrajectoryData:
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"data file not found: {path} (make one with `python -m fvin_mpc.collect`)")
    with np.load(path, allow_pickle=False) as archive:
        missing = {"q", "omega", "u", "metadata"} - set(archive.files)
        if missing:
            raise ValueError(f"{path}: not a fvin_mpc data file (missing {sorted(missing)})")
        return TrajectoryData(
            q=archive["q"].astype(np.float64),
            omega=archive["omega"].astype(np.float64),
            u=archive["u"].astype(np.float64),
            metadata=json.loads(str(archive["metadata"])),
        )
