"""Free-body trajectory data sets: ``.npz`` files of 13-number states ``(x, q, v, ω)`` and controls.

Arrays (``N`` trajectories of ``T`` steps, ``m`` controls): ``state (N, T+1, 13)`` in the layout of
``docs/r3s3.md`` (position and velocity world frame, ``q = (w, x, y, z)``, ω body frame),
``u (N, T, m)``; ``metadata`` a JSON string (scene, control period, seed, counts, collector). Counts,
subsets, windows and the files are :class:`fvin_mpc.core.data.Trajectories`', shared with the
pivoted :class:`~fvin_mpc.core.data.TrajectoryData`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fvin_mpc.core.data import Trajectories, load_arrays, save_arrays
from fvin_mpc.core.fvin_r3s3 import FREE_STATE_DIM

#: ``metadata["configuration_space"]`` of free-body data (pivoted data has none).
CONFIGURATION_SPACE = "R3xS3"


@dataclass(frozen=True)
class FreeBodyData(Trajectories):
    state: np.ndarray
    u: np.ndarray
    metadata: dict[str, Any]

    def __post_init__(self) -> None:
        n, t1 = self.state.shape[:2]
        if self.state.shape != (n, t1, FREE_STATE_DIM) or self.u.shape[:2] != (n, t1 - 1) or self.u.ndim != 3:
            raise ValueError(f"inconsistent free-body trajectory shapes state {self.state.shape}, u {self.u.shape}")

    def windows(self, length: int) -> tuple[np.ndarray, np.ndarray]:  # type: ignore[override]
        """All overlapping windows of ``length`` steps: ``state (W, length+1, 13)``, ``u (W, length, m)``."""
        return super().windows(length)  # type: ignore[return-value]


def save_free_body_data(path: str | Path, data: FreeBodyData) -> Path:
    return save_arrays(path, {"state": data.state, "u": data.u},
                       {**data.metadata, "configuration_space": CONFIGURATION_SPACE})


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
    arrays, metadata = load_arrays(path, ("state", "u"), "free-body data",
                                   "python -m fvin_mpc.collect --scene quadrotor")
    return FreeBodyData(**arrays, metadata=metadata)
