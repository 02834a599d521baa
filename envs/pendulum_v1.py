"""Convert between Gymnasium's ``Pendulum-v1`` and the ``pendulum`` scene's ``(q, ω)``.

Pendulum-v1 (unmodified, ``gymnasium.make("Pendulum-v1")``) observes ``[cos θ, sin θ, θ̇]`` with
θ = 0 *upright*. The ``pendulum`` scene has θ = 0 *hanging* (identity quaternion), the hinge
about +y, ``q = (cos θ/2, 0, sin θ/2, 0)`` and ``ω = (0, θ̇, 0)``. Both integrate
``θ̈ = ∓15 sin θ + 3τ`` with the same torque sign, so (checked numerically in
``tests/test_envs.py``)::

    θ_scene = θ_v1 + π  (mod 2π),   θ̇_scene = θ̇_v1,   τ_scene = τ_v1.

Upright (θ_v1 = 0) is ``q = (0, 0, 1, 0)``, the scene's goal. Functions accept a trailing axis
(``(..., 3)`` observations, ``(..., 7)`` states ``x = (q, ω)``) and return float64.
"""

from __future__ import annotations

import numpy as np

from fvin_mpc.core.space import S3

_ATTITUDE = S3.layout.attitude(by=__name__)


def scene_angle_from_v1(theta_v1):
    """Hinge angle of the scene (θ = 0 hanging) from Pendulum-v1's θ (0 upright), wrapped to [−π, π)."""
    return np.mod(np.asarray(theta_v1, dtype=np.float64) + 2.0 * np.pi, 2.0 * np.pi) - np.pi


def v1_angle_from_scene(theta_scene):
    """Pendulum-v1's θ (0 upright) from the scene's hinge angle, wrapped to [−π, π)."""
    return np.mod(np.asarray(theta_scene, dtype=np.float64), 2.0 * np.pi) - np.pi


def state_from_v1_observation(observation) -> np.ndarray:
    """``[cos θ, sin θ, θ̇]`` of Pendulum-v1 → the scene's state ``x = (q, ω)``, shape ``(..., 7)``."""
    observation = np.asarray(observation, dtype=np.float64)
    if observation.shape[-1:] != (3,):
        raise ValueError(f"a Pendulum-v1 observation has shape (..., 3), got {observation.shape}")
    cos_theta, sin_theta, theta_dot = np.moveaxis(observation, -1, 0)
    half = 0.5 * (np.arctan2(sin_theta, cos_theta) + np.pi)  # half of θ_scene = θ_v1 + π
    zero = np.zeros_like(half)
    q = np.stack([np.cos(half), zero, np.sin(half), zero], axis=-1)
    omega = np.stack([zero, theta_dot, zero], axis=-1)
    return S3.layout.join(q, omega)


def v1_observation_from_state(x) -> np.ndarray:
    """The scene's state ``x = (q, ω)`` ``(..., 7)`` → Pendulum-v1's ``[cos θ, sin θ, θ̇]``, shape ``(..., 3)``.

    Sign invariant in ``q``. Only the rotation about y and ``ω_y`` are used: ``q`` is assumed
    to be a rotation about the hinge axis, ``(cos θ/2, 0, sin θ/2, 0)``.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.shape[-1:] != (S3.state_dim,):
        raise ValueError(f"expected states x = (q, ω) of shape (..., {S3.state_dim}), got {x.shape}")
    q, omega = x[..., _ATTITUDE.quaternion], x[..., _ATTITUDE.omega]
    w, y = q[..., 0], q[..., 2]
    norm2 = w * w + y * y
    cos_scene, sin_scene = (w * w - y * y) / norm2, 2.0 * w * y / norm2
    # θ_v1 = θ_scene − π: cos and sin change sign.
    return np.stack([-cos_scene, -sin_scene, omega[..., 1]], axis=-1)
