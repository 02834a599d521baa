"""Free-body trajectory data sets: ``.npz`` files of 13-number states ``(x, q, v, ω)`` and controls.

Arrays (``N`` trajectories of ``T`` steps, ``m`` controls): ``state (N, T+1, 13)`` in the layout of
``docs/r3s3.md`` (position and velocity world frame, ``q = (w, x, y, z)``, ω body frame),
``u (N, T, m)``; ``metadata`` a JSON string (scene, control period, seed, counts, collector). The
same interface as :class:`fvin_mpc.core.data.TrajectoryData` where training needs it
(``subset``, ``num_trajectories``, ``num_transitions``, ``control_period``, ``windows``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fvin_mpc.core.fvin_r3s3 import FREE_STATE_DIM

#: ``metadata["configuration_space"]`` of free-body data (pivoted data has none).
CONFIGURATION_SPACE = "R3xS3"


@dataclass(frozen=True)
class FreeBodyData:
    state: np.ndarray
    u: np.ndarray
    metadata: dict[str, Any]

    def __post_init__(self) -> None:
        n, t1 = self.state.shape[:2]
        if self.state.shape != (n, t1, FREE_STATE_DIM) or self.u.shape[:2] != (n, t1 - 1) or self.u.ndim != 3:
            raise ValueError(f"inconsistent free-body trajectory shapes state {self.state.shape}, u {self.u.shape}")

    @property
    def num_trajectories(self) -> int:
        return self.state.shape[0]

    @property
    def num_transitions(self) -> int:
        return self.u.shape[0] * self.u.shape[1]

    @property
    def control_period(self) -> float:
        return float(self.metadata["control_period"])

    def subset(self, indices: np.ndarray) -> "FreeBodyData":
        return FreeBodyData(self.state[indices], self.u[indices], dict(self.metadata))

    def windows(self, length: int) -> tuple[np.ndarray, np.ndarray]:
        """All overlapping windows of ``length`` steps: ``state (W, length+1, 13)``, ``u (W, length, m)``."""
        steps = self.u.shape[1]
        if not 1 <= length <= steps:
            raise ValueError(f"window length {length} must be in [1, {steps}]")
        starts = range(steps - length + 1)
        return (np.concatenate([self.state[:, s : s + length + 1] for s in starts]),
                np.concatenate([self.u[:, s : s + length] for s in starts]))


def save_free_body_data(path: str | Path, data: FreeBodyData) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    metadata = {**data.metadata, "configuration_space": CONFIGURATION_SPACE}
    np.savez_compressed(path, state=data.state, u=data.u, metadata=json.dumps(metadata))
    return path


def is_free_body_data(path: str | Path) -> bool:
    """Whether ``path`` is a data file whose metadata say ``configuration_space == "R3xS3"`` (what
    :func:`save_free_body_data` writes); ``False`` for pivoted data and for a missing file."""
    path = Path(path)
    if not path.exists():
        return False
    with np.load(path, allow_pickle=False) as archive:
        if "metadata" not in archive.files:
            return False
        return json.loads(str(archive["metadata"])).get("configuration_space") == CONFIGURATION_SPACE


def load_free_body_data(path: str | Path) -> FreeBodyData:
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"data file not found: {path} (make one with `python -m fvin_mpc.collect --scene quadrotor`)")
    with np.load(path, allow_pickle=False) as archive:
        missing = {"state", "u", "metadata"} - set(archive.files)
        if missing:
            raise ValueError(f"{path}: not a free-body data file (missing {sorted(missing)})")
        return FreeBodyData(state=archive["state"].astype(np.float64), u=archive["u"].astype(np.float64),
                            metadata=json.loads(str(archive["metadata"])))
