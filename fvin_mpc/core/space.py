"""Configuration spaces: one small value that data, checkpoints, models, envs and controllers carry.

A :class:`ConfigurationSpace` says what a state is and how every layer treats it — jaxlie's shape,
one interface and many groups:

* its ``name``, the tag written into checkpoints and data files (``"S3"``, ``"SO3"``, ``"R3xS3"``);
* its :class:`~fvin_mpc.core.blocks.StateLayout`, a product of blocks (:mod:`fvin_mpc.core.blocks`: a
  pivoted body's one :class:`~fvin_mpc.core.blocks.Ball`, a free body's one
  :class:`~fvin_mpc.core.blocks.FreeJoint`, a mechanism's joints);
* its model config type, and the learned terms, weight shapes and initialization for that config;
* the step ``(x, u, terms, h, K, ops) → (x_next, residual)`` on stacked states, on any backend, and
  the energy — the math itself stays in the space's step module (:mod:`~fvin_mpc.core.fvin`,
  :mod:`~fvin_mpc.core.fvin_so3`, :mod:`~fvin_mpc.core.fvin_r3s3`);
* the closed-form body read off an MJCF;
* ``retract``/``local`` on the manifold, the one state check and the one distance to a goal — the
  layout's, written once per block kind for every backend.

What the goal is (a pivot's upright orientation at rest, a craft's hover point) is not the space's: the
scene declares it (:mod:`fvin_mpc.core.goals`).

:func:`get_space` maps names to spaces and :func:`space_of_config` a model config to its space. Adding
a space is a registry entry (:func:`register`) and its step — nothing else in the package asks which
space it is handed. ``tests/test_space_guard.py`` keeps it so: outside this module no code may test a
config's class, compare space names or read a space from a state's length.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Mapping

import numpy as np

from fvin_mpc.core import (
    fvin,
    fvin_r3s3,
    fvin_so3,
    networks,
    networks_r3s3,
    networks_so3,
    quadrotor,
    rigid_body,
    s3,
    so3,
)
from fvin_mpc.core.backend import Ops, get_ops
from fvin_mpc.core.blocks import Ball, FreeJoint, StateLayout, chart_local, chart_retract

NP = get_ops("numpy")
__all__ = ["ConfigurationSpace", "StateLayout", "chart_local", "chart_retract", "get_space", "register", "require",
           "space_for_variant", "space_of_config", "spaces", "unregister", "PIVOTED", "FREE_BODY", "S3", "SO3",
           "R3S3"]


# ----------------------------------------------------------------------------- spaces
@dataclass(frozen=True, eq=False)
class ConfigurationSpace:
    """One configuration space; see the module docstring. A space is a subclass that writes its math as
    methods (:meth:`step`, :meth:`energy`, and the learned model's :meth:`make_terms`, :meth:`shapes`,
    :meth:`initial_weights`, :meth:`closed_form_body` where it has them); its instances are singletons in
    the registry (compare them with ``is``), each with its step written once in its own core module.

    Attributes:
        name: the tag in checkpoints and data (``"S3"``, ``"SO3"``, ``"R3xS3"``).
        description: a few words for messages.
        layout: the state's blocks (:class:`~fvin_mpc.core.blocks.StateLayout`).
        config_type: the model config class of this space's learned models.
        variants: the values of its config's ``variant``, the config's default first.
    """

    name: str
    description: str
    layout: StateLayout
    config_type: type
    variants: tuple[str, ...]

    #: Every registered space by name (:func:`register`).
    registry: ClassVar[dict[str, "ConfigurationSpace"]] = {}

    def __post_init__(self) -> None:
        # The implicit dynamics are the S³ step's equations on (q, ω): a space claiming them must have
        # that layout.
        if self.has_step_residual and self.layout != PIVOTED:
            raise ValueError(f"space {self.name!r}: a space with step_residual must have the layout "
                             f"{PIVOTED.name}, got {self.layout.name}")

    @property
    def has_step_residual(self) -> bool:
        """Whether the space has its step's own equations (:meth:`step_residual`)."""
        return type(self).step_residual is not ConfigurationSpace.step_residual

    @property
    def state_dim(self) -> int:
        return self.layout.state_dim

    # -------------------------------------------------------------- math (a subclass writes these)
    def step(self, x: Any, u: Any, terms: Any, step_size: float, newton_iters: int, ops: Ops,
             **options: Any) -> tuple[Any, Any]:
        """One step on stacked states: ``x (…, n)`` (CasADi: a column), ``u (…, m)`` →
        ``(x_next, residual)``; ``residual`` is the final Newton residual in rad/s, large past the
        solvability limit where ``x_next`` means nothing. ``options`` are the space's own
        (:meth:`step_options`: R³ × S³'s ``force_rule``)."""
        raise NotImplementedError(f"the {self.description} space writes no step")

    def energy(self, x: Any, terms: Any, ops: Ops) -> Any:
        """The model's energy of stacked states (kinetic + potential, in the model's own scale)."""
        raise NotImplementedError(f"the {self.description} space writes no energy")

    def step_options(self, config: Any) -> dict[str, Any]:
        """The :meth:`step` options a model config fixes (e.g. R³ × S³'s force rule)."""
        return {}

    def step_residual(self, *args: Any, **kwargs: Any) -> tuple[Any, ...]:
        """The step's own equations ``G(x_k, u_k, x_{k+1}) = 0`` on components, where the space has them in
        the form the real-time iteration's implicit dynamics imposes (S³: :func:`fvin.step_residual`)."""
        raise NotImplementedError(f"the {self.description} space has no step residual")

    def make_terms(self, weights: Mapping[str, Any], config: Any, ops: Ops) -> Any:
        """The learned terms of ``weights`` (the config already checked: :meth:`learned_terms`)."""
        raise NotImplementedError(f"the {self.description} space has no learned model")

    def shapes(self, config: Any) -> dict[str, tuple[int, ...]]:
        """The weights' names and shapes under ``config`` (checked: :meth:`weight_shapes`)."""
        raise NotImplementedError(f"the {self.description} space has no learned model")

    def initial_weights(self, config: Any, seed: int, **scales: Any) -> dict[str, np.ndarray]:
        """A fresh initialization under ``config`` (checked: :meth:`init_weights`)."""
        raise NotImplementedError(f"the {self.description} space has no learned model")

    def closed_form_body(self, model: Any, body: str) -> Any:
        """The closed-form body of ``body`` in a compiled ``mujoco.MjModel`` (:meth:`closed_form`)."""
        raise NotImplementedError(f"the {self.description} space has no closed-form body")

    # -------------------------------------------------------------- learned models
    def owns(self, config: Any) -> bool:
        """Whether ``config`` is a model config of this space."""
        return type(config) is self.config_type

    def learned_terms(self, weights: Mapping[str, Any], config: Any, ops: Ops) -> Any:
        """The learned terms of ``weights`` under ``config`` on ``ops``' backend."""
        self._require_own(config)
        return self.make_terms(weights, config, ops)

    def weight_shapes(self, config: Any) -> dict[str, tuple[int, ...]]:
        self._require_own(config)
        return self.shapes(config)

    def check_weights(self, weights: Mapping[str, Any], config: Any) -> None:
        """``ValueError`` naming the first weight whose name or shape does not match ``config``."""
        networks.check_weight_shapes(weights, self.weight_shapes(config), config.CONFIG_NAME)

    def init_weights(self, config: Any, seed: int, **scales: Any) -> dict[str, np.ndarray]:
        """A fresh initialization (``scales``: the space's initial physical scales, e.g. ``inertia``)."""
        self._require_own(config)
        return self.initial_weights(config, seed, **scales)

    def config_from_dict(self, fields: Mapping[str, Any]) -> Any:
        return self.config_type.from_dict(fields)

    # -------------------------------------------------------------- closed form
    def closed_form(self, model: Any, body: str) -> Any:
        """The closed-form body of ``body`` in a compiled ``mujoco.MjModel``; it has ``terms(ops)``
        and ``control_dim``. ``NotImplementedError`` for a space with no closed form."""
        return self.closed_form_body(model, body)

    # -------------------------------------------------------------- manifold
    def check(self, x: Any) -> np.ndarray:
        """The one check of a measured state (:meth:`~fvin_mpc.core.blocks.StateLayout.check`)."""
        return self.layout.check(x)

    def retract(self, x: Any, delta: Any, ops: Ops = NP) -> Any:
        """:meth:`~fvin_mpc.core.blocks.StateLayout.retract` (NumPy arrays by default; any backend)."""
        if ops is NP:
            x, delta = np.asarray(x, dtype=float), np.asarray(delta, dtype=float)
        return self.layout.retract(x, delta, ops)

    def local(self, x: Any, y: Any, ops: Ops = NP) -> Any:
        """:meth:`~fvin_mpc.core.blocks.StateLayout.local` (NumPy arrays by default; any backend)."""
        if ops is NP:
            x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        return self.layout.local(x, y, ops)

    def distance(self, x: Any, goal: Any, ops: Ops = NP) -> Any:
        """The configuration's distance of states ``x (…, n)`` to a goal state ``(n,)``: zero on the goal's
        configuration, sign- and wrap-invariant (:meth:`~fvin_mpc.core.blocks.StateLayout.distance`; for one
        attitude ``1 − ⟨q, q_goal⟩²``)."""
        if ops is NP:
            x, goal = np.asarray(x, dtype=float), np.asarray(goal, dtype=float)
        return self.layout.distance(x, goal, ops)

    def _require_own(self, config: Any) -> None:
        if not self.owns(config):
            raise ValueError(f"a {type(config).__name__} is not a model config of the {self.description} space "
                             f"({self.config_type.__name__})")

    def __repr__(self) -> str:
        return f"ConfigurationSpace({self.name!r})"


