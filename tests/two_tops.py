"""A coupled two-body product S³ × S³, defined only in the tests: two heavy tops on their own pivots,
joined by a torsion spring ``V = k (1 − ⟨q_a, q_b⟩²)`` (zero where the two attitudes agree, for either
sign). State ``(q_a, q_b, ω_a, ω_b)`` (14 entries): the blocks ``(Ball("a"), Ball("b"))``, every position
first, then every rate.

The step is written here, by hand: each top takes the S³ step (:func:`fvin_mpc.core.fvin.fvin_step`) on its
own terms plus the spring, the other top's attitude held where it starts the step (a splitting, first order
in the coupling). Nothing here edits a package module: :data:`TWO_TOPS` is a
:class:`~fvin_mpc.core.space.ConfigurationSpace` value a test registers and takes out again, and every layer
reads it through its blocks.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from fvin_mpc.core import fvin, networks, s3
from fvin_mpc.core.backend import Ops
from fvin_mpc.core.blocks import Ball
from fvin_mpc.core.rigid_body import PivotedRigidBody
from fvin_mpc.core.space import ConfigurationSpace, StateLayout

TWO_TOPS_LAYOUT = StateLayout((Ball(label="a"), Ball(label="b")), name="(q_a, q_b, ω_a, ω_b)")
TWO_TOPS_VARIANTS = ("sign-invariant", "plain")


@dataclass(frozen=True)
class TwoTopsConfig(networks.ModelFields):
    """A learned model of the two tops: each an S3FVIN (the same widths), the spring one learned constant
    (``k`` through softplus). ``control_dim`` counts both tops' motors; the first half drives top a."""

    CONFIG_NAME = "two-tops toy model"

    control_dim: int = 2
    hidden_width: int = 5
    hidden_layers: int = 1
    newton_iters: int = 3

    def __post_init__(self) -> None:
        if self.variant not in TWO_TOPS_VARIANTS:
            raise ValueError(f"unknown two-tops variant {self.variant!r}; expected one of {TWO_TOPS_VARIANTS}")
        if self.control_dim < 2 or self.control_dim % 2:
            raise ValueError(f"the two tops have as many motors each: an even control_dim >= 2, got {self.control_dim}")

    def top_config(self) -> networks.ModelConfig:
        return networks.ModelConfig(variant=self.variant, control_dim=self.control_dim // 2,
                                    hidden_width=self.hidden_width, hidden_layers=self.hidden_layers,
                                    step_size=self.step_size, newton_iters=self.newton_iters)


class TwoTopsTerms:
    """Both tops' S³ terms and the spring's stiffness, on one backend."""

    def __init__(self, a: Any, b: Any, stiffness: Any) -> None:
        self.a, self.b, self.stiffness = a, b, stiffness
        self.control_dim = a.control_dim + b.control_dim


class _Sprung:
    """A top's terms with the spring to the other top (held at ``other``) in its potential."""

    def __init__(self, terms: Any, other: s3.Quat, stiffness: Any) -> None:
        self._terms, self._other, self._stiffness = terms, other, stiffness

    def __getattr__(self, name: str) -> Any:
        return getattr(self._terms, name)

    def potential(self, q: s3.Quat) -> Any:
        cosine = s3.dot(q, self._other)
        return self._terms.potential(q) + self._stiffness * (1.0 - cosine * cosine)

    def potential_gradient(self, q: s3.Quat) -> s3.Quat:
        scale = -2.0 * self._stiffness * s3.dot(q, self._other)
        return tuple(g + scale * o for g, o in zip(self._terms.potential_gradient(q), self._other))  # type: ignore


@dataclass(frozen=True)
class TwoTops:
    """The closed form: two :class:`PivotedRigidBody` tops and the spring's stiffness (``terms(ops)``)."""

    a: PivotedRigidBody
    b: PivotedRigidBody
    stiffness: float

    @property
    def control_dim(self) -> int:
        return self.a.control_dim + self.b.control_dim

    def terms(self, ops: Ops) -> TwoTopsTerms:
        return TwoTopsTerms(self.a.terms(ops), self.b.terms(ops), self.stiffness)


