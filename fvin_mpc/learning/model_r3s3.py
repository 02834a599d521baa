"""The trainable torch R³ × S³ model (float64, batched) — a thin shell around the shared step.

All math lives in :mod:`fvin_mpc.core.fvin_r3s3` and :mod:`fvin_mpc.core.networks_r3s3`; this
module only owns the parameters (:class:`~fvin_mpc.learning.model.LearnedModel`) and the tensor
layout, like :mod:`fvin_mpc.learning.model`.

Training layout. :func:`fvin_mpc.learning.training`'s loss and Levenberg–Marquardt take a rollout
``(q0, ω0, u) → (q, ω)`` and score ``q`` by the sign-invariant orientation error and the second
block by its squared difference, whatever its width. :meth:`R3S3FVIN.rollout` therefore takes and
returns the orientation apart and the rest of the state as one *scaled* block
``r = (s_x·x, s_v·v, ω)`` (9 entries): the scales ``s_x`` (1/m) and ``s_v`` (s/m) weigh position
and velocity errors against angular-velocity errors in that one loss.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np
import torch

from fvin_mpc.core import fvin_r3s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.networks_r3s3 import LearnedCombinedTerms, R3S3Config, check_weights, init_weights
from fvin_mpc.learning.model import LearnedModel


@dataclass(frozen=True)
class TorchFreeStep:
    """A batch of steps: ``state (B, 13)``, ``residual (B,)`` or ``None``."""

    state: torch.Tensor
    residual: torch.Tensor | None


class R3S3FVIN(LearnedModel):
    """Forced variational integrator network on R³ × S³ (float64).

    Args:
        config: architecture and integration settings.
        weights: initial weights; by default ``init_weights(config, seed)``.
        seed: seed of the default initialization.
        position_scale, velocity_scale: ``s_x``, ``s_v`` of the training layout (module docstring).
    """

    def __init__(self, config: R3S3Config, weights: Mapping[str, np.ndarray] | None = None, seed: int = 0,
                 position_scale: float = 1.0, velocity_scale: float = 1.0) -> None:
        super().__init__(config, weights, seed, init_weights, check_weights)
        self.position_scale, self.velocity_scale = float(position_scale), float(velocity_scale)
        self._ops = get_ops("torch")

    def terms(self) -> LearnedCombinedTerms:
        return LearnedCombinedTerms(self.weights, self.config, self._ops)

    def step_state(self, state: torch.Tensor, u: torch.Tensor, newton_iters: int | None = None) -> TorchFreeStep:
        """One step for a batch: ``state (B, 13)`` ``(x, q, v, ω)``, ``u (B, m)``."""
        config = self.config
        next_state, residual = fvin_r3s3.step_state(state, u, self.terms(), config.step_size,
                                                    newton_iters or config.newton_iters, self._ops, config.force_rule)
        return TorchFreeStep(next_state, residual)

    # -- the training layout ------------------------------------------------------
    def pack(self, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``state (..., 13)`` → ``(q (..., 4), r (..., 9))`` with ``r = (s_x x, s_v v, ω)``."""
        return state[..., 3:7], torch.cat([self.position_scale * state[..., :3],
                                           self.velocity_scale * state[..., 7:10], state[..., 10:]], dim=-1)

    def unpack(self, q: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`pack`."""
        return torch.cat([rest[..., :3] / self.position_scale, q, rest[..., 3:6] / self.velocity_scale,
                          rest[..., 6:]], dim=-1)

    def rollout(self, q0: torch.Tensor, rest0: torch.Tensor, controls: torch.Tensor,
                step: Callable[..., Any] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``T`` steps in the training layout: ``q0 (B, 4)``, ``rest0 (B, 9)``, ``controls (B, T, m)`` →
        ``q (B, T+1, 4)``, ``rest (B, T+1, 9)``. (``step`` is accepted for the training loop's interface
        and must be ``None``: no compiled variant.)"""
        if step is not None:
            raise ValueError("R3S3FVIN.rollout has no replaceable step")
        states = [self.unpack(q0, rest0)]
        for k in range(controls.shape[1]):
            states.append(self.step_state(states[-1], controls[:, k]).state)
        return self.pack(torch.stack(states, dim=1))

    def rollout_states(self, state0: torch.Tensor, controls: torch.Tensor) -> torch.Tensor:
        """``state0 (B, 13)``, ``controls (B, T, m)`` → ``states (B, T+1, 13)``."""
        return self.unpack(*self.rollout(*self.pack(state0), controls))

    def forward(self, state: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return self.step_state(state, u).state