def register(space: ConfigurationSpace) -> ConfigurationSpace:
    """Add ``space`` to the registry; ``ValueError`` if its name or config type is taken."""
    for other in ConfigurationSpace.registry.values():
        if other.name == space.name or other.config_type is space.config_type:
            raise ValueError(f"a space named {other.name!r} with config {other.config_type.__name__} is registered")
    ConfigurationSpace.registry[space.name] = space
    return space


def unregister(name: str) -> None:
    """Remove a space added by :func:`register` (tests register toy spaces and take them out again)."""
    ConfigurationSpace.registry.pop(name, None)


def get_space(name: str | ConfigurationSpace | None) -> ConfigurationSpace:
    """The registered space called ``name`` (``None``: S³, what files written before the tag mean)."""
    if isinstance(name, ConfigurationSpace):
        return name
    try:
        return ConfigurationSpace.registry["S3" if name is None else name]
    except (KeyError, TypeError):
        raise ValueError(
            f"unknown configuration space {name!r}; known: {sorted(ConfigurationSpace.registry)}"
        ) from None


def space_of_config(config: Any) -> ConfigurationSpace:
    """The registered space whose model config ``config`` is."""
    for space in ConfigurationSpace.registry.values():
        if space.owns(config):
            return space
    raise ValueError(f"{type(config).__name__} is the model config of no registered configuration space")


