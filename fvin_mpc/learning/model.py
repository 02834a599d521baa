"""The trainable torch S3FVIN (float64, batched) — a thin shell around the shared step.

All math lives in :mod:`fvin_mpc.s3`, :mod:`fvin_mpc.fvin` and
:mod:`fvin_mpc.networks`; this module only owns the parameters and the tensor layout.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Mapping

import numpy as np
import torch
from torch import nn

from fvin_mpc.core import fvin, s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.networks import LearnedTerms, ModelConfig, check_weights, init_weights

DTYPE = torch.float64


@dataclass(frozen=True)
class TorchStep:
    """A batch of steps: ``q (B, 4)``, ``omega (B, 3)``, ``residual (B,)`` or ``None``."""

    q: torch.Tensor
    omega: torch.Tensor
    residual: torch.Tensor | None


class S3FVIN(nn.Module):
    """Forced variational integrator network on S³ (float64).

    Args:
        config: architecture and integration settings.
        weights: initial weights (name → array); by default ``init_weights(config, seed)``.
        seed: seed of the default initialization.
    """

    def __init__(self, config: ModelConfig, weights: Mapping[str, np.ndarray] | None = None, seed: int = 0) -> None:
        super().__init__()
        self.config = config
        weights = init_weights(config, seed) if weights is None else weights
        check_weights(weights, config)
        self.weights = nn.ParameterDict(
            {name: nn.Parameter(torch.as_tensor(np.asarray(value), dtype=DTYPE).clone()) for name, value in weights.items()}
        )
        self._ops = get_ops("torch")

    def terms(self) -> LearnedTerms:
        return LearnedTerms(self.weights, self.config, self._ops)

    def numpy_weights(self) -> dict[str, np.ndarray]:
        return {name: p.detach().cpu().numpy().copy() for name, p in self.weights.items()}

    def step(self, q: torch.Tensor, omega: torch.Tensor, u: torch.Tensor, with_residual: bool = False,
             newton_iters: int | None = None) -> TorchStep:
        """One step for a batch: ``q (B, 4)``, ``omega (B, 3)``, ``u (B, m)``."""
        ops = self._ops
        result = fvin.fvin_step(
            ops.unstack(q), ops.unstack(omega), ops.unstack(u), self.terms(),
            self.config.step_size, newton_iters or self.config.newton_iters, ops, with_residual=with_residual,
        )
        return TorchStep(ops.stack(result.q), ops.stack(result.omega), result.residual)

    def rollout(self, q0: torch.Tensor, omega0: torch.Tensor, controls: torch.Tensor,
                step: Callable[..., TorchStep] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Roll out ``T`` steps: ``controls (B, T, m)`` → ``q (B, T+1, 4)``, ``omega (B, T+1, 3)``.

        ``step`` replaces :meth:`step` (e.g. a ``torch.compile``-d version of it)."""
        step = step or self.step
        qs, omegas = [q0], [omega0]
        for k in range(controls.shape[1]):
            out = step(qs[-1], omegas[-1], controls[:, k])
            qs.append(out.q)
            omegas.append(out.omega)
        return torch.stack(qs, dim=1), torch.stack(omegas, dim=1)

    def energy(self, q: torch.Tensor, omega: torch.Tensor) -> torch.Tensor:
        ops = self._ops
        return fvin.total_energy(ops.unstack(q), ops.unstack(omega), self.terms())

    def forward(self, q: torch.Tensor, omega: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.step(q, omega, u)
        return out.q, out.omega


def quaternion_to_tensor(q: s3.Quat) -> torch.Tensor:
    return get_ops("torch").stack(q)
