"""The learned R³ × S³ terms ``M``, ``J(q)``, ``U(x, q)``, ``F_x(x, q, u)``, ``g(x, q)`` from weights —
the :class:`~fvin_mpc.core.fvin_r3s3.CombinedTerms` of a learned free body, written once for NumPy,
torch and CasADi on :mod:`fvin_mpc.core.networks`' MLPs.

Weights (names → arrays; MLPs as in :mod:`fvin_mpc.core.networks`: ``{net}_w{i}`` ``(out, in)``,
``{net}_b{i}`` ``(out,)``, tanh hidden layers):

* ``mass_cholesky`` (6): ``M = L Lᵀ + ε_M I``, constant (the paper's ``M``).
* ``inertia_cholesky`` (6) for ``"fixed-inertia"``, else MLP ``inertia`` on ``q`` (→ 6): ``J = L Lᵀ + ε_J I``.
* ``potential_linear`` (3) and MLP ``potential`` on ``(x, q)`` (→ 1): ``U = aᵀx + N(x, q)``. The
  linear term is a uniform field (gravity) exactly, also outside the data's positions, where the
  tanh network flattens out.
* MLP ``force`` (→ 3m) and MLP ``gain`` (→ 3m): the translational force ``F_x = G_x u`` (control
  affine) and the rotational gain ``g`` (3×m, row-major), on ``q`` — or on ``(x, q)`` with
  ``position_in_forces`` (a body whose actuation depends on where it is; a rotor craft's does not).
  With ``force_frame="body"`` (default) the network gives the force in the body frame and
  ``G_x = R(q) G_b(q)``: actuators that push the body in its own frame (rotors, thrusters). This is
  what makes ``M`` identifiable: with a free world-frame ``G_x(q)`` only ``M⁻¹G_x`` enters the motion,
  so any SPD ``M`` fits as well as the true one; with ``R(q) G_b`` and orientations that turn, only
  ``M ∝ I`` does (the scale ``c`` below aside). ``force_frame="world"`` is the paper's free ``f^x``.

Sign invariance (``"sign-invariant"``, ``"fixed-inertia"``): ``J``, ``U``, ``G_x``, ``g`` are averaged
over ``q`` and ``−q`` (for ``U``: ``∇_q Û(x, q) = ½(∇_q U(x, q) − ∇_q U(x, −q))``), as for the pivoted
model. ``"plain"`` averages nothing.

Scale: the dynamics do not change when every term is multiplied by one constant ``c > 0``; a
learned model's mass and inertia are compared with the truth after dividing by ``c`` (see
:func:`physical_scale`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from fvin_mpc.core import networks, s3
from fvin_mpc.core.backend import Ops
from fvin_mpc.core.fvin_r3s3 import FORCE_RULES
from fvin_mpc.core.networks import VARIANTS, Variant, mlp, scalar_mlp_value_and_gradient


@dataclass(frozen=True)
class R3S3Config(networks.ModelFields):
    """Architecture and integration settings of a learned R³ × S³ model.

    Attributes:
        variant: as :class:`~fvin_mpc.core.networks.ModelConfig` (``"sign-invariant"``: ``J(q)``
            learned, everything averaged over ``±q``; ``"fixed-inertia"``: constant ``J``, averaged;
            ``"plain"``: neither).
        control_dim: ``m``.
        hidden_width, hidden_layers: of every MLP.
        step_size: ``h`` (s), the data's control period.
        newton_iters: ``K`` of the rotational solve.
        force_rule: ``"trapezoid"`` or ``"hold"`` (:func:`fvin_mpc.core.fvin_r3s3.r3s3_step`).
        position_in_forces: ``F_x`` and ``g`` see ``(x, q)`` instead of ``q`` only.
        force_frame: ``"body"`` (``F_x = R(q) G_b u``) or ``"world"`` (``F_x = G_x u``); module docstring.
        mass_epsilon, inertia_epsilon: ``ε`` of the Cholesky parametrizations.
    """

    variant: Variant = "fixed-inertia"
    control_dim: int = 4
    hidden_width: int = 16
    step_size: float = 0.02
    force_rule: str = "trapezoid"
    position_in_forces: bool = False
    force_frame: str = "body"
    mass_epsilon: float = 1e-6
    inertia_epsilon: float = 1e-8

    def __post_init__(self) -> None:
        self.check_fields()
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown variant {self.variant!r}; expected one of {VARIANTS}")
        if self.force_frame not in ("body", "world"):
            raise ValueError(f"force_frame must be 'body' or 'world', got {self.force_frame!r}")
        if self.force_rule not in FORCE_RULES:
            raise ValueError(f"force_rule must be one of {FORCE_RULES}, got {self.force_rule!r}")
        if self.control_dim < 1 or self.hidden_width < 1 or self.hidden_layers < 1 or self.newton_iters < 1:
            raise ValueError("control_dim, hidden_width, hidden_layers and newton_iters must be >= 1")
        if not self.step_size > 0:
            raise ValueError(f"step_size must be > 0, got {self.step_size}")

    @property
    def sign_invariant(self) -> bool:
        return self.variant != "plain"

    @property
    def constant_inertia(self) -> bool:
        return self.variant == "fixed-inertia"

    CONFIG_NAME = "R3xS3 model"


def weight_shapes(config: R3S3Config) -> dict[str, tuple[int, ...]]:
    """Name → shape of every weight of a model with this config."""
    shapes: dict[str, tuple[int, ...]] = {"mass_cholesky": (6,), "potential_linear": (3,)}
    force_inputs = 7 if config.position_in_forces else 4

    def add_mlp(name: str, inputs: int, outputs: int) -> None:
        networks.add_mlp_shapes(shapes, name, inputs, outputs, config.hidden_width, config.hidden_layers)

    if config.constant_inertia:
        shapes["inertia_cholesky"] = (6,)
    else:
        add_mlp("inertia", 4, 6)
    add_mlp("potential", 7, 1)
    add_mlp("force", force_inputs, 3 * config.control_dim)
    add_mlp("gain", force_inputs, 3 * config.control_dim)
    return shapes


def check_weights(weights: Mapping[str, Any], config: R3S3Config) -> None:
    """``ValueError`` naming the first missing, unexpected or mis-shaped weight."""
    networks.check_weight_shapes(weights, weight_shapes(config), R3S3Config.CONFIG_NAME)


def init_weights(config: R3S3Config, seed: int, mass: float = 1.0, inertia: float = 0.01,
                 force: Any = None, gravity_force: float = 0.0) -> dict[str, np.ndarray]:
    """Seeded initial weights: Glorot-uniform hidden layers, output layers scaled by 0.1, ``M = mass·I``,
    ``J ≈ inertia·I``, ``a = (0, 0, gravity_force)``; ``force`` (3×m, optional) the initial constant
    ``G_x`` (the force networks' output bias), e.g. "thrust along z" for a rotor craft."""
    rng = np.random.default_rng(seed)
    weights: dict[str, np.ndarray] = {}
    for name, shape in weight_shapes(config).items():
        if name == "mass_cholesky":
            weights[name] = np.array([np.sqrt(mass)] * 3 + [0.0] * 3)
        elif name == "inertia_cholesky":
            weights[name] = np.array([np.sqrt(inertia)] * 3 + [0.0] * 3)
        elif name == "potential_linear":
            weights[name] = np.array([0.0, 0.0, gravity_force])
        elif len(shape) == 2:
            limit = np.sqrt(6.0 / (shape[0] + shape[1])) * (0.1 if name.endswith(f"_w{config.hidden_layers}") else 1.0)
            weights[name] = rng.uniform(-limit, limit, size=shape)
        else:
            weights[name] = np.zeros(shape)
            if name == f"inertia_b{config.hidden_layers}":
                weights[name][:3] = np.sqrt(inertia)
            if name == f"force_b{config.hidden_layers}" and force is not None:
                weights[name][:] = np.asarray(force, dtype=float).reshape(-1)
    return weights


class _Remembered:
    """The last result of a function of backend components, recomputed only when the arguments are
    other objects (the step asks for ``∇ₓU`` and ``∇_qU`` at the same ``(x, q)`` one after the other)."""

    def __init__(self) -> None:
        self.arguments: tuple[Any, ...] | None = None
        self.value: Any = None

    def get(self, arguments: tuple[Any, ...], compute: Any) -> Any:
        if self.arguments is None or len(arguments) != len(self.arguments) or any(
                a is not b for a, b in zip(arguments, self.arguments)):
            self.value = compute()
            self.arguments = arguments  # holding the objects keeps their ids from being reused
        return self.value


class LearnedCombinedTerms:
    """:class:`~fvin_mpc.core.fvin_r3s3.CombinedTerms` of a learned model on one backend."""

    def __init__(self, weights: Mapping[str, Any], config: R3S3Config, ops: Ops) -> None:
        self.weights, self.config, self.ops = weights, config, ops
        self.control_dim = config.control_dim
        self.constant_inertia = config.constant_inertia
        self._potential = _Remembered()

    # -- helpers --------------------------------------------------------------
    def _net(self, name: str, inputs: tuple[Any, ...]) -> tuple[Any, ...]:
        ops = self.ops
        return ops.unstack(mlp(self.weights, name, self.config.hidden_layers, ops.stack(inputs), ops))

    def _averaged(self, name: str, x: s3.Vec3 | None, q: s3.Quat) -> tuple[Any, ...]:
        """Outputs of MLP ``name`` on ``q`` (or ``(x, q)``), averaged over ``±q`` when sign invariant."""
        front = tuple(x) if x is not None else ()
        out = self._net(name, (*front, *q))
        if not self.config.sign_invariant:
            return out
        mirrored = self._net(name, (*front, *s3.negate(q)))
        return tuple(0.5 * (a + b) for a, b in zip(out, mirrored))

    def _constant(self, name: str, like: Any) -> tuple[Any, ...]:
        zero = 0.0 * like
        return tuple(zero + self.weights[name][i] for i in range(6))

    def _force_position(self, x: s3.Vec3) -> s3.Vec3 | None:
        return x if self.config.position_in_forces else None

    def _potential_parts(self, x: s3.Vec3, q: s3.Quat) -> tuple[Any, s3.Vec3, s3.Quat]:
        """``(U, ∇ₓU, ∇_qU)`` in one pass (hand-written backpropagation, as the pivoted model)."""

        def compute() -> tuple[Any, s3.Vec3, s3.Quat]:
            ops, layers, w = self.ops, self.config.hidden_layers, self.weights
            value, grad = scalar_mlp_value_and_gradient(w, "potential", layers, ops.stack((*x, *q)), ops)
            value, grad = ops.unstack(value)[0], ops.unstack(grad)
            if self.config.sign_invariant:
                value_m, grad_m = scalar_mlp_value_and_gradient(
                    w, "potential", layers, ops.stack((*x, *s3.negate(q))), ops
                )
                grad_m = ops.unstack(grad_m)
                value = 0.5 * (value + ops.unstack(value_m)[0])
                # x enters both terms alike, q with opposite signs.
                grad = tuple(0.5 * (a + b) for a, b in zip(grad[:3], grad_m[:3])) + tuple(
                    0.5 * (a - b) for a, b in zip(grad[3:], grad_m[3:]))
            linear = w["potential_linear"]
            value = value + s3.dot(tuple(linear[i] for i in range(3)), x)
            grad_x = tuple(grad[i] + linear[i] for i in range(3))
            return value, grad_x, tuple(grad[3:])

        return self._potential.get((*x, *q), compute)

    # -- CombinedTerms ----------------------------------------------------------
    def mass_matrix(self) -> s3.Mat3:
        weights = self.weights["mass_cholesky"]
        return s3.symmetric_from_cholesky(tuple(weights[i] for i in range(6)), self.config.mass_epsilon)

    def inertia(self, q: s3.Quat) -> s3.Mat3:
        eps = self.config.inertia_epsilon
        if self.config.constant_inertia:
            return s3.symmetric_from_cholesky(self._constant("inertia_cholesky", q[0]), eps)
        inertia = s3.symmetric_from_cholesky(self._net("inertia", tuple(q)), eps)
        if not self.config.sign_invariant:
            return inertia
        mirrored = s3.symmetric_from_cholesky(self._net("inertia", s3.negate(q)), eps)
        return tuple(tuple(0.5 * (a + b) for a, b in zip(ra, rb)) for ra, rb in zip(inertia, mirrored))  # type: ignore[return-value]

    def potential(self, x: s3.Vec3, q: s3.Quat) -> Any:
        return self._potential_parts(x, q)[0]

    def potential_gradient_x(self, x: s3.Vec3, q: s3.Quat) -> s3.Vec3:
        return self._potential_parts(x, q)[1]

    def potential_gradient_q(self, x: s3.Vec3, q: s3.Quat) -> s3.Quat:
        return self._potential_parts(x, q)[2]

    def force_gain(self, x: s3.Vec3, q: s3.Quat) -> tuple[tuple[Any, ...], ...]:
        """``G_x`` (3×m): the world force per unit of each control."""
        flat, m = self._averaged("force", self._force_position(x), q), self.control_dim
        gain = tuple(tuple(flat[i * m + j] for j in range(m)) for i in range(3))
        if self.config.force_frame == "world":
            return gain
        rotation = s3.rotation_matrix(q)
        return tuple(tuple(s3.dot(rotation[i], tuple(gain[k][j] for k in range(3))) for j in range(m))
                     for i in range(3))

    def translational_force(self, x: s3.Vec3, q: s3.Quat, u: tuple[Any, ...]) -> s3.Vec3:
        return s3.matvec(self.force_gain(x, q), u)  # type: ignore[return-value]

    def control_gain(self, x: s3.Vec3, q: s3.Quat) -> tuple[tuple[Any, ...], ...]:
        flat, m = self._averaged("gain", self._force_position(x), q), self.control_dim
        return tuple(tuple(flat[i * m + j] for j in range(m)) for i in range(3))


def physical_scale(terms: Any, level: s3.Quat = (1.0, 0.0, 0.0, 0.0), position: s3.Vec3 = (0.0, 0.0, 0.0)) -> float:
    """The constant ``c`` by which a learned model's terms exceed the physical ones, fixed by one
    known fact of a rotor craft: one newton of total thrust, shared evenly, is one newton of force
    (``c = |G_x(x, q_level) 1/m|``). NumPy terms with scalar components."""
    gain = np.asarray(terms.force_gain(tuple(np.float64(c) for c in position), tuple(np.float64(c) for c in level)),
                      dtype=float)
    return float(np.linalg.norm(gain.mean(axis=1)))