def space_for_variant(data_space: ConfigurationSpace, variant: str) -> ConfigurationSpace:
    """The space of a model ``variant`` trained on states of ``data_space``: ``data_space`` itself if it
    has the variant, else another registered space with the same state layout that has it (S³ data
    trains the SO(3) baseline's ``so3-…`` variants).

    Raises:
        ValueError: no space on ``data_space``'s states has ``variant`` (the message lists theirs).
    """
    candidates = [data_space, *(s for s in spaces() if s is not data_space and s.layout == data_space.layout)]
    for space in candidates:
        if variant in space.variants:
            return space
    known = sorted({v for s in candidates for v in s.variants})
    raise ValueError(f"no model variant {variant!r} on {data_space.description} data; choose from {known}")


def require(space: ConfigurationSpace, supported: tuple[ConfigurationSpace, ...], by: str, what: str) -> None:
    """``ValueError`` unless ``space`` is one of ``supported``: how code written for some spaces
    refuses the others (``what`` names the model or checkpoint, ``by`` the refusing code)."""
    if not any(space is other for other in supported):
        names = ", ".join(other.description for other in supported)
        raise ValueError(f"{by} supports models on {names}; {what} is on {space.description}")


def spaces() -> tuple[ConfigurationSpace, ...]:
    """Every registered space, in registration order."""
    return tuple(ConfigurationSpace.registry.values())


# ----------------------------------------------------------------------------- S³: a pivoted body
def _split_pivoted(x: Any, ops: Ops) -> tuple[s3.Quat, s3.Vec3]:
    c = ops.unstack(x)
    return c[0:4], c[4:7]  # type: ignore[return-value]


def _s3_step(x: Any, u: Any, terms: Any, step_size: float, newton_iters: int, ops: Ops) -> tuple[Any, Any]:
    q, omega = _split_pivoted(x, ops)
    out = fvin.fvin_step(q, omega, ops.unstack(u), terms, step_size, newton_iters, ops, with_residual=True)
    return ops.stack((*out.q, *out.omega)), out.residual


def _s3_energy(x: Any, terms: Any, ops: Ops) -> Any:
    return fvin.total_energy(*_split_pivoted(x, ops), terms)


#: A body on a fixed pivot, its attitude on S³: ``(q, ω)``.
PIVOTED = StateLayout((Ball(),), name="(q, ω)")
#: A free rigid body: ``(x, q, v, ω)``.
FREE_BODY = StateLayout((FreeJoint(),), name="(x, q, v, ω)")

class PivotedSpace(ConfigurationSpace):
    """S³: a pivoted body's S3FVIN step (:mod:`~fvin_mpc.core.fvin`) on ``(q, ω)``."""

    def step(self, x, u, terms, step_size, newton_iters, ops, **options):
        return _s3_step(x, u, terms, step_size, newton_iters, ops)

    def energy(self, x, terms, ops):
        return _s3_energy(x, terms, ops)

    def step_residual(self, *args, **kwargs):
        return fvin.step_residual(*args, **kwargs)

    def make_terms(self, weights, config, ops):
        return networks.LearnedTerms(weights, config, ops)

    def shapes(self, config):
        return networks.weight_shapes(config)

    def initial_weights(self, config, seed, **scales):
        return networks.init_weights(config, seed, **scales)

    def closed_form_body(self, model, body):
        return rigid_body.from_mujoco(model, body)


