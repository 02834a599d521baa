"""Array checks at numeric boundaries.

A state is one float64 array whose blocks (:class:`fvin_mpc.core.blocks.StateLayout`) say where each
part sits: a pivoted body's ``x = (q_w, q_x, q_y, q_z, ω_x, ω_y, ω_z)``, the orientation quaternion
(Hamilton, ``(w, x, y, z)``, MuJoCo's order) followed by the body-frame angular velocity (rad/s) —
``DESIGN.md``'s ``x = (q, ω)``. Inside the math core the parts travel as tuples of components
(``fvin_mpc.core.s3``).

Policy for measured states (:meth:`fvin_mpc.core.blocks.StateLayout.check`, the one check): a
quaternion within :data:`UNIT_NORM_TOLERANCE` of unit norm is normalized (float32 observations,
sensor rounding); anything further raises ``ValueError`` — a non-unit ``q`` is not a rotation, and
silently normalizing a wrong one would hide a bug upstream. NaN/inf or a wrong shape raise too.
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: How far a measured quaternion's norm may be from 1 before it is refused.
UNIT_NORM_TOLERANCE = 1e-3
#: The identity rotation ``(w, x, y, z)``.
IDENTITY = (1.0, 0.0, 0.0, 0.0)


def as_float_array(value: Any, shape: tuple[int, ...], name: str) -> np.ndarray:
    """``value`` as a finite float64 array of ``shape``; ``ValueError`` naming ``name`` otherwise."""
    try:
        array = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as error:  # None-like, strings, dicts, ragged lists
        raise ValueError(f"{name} must be a float array of shape {shape}: {error}") from None
    if array.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} contains NaN or inf: {array}")
    return array


def unit_quaternion(value: Any, name: str = "quaternion") -> np.ndarray:
    """A given orientation (goal, rest, a joint's qpos) as a unit quaternion ``(4,)``.

    Any finite non-zero 4-vector is accepted and normalized: this is for orientations a user
    writes down, not for measurements (see :meth:`fvin_mpc.core.blocks.StateLayout.check`).
    """
    q = as_float_array(value, (4,), name)
    norm = float(np.linalg.norm(q))
    if norm < 1e-12:
        raise ValueError(f"{name} must be a non-zero quaternion (w, x, y, z), got {q}")
    return q / norm