def _split(x: Any, ops: Ops) -> tuple[tuple[Any, ...], ...]:
    c = ops.unstack(x)
    slots = TWO_TOPS_LAYOUT.slots
    return tuple(tuple(c[slot.position]) for slot in slots) + tuple(tuple(c[slot.rate]) for slot in slots)


def two_tops_step(x: Any, u: Any, terms: TwoTopsTerms, step_size: float, newton_iters: int,
                  ops: Ops) -> tuple[Any, Any]:
    q_a, q_b, omega_a, omega_b = _split(x, ops)
    controls = ops.unstack(u)
    m = terms.a.control_dim
    a = fvin.fvin_step(q_a, omega_a, controls[:m], _Sprung(terms.a, q_b, terms.stiffness), step_size, newton_iters,
                       ops, with_residual=True)
    b = fvin.fvin_step(q_b, omega_b, controls[m:], _Sprung(terms.b, q_a, terms.stiffness), step_size, newton_iters,
                       ops, with_residual=True)
    residual = a.residual + b.residual
    return ops.stack((*a.q, *b.q, *a.omega, *b.omega)), residual


def two_tops_energy(x: Any, terms: TwoTopsTerms, ops: Ops) -> Any:
    q_a, q_b, omega_a, omega_b = _split(x, ops)
    cosine = s3.dot(q_a, q_b)
    return (fvin.total_energy(q_a, omega_a, terms.a) + fvin.total_energy(q_b, omega_b, terms.b)
            + terms.stiffness * (1.0 - cosine * cosine))


def _top_weights(weights: Mapping[str, Any], prefix: str) -> dict[str, Any]:
    return {name[len(prefix):]: value for name, value in weights.items() if name.startswith(prefix)}


def two_tops_weight_shapes(config: TwoTopsConfig) -> dict[str, tuple[int, ...]]:
    top = networks.weight_shapes(config.top_config())
    return {**{f"a.{k}": v for k, v in top.items()}, **{f"b.{k}": v for k, v in top.items()}, "spring": (1,)}


def two_tops_init_weights(config: TwoTopsConfig, seed: int) -> dict[str, np.ndarray]:
    """Each top's S3FVIN initialization (seeds ``seed`` and ``seed + 1``) and ``k`` near 2."""
    weights = {f"a.{k}": v for k, v in networks.init_weights(config.top_config(), seed).items()}
    weights.update({f"b.{k}": v for k, v in networks.init_weights(config.top_config(), seed + 1).items()})
    weights["spring"] = np.array([np.log(np.expm1(2.0))])
    return weights


def two_tops_learned_terms(weights: Mapping[str, Any], config: TwoTopsConfig, ops: Ops) -> TwoTopsTerms:
    top = config.top_config()
    return TwoTopsTerms(networks.LearnedTerms(_top_weights(weights, "a."), top, ops),
                        networks.LearnedTerms(_top_weights(weights, "b."), top, ops),
                        ops.softplus(weights["spring"][0]))


class TwoTopsSpace(ConfigurationSpace):
    """The two tops' math: the functions above as the space's methods."""

    def step(self, x, u, terms, step_size, newton_iters, ops, **options):
        return two_tops_step(x, u, terms, step_size, newton_iters, ops)

    def energy(self, x, terms, ops):
        return two_tops_energy(x, terms, ops)

    def make_terms(self, weights, config, ops):
        return two_tops_learned_terms(weights, config, ops)

    def shapes(self, config):
        return two_tops_weight_shapes(config)

    def initial_weights(self, config, seed, **scales):
        return two_tops_init_weights(config, seed)


TWO_TOPS = TwoTopsSpace(
    name="S3xS3-toy", description="S³ × S³ (a toy: two tops joined by a torsion spring)", layout=TWO_TOPS_LAYOUT,
    config_type=TwoTopsConfig, variants=TWO_TOPS_VARIANTS,
)
