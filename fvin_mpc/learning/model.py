"""The trainable torch S3FVIN (float64, batched) — a thin shell around the shared step.

All math lives in :mod:`fvin_mpc.s3`, :mod:`fvin_mpc.fvin` and
:mod:`fvin_mpc.networks`; this module only owns the parameters and the tensor layout.

Two things here are for speed only (``docs/training.md``; the values are those of the shared
step, tested against NumPy and CasADi):

- the networks see their inputs feature-first (:class:`FeatureFirstTorchOps`: a vector is
  ``(n, *batch)``), which makes every layer one ``addmm`` on a wide, contiguous matrix instead
  of a thin ``(batch, n) @ (n, out)`` product (≈ 3× faster on this model's widths);
- :meth:`S3FVIN.rollout` evaluates ``J``, ``∇U`` (and ``D``) at each ``q_{k+1}`` once: the step
  that produced ``q_{k+1}`` needs them to finish and the next step needs them to start
  (:class:`RolloutTerms`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np
import torch
from torch import nn

from fvin_mpc.core import fvin, s3
from fvin_mpc.core.backend import TorchOps, get_ops
from fvin_mpc.core.networks import LearnedTerms, ModelConfig, check_weights, init_weights

DTYPE = torch.float64


class FeatureFirstTorchOps(TorchOps):
    """torch :class:`~fvin_mpc.core.backend.Ops` whose vectors are ``(n, *batch)`` (components
    stacked on the first dimension) instead of ``(*batch, n)``.

    The networks' layers then are ``addmm(b, W, x)`` on ``x (in, batch)``: wide, contiguous
    products that torch's CPU kernels run several times faster than ``linear`` on a
    ``(batch, in)`` matrix a few columns wide, and unstacking gives contiguous components.

    A single column (one window inside LM's ``torch.func.vmap``) is multiplied element-wise and
    summed instead: as a matrix product, vmap would turn it into a batch of tiny ``bmm``s and its
    weight gradient into a batch of tiny outer products, far slower."""

    name = "torch"

    def stack(self, components):
        tensors = [c if isinstance(c, torch.Tensor) else torch.as_tensor(c, dtype=DTYPE) for c in components]
        return torch.stack(torch.broadcast_tensors(*tensors), dim=0)

    def unstack(self, vector):
        return tuple(vector.unbind(0))

    def linear(self, vector, weight, bias):
        flat = vector.reshape(vector.shape[0], -1)
        if flat.shape[1] == 1:  # one window inside torch.func.vmap (class docstring)
            out = (weight * flat[:, 0]).sum(-1, keepdim=True) + bias[:, None]
        else:
            out = torch.addmm(bias[:, None], weight, flat)
        return out.reshape((weight.shape[0],) + vector.shape[1:])

    def linear_transpose(self, vector, weight):
        flat = vector.reshape(vector.shape[0], -1)
        if flat.shape[1] == 1:
            out = (weight * flat).sum(0)[:, None]
        else:
            out = weight.T @ flat
        return out.reshape((weight.shape[1],) + vector.shape[1:])


_OPS = FeatureFirstTorchOps()


class RolloutTerms:
    """:class:`~fvin_mpc.core.fvin.RigidBodyTerms` that evaluate each term once per
    configuration during one rollout.

    Step ``k`` finishes with ``J``, ``∇U`` and ``D`` at ``q_{k+1}`` and step ``k+1`` starts with
    them at the same ``q_{k+1}``; the rollout passes the very component tuple on, so results are
    remembered by the identity of that tuple (held here, so identities stay unique). Values are
    those of ``terms``, unchanged."""

    def __init__(self, terms: LearnedTerms) -> None:
        self.terms = terms
        self.control_dim = terms.control_dim
        self.constant_inertia = terms.constant_inertia
        self._memory: dict[tuple[str, int], tuple[s3.Quat, object]] = {}

    def _remembered(self, name: str, q: s3.Quat):
        key = (name, id(q))
        hit = self._memory.get(key)
        if hit is not None and hit[0] is q:
            return hit[1]
        value = getattr(self.terms, name)(q)
        self._memory[key] = (q, value)
        return value

    def forget_all_but(self, q: s3.Quat) -> None:
        """Drop what was remembered at any configuration other than ``q`` (bounded memory)."""
        self._memory = {key: hit for key, hit in self._memory.items() if hit[0] is q}

    def inertia(self, q):
        return self._remembered("inertia", q)

    def potential(self, q):
        return self.terms.potential(q)

    def potential_gradient(self, q):
        return self._remembered("potential_gradient", q)

    def control_gain(self, q):
        return self._remembered("control_gain", q)

    def dissipation(self, q):
        return self._remembered("dissipation", q)


@dataclass(frozen=True)
class TorchStep:
    """A batch of steps: ``q (B, 4)``, ``omega (B, 3)``, ``residual (B,)`` or ``None``."""

    q: torch.Tensor
    omega: torch.Tensor
    residual: torch.Tensor | None


class LearnedModel(nn.Module):
    """What every learned model (S³, SO(3), R³ × S³) owns: its ``config`` and ``weights``, an
    ``nn.ParameterDict`` of float64 copies of a core weight dictionary (the names the core's terms
    and the checkpoints use).

    Args:
        config: architecture and integration settings.
        weights: initial weights (name → array); ``None``: ``init_weights(config, seed)``.
        seed: seed of the default initialization.
        init_weights, check_weights: the configuration space's functions from ``fvin_mpc.core``.
    """

    def __init__(self, config: Any, weights: Mapping[str, np.ndarray] | None, seed: int,
                 init_weights: Callable[[Any, int], Mapping[str, np.ndarray]],
                 check_weights: Callable[[Mapping[str, Any], Any], None]) -> None:
        super().__init__()
        self.config = config
        weights = init_weights(config, seed) if weights is None else weights
        check_weights(weights, config)
        self.weights = nn.ParameterDict(
            {name: nn.Parameter(torch.as_tensor(np.asarray(value), dtype=DTYPE).clone()) for name, value in weights.items()}
        )

    def numpy_weights(self) -> dict[str, np.ndarray]:
        return {name: p.detach().cpu().numpy().copy() for name, p in self.weights.items()}


def rollout_with_step(step: Callable[..., TorchStep], q0: torch.Tensor, omega0: torch.Tensor,
                      controls: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``T`` calls of a step function on quaternions: ``controls (B, T, m)`` → ``q (B, T+1, 4)``,
    ``omega (B, T+1, 3)`` (the rollout of a pivoted model whose step is replaced, e.g. compiled)."""
    qs, omegas = [q0], [omega0]
    for k in range(controls.shape[1]):
        out = step(qs[-1], omegas[-1], controls[:, k])
        qs.append(out.q)
        omegas.append(out.omega)
    return torch.stack(qs, dim=1), torch.stack(omegas, dim=1)


class S3FVIN(LearnedModel):
    """Forced variational integrator network on S³ (float64).

    Args:
        config: architecture and integration settings.
        weights: initial weights (name → array); by default ``init_weights(config, seed)``.
        seed: seed of the default initialization.
    """

    def __init__(self, config: ModelConfig, weights: Mapping[str, np.ndarray] | None = None, seed: int = 0) -> None:
        super().__init__(config, weights, seed, init_weights, check_weights)
        self._ops = _OPS

    def terms(self) -> LearnedTerms:
        return LearnedTerms(self.weights, self.config, self._ops)

    def step(self, q: torch.Tensor, omega: torch.Tensor, u: torch.Tensor, with_residual: bool = False,
             newton_iters: int | None = None) -> TorchStep:
        """One step for a batch: ``q (B, 4)``, ``omega (B, 3)``, ``u (B, m)``."""
        result = fvin.fvin_step(
            _components(q), _components(omega), _components(u), self.terms(),
            self.config.step_size, newton_iters or self.config.newton_iters, self._ops, with_residual=with_residual,
        )
        return TorchStep(_tensor(result.q), _tensor(result.omega), result.residual)

    def rollout(self, q0: torch.Tensor, omega0: torch.Tensor, controls: torch.Tensor,
                step: Callable[..., TorchStep] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Roll out ``T`` steps: ``controls (B, T, m)`` → ``q (B, T+1, 4)``, ``omega (B, T+1, 3)``.

        ``step`` replaces :meth:`step` (e.g. a ``torch.compile``-d version of it)."""
        if step is not None:
            return rollout_with_step(step, q0, omega0, controls)
        # Components stay components from step to step, so RolloutTerms can hand step k+1 what
        # step k computed at q_{k+1}.
        terms = RolloutTerms(self.terms())
        q, omega = _components(q0), _components(omega0)
        qs, omegas = [q], [omega]
        for k in range(controls.shape[1]):
            out = fvin.fvin_step(q, omega, _components(controls[:, k]), terms, self.config.step_size,
                                 self.config.newton_iters, self._ops)
            q, omega = out.q, out.omega
            terms.forget_all_but(q)
            qs.append(q)
            omegas.append(omega)
        stack = lambda states: torch.stack([torch.stack(c, dim=-1) for c in states], dim=1)  # noqa: E731
        return stack(qs), stack(omegas)

    def energy(self, q: torch.Tensor, omega: torch.Tensor) -> torch.Tensor:
        return fvin.total_energy(_components(q), _components(omega), self.terms())

    def forward(self, q: torch.Tensor, omega: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.step(q, omega, u)
        return out.q, out.omega


def _components(x: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """``x (*batch, n)`` → ``n`` components ``(*batch,)``."""
    return tuple(x.unbind(-1))


def _tensor(components: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """Components ``(*batch,)`` → ``(*batch, n)``."""
    return get_ops("torch").stack(components)


def quaternion_to_tensor(q: s3.Quat) -> torch.Tensor:
    return _tensor(q)