S3 = register(PivotedSpace(
    name="S3", description="S³ (a pivoted body on unit quaternions)", layout=PIVOTED,
    config_type=networks.ModelConfig, variants=networks.VARIANTS,
))


# ----------------------------------------------------------------------------- SO(3): the paper's baseline
def _so3_step(x: Any, u: Any, terms: Any, step_size: float, newton_iters: int, ops: Ops) -> tuple[Any, Any]:
    """The SO(3) step on a ``(q, ω)`` state: ``R(q)`` in, the preimage of ``R_{k+1}`` on ``q``'s side
    of S³ out (continuous along a trajectory; the map is the same for ``±q``)."""
    q, omega = _split_pivoted(x, ops)
    out = fvin_so3.so3_step(s3.rotation_matrix(q), omega, ops.unstack(u), terms, step_size, newton_iters, ops,
                            with_residual=True)
    q_next = so3.quaternion_from_rotation(out.rotation, ops)
    q_next = s3.scale(ops.where(s3.dot(q, q_next) >= 0.0, 1.0, -1.0), q_next)
    return ops.stack((*q_next, *out.omega)), out.residual


def _so3_energy(x: Any, terms: Any, ops: Ops) -> Any:
    q, omega = _split_pivoted(x, ops)
    return fvin_so3.total_energy(s3.rotation_matrix(q), omega, terms)


class _SO3ClosedForm:
    """A closed-form pivoted body as SO(3) terms (physical torques, not the S³ model's doubled ones)."""

    def __init__(self, body: Any) -> None:
        self.body = body
        self.control_dim = body.control_dim

    def terms(self, ops: Ops) -> Any:
        return fvin_so3.PivotedRigidBodySO3Terms(self.body, ops)


class SO3Space(ConfigurationSpace):
    """SO(3): the paper's SO3FVIN baseline (:mod:`~fvin_mpc.core.fvin_so3`) on a ``(q, ω)`` state."""

    def step(self, x, u, terms, step_size, newton_iters, ops, **options):
        return _so3_step(x, u, terms, step_size, newton_iters, ops)

    def energy(self, x, terms, ops):
        return _so3_energy(x, terms, ops)

    def make_terms(self, weights, config, ops):
        return networks_so3.LearnedSO3Terms(weights, config, ops)

    def shapes(self, config):
        return networks_so3.weight_shapes(config)

    def initial_weights(self, config, seed, **scales):
        return networks_so3.init_weights(config, seed, **scales)

    def closed_form_body(self, model, body):
        return _SO3ClosedForm(rigid_body.from_mujoco(model, body))


SO3 = register(SO3Space(
    name="SO3", description="SO(3) (the paper's SO3FVIN baseline on a pivoted body)", layout=PIVOTED,
    config_type=networks_so3.SO3ModelConfig, variants=networks_so3.SO3_VARIANTS,
))


# ----------------------------------------------------------------------------- R³ × S³: a free body
def _r3s3_step(x: Any, u: Any, terms: Any, step_size: float, newton_iters: int, ops: Ops,
               force_rule: str = "trapezoid") -> tuple[Any, Any]:
    return fvin_r3s3.step_state(x, u, terms, step_size, newton_iters, ops, force_rule)


def _r3s3_energy(x: Any, terms: Any, ops: Ops) -> Any:
    return fvin_r3s3.total_energy(*fvin_r3s3.split_free_state(x, ops), terms)


class FreeBodySpace(ConfigurationSpace):
    """R³ × S³: a free body's step (:mod:`~fvin_mpc.core.fvin_r3s3`) on ``(x, q, v, ω)``."""

    def step(self, x, u, terms, step_size, newton_iters, ops, **options):
        return _r3s3_step(x, u, terms, step_size, newton_iters, ops, **options)

    def energy(self, x, terms, ops):
        return _r3s3_energy(x, terms, ops)

    def step_options(self, config):
        return {"force_rule": config.force_rule}

    def make_terms(self, weights, config, ops):
        return networks_r3s3.LearnedCombinedTerms(weights, config, ops)

    def shapes(self, config):
        return networks_r3s3.weight_shapes(config)

    def initial_weights(self, config, seed, **scales):
        return networks_r3s3.init_weights(config, seed, **scales)

    def closed_form_body(self, model, body):
        return quadrotor.from_mujoco(model, body)


R3S3 = register(FreeBodySpace(
    name="R3xS3", description="R³ × S³ (a free body that translates and rotates)", layout=FREE_BODY,
    config_type=networks_r3s3.R3S3Config, variants=("fixed-inertia", "sign-invariant", "plain"),
))
