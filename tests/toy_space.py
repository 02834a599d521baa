"""A toy configuration space R¹ × S³, defined only in the tests: a bead of mass ``m`` on a vertical
rail (position ``s``, up; a spring of stiffness ``k`` to ``s = 0``, gravity ``g``, a control force
``u₀``) carrying a body on a pivot (``q``, ``ω``; torques ``u₁…``). State ``(s, q, ṡ, ω)`` (9
entries): the blocks ``(Slide(), Ball())``.

The step is separable: the rail by Velocity-Verlet under ``u₀ − k s − m g``, the rotation by the
S³ step (:func:`fvin_mpc.core.fvin.fvin_step`) on S³ terms. Nothing here edits a package module:
:data:`TOY` is a :class:`~fvin_mpc.core.space.ConfigurationSpace` (a subclass with its math as
methods) that a test registers (:func:`fvin_mpc.core.space.register`) and takes out again
(``unregister``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from fvin_mpc.core import fvin, networks
from fvin_mpc.core.backend import Ops
from fvin_mpc.core.blocks import Ball, Slide
from fvin_mpc.core.rigid_body import PivotedRigidBody
from fvin_mpc.core.space import ConfigurationSpace, StateLayout

#: ``(s, q, ṡ, ω)``: the rail's position and the body's attitude, then their rates.
RAIL_LAYOUT = StateLayout((Slide(label="rail"), Ball()), name="(s, q, ṡ, ω)")
#: The toy's model variants: its rotation's S3FVIN variant (the default first).
TOY_VARIANTS = ("sign-invariant", "plain")


@dataclass(frozen=True)
class ToyConfig(networks.ModelFields):
    """The toy space's learned-model config: the rotation is an S3FVIN (its variant and widths), the
    rail three learned constants (``m``, ``k`` through softplus, ``g``). ``control_dim`` counts the
    rail force too."""

    CONFIG_NAME = "R1xS3 toy model"

    control_dim: int = 2
    hidden_width: int = 5
    hidden_layers: int = 1
    newton_iters: int = 3

    def __post_init__(self) -> None:
        if self.variant not in TOY_VARIANTS:
            raise ValueError(f"unknown toy variant {self.variant!r}; expected one of {TOY_VARIANTS}")
        if self.control_dim < 2:
            raise ValueError(
                f"the toy has a rail force and at least one torque: control_dim >= 2, got {self.control_dim}"
            )

    def rotation_config(self) -> networks.ModelConfig:
        return networks.ModelConfig(variant=self.variant, control_dim=self.control_dim - 1,
                                    hidden_width=self.hidden_width, hidden_layers=self.hidden_layers,
                                    step_size=self.step_size, newton_iters=self.newton_iters, dissipation=True)


@dataclass(frozen=True)
class Rail:
    """The rail's constants: mass, spring stiffness, gravity (SI)."""

    mass: float
    stiffness: float
    gravity: float = 9.81


class ToyTerms:
    """Terms of the toy space on one backend: ``rail`` (``mass``, ``stiffness``, ``gravity`` as
    backend scalars) and ``rotation`` (S³ :class:`~fvin_mpc.core.fvin.RigidBodyTerms`)."""

    def __init__(self, mass: Any, stiffness: Any, gravity: Any, rotation: Any) -> None:
        self.mass, self.stiffness, self.gravity = mass, stiffness, gravity
        self.rotation = rotation
        self.control_dim = 1 + rotation.control_dim


@dataclass(frozen=True)
class RailBody:
    """The toy's closed form: a :class:`Rail` and a :class:`PivotedRigidBody` (``terms(ops)``)."""

    rail: Rail
    body: PivotedRigidBody

    @property
    def control_dim(self) -> int:
        return 1 + self.body.control_dim

    def terms(self, ops: Ops) -> ToyTerms:
        return ToyTerms(self.rail.mass, self.rail.stiffness, self.rail.gravity, self.body.terms(ops))


def _split(x: Any, ops: Ops) -> tuple[Any, tuple[Any, ...], Any, tuple[Any, ...]]:
    c = ops.unstack(x)
    return c[0], c[1:5], c[5], c[6:9]


def toy_step(x: Any, u: Any, terms: ToyTerms, step_size: float, newton_iters: int, ops: Ops) -> tuple[Any, Any]:
    s, q, s_dot, omega = _split(x, ops)
    controls = ops.unstack(u)
    h, m, k, g = step_size, terms.mass, terms.stiffness, terms.gravity
    a0 = (controls[0] - k * s) / m - g
    s_next = s + h * s_dot + 0.5 * h * h * a0
    a1 = (controls[0] - k * s_next) / m - g
    s_dot_next = s_dot + 0.5 * h * (a0 + a1)
    out = fvin.fvin_step(q, omega, controls[1:], terms.rotation, h, newton_iters, ops, with_residual=True)
    return ops.stack((s_next, *out.q, s_dot_next, *out.omega)), out.residual


def toy_energy(x: Any, terms: ToyTerms, ops: Ops) -> Any:
    s, q, s_dot, omega = _split(x, ops)
    rail = 0.5 * terms.mass * s_dot * s_dot + 0.5 * terms.stiffness * s * s + terms.mass * terms.gravity * s
    return rail + fvin.total_energy(q, omega, terms.rotation)


def toy_weight_shapes(config: ToyConfig) -> dict[str, tuple[int, ...]]:
    return {**networks.weight_shapes(config.rotation_config()), "rail": (3,)}


def toy_init_weights(config: ToyConfig, seed: int) -> dict[str, np.ndarray]:
    """The rotation's S3FVIN initialization and rail constants near ``m = 0.8``, ``k = 3``, ``g = 9``."""
    weights = networks.init_weights(config.rotation_config(), seed)

    def inverse_softplus(y: float) -> float:
        return np.log(np.expm1(y))

    weights["rail"] = (np.array([inverse_softplus(0.8), inverse_softplus(3.0), 9.0])
                       + 0.05 * np.random.default_rng(seed).normal(size=3))
    return weights


def toy_learned_terms(weights: Mapping[str, Any], config: ToyConfig, ops: Ops) -> ToyTerms:
    """``m = softplus(w₀)``, ``k = softplus(w₁)``, ``g = w₂`` and the rotation's learned terms."""
    rail = weights["rail"]
    return ToyTerms(ops.softplus(rail[0]), ops.softplus(rail[1]), rail[2],
                    networks.LearnedTerms(weights, config.rotation_config(), ops))


class ToySpace(ConfigurationSpace):
    """The toy's math: the functions above as the space's methods."""

    def step(self, x, u, terms, step_size, newton_iters, ops, **options):
        return toy_step(x, u, terms, step_size, newton_iters, ops)

    def energy(self, x, terms, ops):
        return toy_energy(x, terms, ops)

    def make_terms(self, weights, config, ops):
        return toy_learned_terms(weights, config, ops)

    def shapes(self, config):
        return toy_weight_shapes(config)

    def initial_weights(self, config, seed, **scales):
        return toy_init_weights(config, seed)


TOY = ToySpace(
    name="R1xS3-toy", description="R¹ × S³ (a toy: a bead on a rail carrying a pivoted body)", layout=RAIL_LAYOUT,
    config_type=ToyConfig, variants=TOY_VARIANTS,
)
