"""The trainable torch SO3FVIN (float64, batched) — a thin shell around the shared SO(3) step.

All math lives in :mod:`fvin_mpc.core.so3`, :mod:`fvin_mpc.core.fvin_so3` and
:mod:`fvin_mpc.core.networks_so3`. The interface is :class:`fvin_mpc.learning.model.S3FVIN`'s
(``weights``, ``config``, ``step``, ``rollout(q0, omega0, controls)``, ``energy``) so that
:func:`fvin_mpc.learning.training.train` (``model_factory=SO3FVIN``) trains either on the same
data, loss and early stopping:
states enter and leave as quaternions ``q (B, 4)`` (the data's convention); inside a rollout the
model carries ``R (B, 3, 3)`` and returns a quaternion preimage of each ``R`` (the loss is sign
invariant, so which preimage does not matter).
"""

from __future__ import annotations

from typing import Any, Callable, Mapping

import numpy as np
import torch

from fvin_mpc.core import fvin_so3, s3, so3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.data import TrajectoryData
from fvin_mpc.core.networks_so3 import LearnedSO3Terms, SO3ModelConfig, check_weights, init_weights
from fvin_mpc.learning.model import DTYPE, LearnedModel, TorchStep, rollout_with_step


def matrix_components(r: torch.Tensor) -> so3.Mat3:
    """``(B, 3, 3)`` → row tuples of ``(B,)`` components."""
    return tuple(tuple(r[..., i, j] for j in range(3)) for i in range(3))  # type: ignore[return-value]


def matrix_tensor(r: so3.Mat3) -> torch.Tensor:
    """Row tuples of ``(B,)`` components → ``(B, 3, 3)``."""
    return torch.stack([torch.stack(list(row), dim=-1) for row in r], dim=-2)


class SO3FVIN(LearnedModel):
    """Forced variational integrator network on SO(3) (float64), the paper's SO3FVIN baseline.
    ``config``, ``weights``, ``seed``: as :class:`~fvin_mpc.learning.model.LearnedModel`'s, with
    :mod:`fvin_mpc.core.networks_so3`'s initialization."""

    def __init__(self, config: SO3ModelConfig, weights: Mapping[str, np.ndarray] | None = None, seed: int = 0) -> None:
        super().__init__(config, weights, seed, init_weights, check_weights)
        self._ops = get_ops("torch")

    def terms(self) -> LearnedSO3Terms:
        return LearnedSO3Terms(self.weights, self.config, self._ops)

    def step_rotation(self, rotation: torch.Tensor, omega: torch.Tensor, u: torch.Tensor, with_residual: bool = False,
                      newton_iters: int | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """One step on rotation matrices: ``R (B, 3, 3)``, ``omega (B, 3)``, ``u (B, m)``."""
        ops = self._ops
        out = fvin_so3.so3_step(matrix_components(rotation), ops.unstack(omega), ops.unstack(u), self.terms(),
                                self.config.step_size, newton_iters or self.config.newton_iters, ops, with_residual)
        return matrix_tensor(out.rotation), ops.stack(out.omega), out.residual

    def step(self, q: torch.Tensor, omega: torch.Tensor, u: torch.Tensor, with_residual: bool = False,
             newton_iters: int | None = None) -> TorchStep:
        """One step from quaternions (``q (B, 4)``; its sign is irrelevant): ``R = R(q)`` in, a preimage out."""
        ops = self._ops
        rotation = matrix_tensor(s3.rotation_matrix(ops.unstack(q)))
        rotation, omega, residual = self.step_rotation(rotation, omega, u, with_residual, newton_iters)
        return TorchStep(self.quaternion(rotation), omega, residual)

    def quaternion(self, rotation: torch.Tensor) -> torch.Tensor:
        """A unit-quaternion preimage ``(B, 4)`` of ``R (B, 3, 3)``."""
        ops = self._ops
        return ops.stack(so3.quaternion_from_rotation(matrix_components(rotation), ops))

    def rollout(self, q0: torch.Tensor, omega0: torch.Tensor, controls: torch.Tensor,
                step: Callable[..., TorchStep] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Roll out ``T`` steps: ``controls (B, T, m)`` → ``q (B, T+1, 4)``, ``omega (B, T+1, 3)``.

        The rotation matrix is carried from step to step; ``step`` (e.g. a ``torch.compile``-d
        :meth:`step`) replaces that by steps on quaternions."""
        if step is not None:
            return rollout_with_step(step, q0, omega0, controls)
        rotation = matrix_tensor(s3.rotation_matrix(self._ops.unstack(q0)))
        rotations, omegas = [], [omega0]
        for k in range(controls.shape[1]):
            rotation, omega, _ = self.step_rotation(rotation, omegas[-1], controls[:, k])
            rotations.append(rotation)
            omegas.append(omega)
        qs = self.quaternion(torch.stack(rotations, dim=1))
        return torch.cat([q0[:, None], qs], dim=1), torch.stack(omegas, dim=1)

    def energy(self, q: torch.Tensor, omega: torch.Tensor) -> torch.Tensor:
        ops = self._ops
        return fvin_so3.total_energy(s3.rotation_matrix(ops.unstack(q)), ops.unstack(omega), self.terms())

    def forward(self, q: torch.Tensor, omega: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.step(q, omega, u)
        return out.q, out.omega


def loss_and_gradient_cpu_s(so3: bool, config: Any, data: TrajectoryData, repeats: int, seed: int = 0) -> float:
    """Median thread CPU seconds of one full-batch rollout loss with its gradient — the least any
    optimizer iteration pays — for a freshly initialized SO3FVIN (``so3``) or S3FVIN with ``config``
    on ``data``'s windows (the training's default window and weight), one torch thread."""
    import time

    from fvin_mpc.learning.model import S3FVIN
    from fvin_mpc.learning.timing import torch_threads
    from fvin_mpc.learning.training import TrainSettings, rollout_loss

    settings = TrainSettings()
    windows = tuple(torch.as_tensor(a, dtype=DTYPE) for a in data.windows(settings.window))
    network = (SO3FVIN if so3 else S3FVIN)(config, seed=seed)
    times = []
    with torch_threads(1):
        for _ in range(repeats + 1):  # the first call warms up
            network.zero_grad()
            start = time.thread_time()
            rollout_loss(network, *windows, settings.omega_weight).backward()
            times.append(time.thread_time() - start)
    return float(np.median(times[1:]))
