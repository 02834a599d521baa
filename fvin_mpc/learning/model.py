"""The trainable torch models (float64, batched): one shell, :class:`FVINModel`, parametrized by the
configuration space of its config (:mod:`fvin_mpc.core.space`).

All math lives in the core: the space's step, energy and learned terms. The shell owns the
parameters and the tensor layout of training: a rollout takes and returns the orientation ``q``
apart from the ``rest`` of the state (every other entry, in state order, each scaled by
``rest_scale`` so that one loss weighs positions, velocities and angular velocities together;
:func:`fvin_mpc.learning.training.rollout_loss`). :func:`model_for` makes the model of a config.

Two spaces have faster rollouts with the same values (tested against the shell's generic one):
:class:`S3FVIN` and :class:`SO3FVIN` (which carries ``R`` from step to step). Speed only, for S³
(``docs/training.md``; the values are those of the shared step, tested against NumPy and CasADi):

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

from fvin_mpc.core import fvin, fvin_so3, s3, so3
from fvin_mpc.core.backend import TorchOps, get_ops
from fvin_mpc.core.networks import LearnedTerms, ModelConfig
from fvin_mpc.core.networks_so3 import LearnedSO3Terms, SO3ModelConfig
from fvin_mpc.core.space import S3, SO3, ConfigurationSpace, space_of_config

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
        self.hinge_axis = fvin.hinge_axis_of(terms)
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
    """What every trainable model owns: its ``config`` and ``weights``, an ``nn.ParameterDict`` of
    float64 copies of a weight dictionary (the names the core's terms and the checkpoints use).

    Args:
        config: architecture and integration settings.
        weights: initial weights (name → array); ``None``: ``init_weights(config, seed)``.
        seed: seed of the default initialization.
        init_weights, check_weights: the model's initialization and weight check.
    """

    def __init__(self, config: Any, weights: Mapping[str, np.ndarray] | None, seed: int,
                 init_weights: Callable[[Any, int], Mapping[str, np.ndarray]],
                 check_weights: Callable[[Mapping[str, Any], Any], None]) -> None:
        super().__init__()
        self.config = config
        weights = init_weights(config, seed) if weights is None else weights
        check_weights(weights, config)
        self.weights = nn.ParameterDict(
            {
                name: nn.Parameter(torch.as_tensor(np.asarray(value), dtype=DTYPE).clone())
                for name, value in weights.items()
            }
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


class FVINModel(LearnedModel):
    """A forced variational integrator network on the configuration space of ``config`` (float64).

    Args:
        config: a model config of a registered space (its architecture and integration settings).
        weights: initial weights (name → array); by default the space's seeded initialization.
        seed: seed of the default initialization.
        rest_scale: per-entry scales of the training layout's ``rest`` (module docstring); default 1.
        initial_scales: the space's initial physical scales, passed to its initialization.
    """

    _ops: Any = get_ops("torch")

    def __init__(self, config: Any, weights: Mapping[str, np.ndarray] | None = None, seed: int = 0,
                 rest_scale: Any = None, **initial_scales: Any) -> None:
        space = space_of_config(config)
        super().__init__(config, weights, seed, lambda c, s: space.init_weights(c, s, **initial_scales),
                         space.check_weights)
        self.space: ConfigurationSpace = space
        rest_dim = space.state_dim - 4
        scale = np.ones(rest_dim) if rest_scale is None else np.broadcast_to(np.asarray(rest_scale, float), (rest_dim,))
        self.register_buffer("rest_scale", torch.as_tensor(np.array(scale), dtype=DTYPE), persistent=False)
        self._step_options = space.step_options(config)

    def terms(self) -> Any:
        return self.space.learned_terms(self.weights, self.config, self._ops)

    def step_state(self, state: torch.Tensor, u: torch.Tensor,
                   newton_iters: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """One step of the space for a batch: ``state (B, n)``, ``u (B, m)`` → ``(state_next, residual)``."""
        ops = get_ops("torch")  # stacked states are (B, n) whatever the networks' layout
        return self.space.step(state, u, self.terms(), self.config.step_size, newton_iters or self.config.newton_iters,
                               ops, **self._step_options)

    def energy_state(self, state: torch.Tensor) -> torch.Tensor:
        return self.space.energy(state, self.terms(), get_ops("torch"))

    # -- the training layout ------------------------------------------------------
    def pack(self, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``state (..., n)`` → ``(q (..., 4k), rest (..., n − 4k))`` (:meth:`StateLayout.split
        <fvin_mpc.core.blocks.StateLayout.split>`), ``rest`` scaled by ``rest_scale``."""
        quaternion, other, _ = self.space.layout.split_entries
        return state[..., quaternion], state[..., other] * self.rest_scale

    def unpack(self, q: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`pack`."""
        return torch.cat([q, rest / self.rest_scale], dim=-1)[..., self.space.layout.split_entries[2]]

    def rollout(self, q0: torch.Tensor, rest0: torch.Tensor, controls: torch.Tensor,
                step: Callable[..., Any] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``T`` steps in the training layout: ``q0 (B, 4)``, ``rest0 (B, n − 4)``, ``controls (B, T, m)`` →
        ``q (B, T+1, 4)``, ``rest (B, T+1, n − 4)``. ``step`` (a compiled step) is the fast paths' only."""
        if step is not None:
            raise ValueError(f"{type(self).__name__}.rollout has no replaceable step")
        states = [self.unpack(q0, rest0)]
        for k in range(controls.shape[1]):
            states.append(self.step_state(states[-1], controls[:, k])[0])
        return self.pack(torch.stack(states, dim=1))

    def rollout_states(self, state0: torch.Tensor, controls: torch.Tensor) -> torch.Tensor:
        """``state0 (B, n)``, ``controls (B, T, m)`` → ``states (B, T+1, n)``."""
        return self.unpack(*self.rollout(*self.pack(state0), controls))

    def forward(self, state: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return self.step_state(state, u)[0]


class S3FVIN(FVINModel):
    """:class:`FVINModel` on S³ with the fast rollout (module docstring) and a step on ``(q, ω)``
    that ``torch.compile`` can take.

    Args:
        config: architecture and integration settings.
        weights: initial weights (name → array); by default ``init_weights(config, seed)``.
        seed: seed of the default initialization.
    """

    _ops = _OPS

    def __init__(self, config: ModelConfig, weights: Mapping[str, np.ndarray] | None = None, seed: int = 0) -> None:
        super().__init__(config, weights, seed)

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


def matrix_components(r: torch.Tensor) -> so3.Mat3:
    """``(B, 3, 3)`` → row tuples of ``(B,)`` components."""
    return tuple(tuple(r[..., i, j] for j in range(3)) for i in range(3))  # type: ignore[return-value]


def matrix_tensor(r: so3.Mat3) -> torch.Tensor:
    """Row tuples of ``(B,)`` components → ``(B, 3, 3)``."""
    return torch.stack([torch.stack(list(row), dim=-1) for row in r], dim=-2)


class SO3FVIN(FVINModel):
    """:class:`FVINModel` on SO(3), the paper's SO3FVIN baseline, whose rollout carries the rotation
    matrix from step to step (no quaternion round trip inside a window); states enter and leave as
    quaternions ``q (B, 4)`` — a preimage of each ``R``, which one does not matter to the sign-invariant
    loss."""

    def __init__(self, config: SO3ModelConfig, weights: Mapping[str, np.ndarray] | None = None, seed: int = 0) -> None:
        super().__init__(config, weights, seed)

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
        rotation = matrix_tensor(s3.rotation_matrix(self._ops.unstack(q)))
        rotation, omega, residual = self.step_rotation(rotation, omega, u, with_residual, newton_iters)
        return TorchStep(self.quaternion(rotation), omega, residual)

    def quaternion(self, rotation: torch.Tensor) -> torch.Tensor:
        """A unit-quaternion preimage ``(B, 4)`` of ``R (B, 3, 3)``."""
        return self._ops.stack(so3.quaternion_from_rotation(matrix_components(rotation), self._ops))

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
        return fvin_so3.total_energy(s3.rotation_matrix(self._ops.unstack(q)), self._ops.unstack(omega), self.terms())


#: The spaces whose models roll out faster than the shell's generic rollout (same values).
_FAST_ROLLOUTS: dict[ConfigurationSpace, type[FVINModel]] = {S3: S3FVIN, SO3: SO3FVIN}


def model_for(config: Any, weights: Mapping[str, np.ndarray] | None = None, seed: int = 0, **kwargs: Any) -> FVINModel:
    """The trainable model of ``config``'s configuration space (``kwargs``: :class:`FVINModel`'s
    ``rest_scale`` and initial scales, for spaces without a fast rollout)."""
    model_class = _FAST_ROLLOUTS.get(space_of_config(config), FVINModel)
    return model_class(config, weights, seed, **kwargs) if kwargs else model_class(config, weights, seed)


def _components(x: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """``x (*batch, n)`` → ``n`` components ``(*batch,)``."""
    return tuple(x.unbind(-1))


def _tensor(components: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """Components ``(*batch,)`` → ``(*batch, n)``."""
    return get_ops("torch").stack(components)


def quaternion_to_tensor(q: s3.Quat) -> torch.Tensor:
    return _tensor(q)
