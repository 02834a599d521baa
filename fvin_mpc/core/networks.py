"""The learned S3FVIN terms ``J(q)``, ``U(q)``, ``g(q)`` (and optional ``D``) from weights.

Weights are a flat mapping ``name → array`` (NumPy arrays, torch tensors or anything the
backend's ``linear`` accepts). The same :class:`LearnedTerms` code runs in torch for
training, in NumPy for the control runtime and in CasADi for the export.

Networks are tanh MLPs on the quaternion ``q ∈ R⁴`` (``hidden_layers`` layers of
``hidden_width``). Names: ``{net}_w{i}`` with shape ``(out, in)``, ``{net}_b{i}`` with
shape ``(out,)``, for ``net`` in ``potential`` (→ 1), ``inertia`` (→ 6, the lower
triangle of ``L`` with ``J = LLᵀ + εI``), ``gain`` (→ 3m, row-major 3×m). Constant
parts: ``inertia_cholesky`` (6,) for the fixed-inertia variant, ``dissipation_cholesky``
(6,) when ``dissipation`` is on (``D = L_D L_Dᵀ``, constant).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Literal, Mapping

import numpy as np

from fvin_mpc.core import s3
from fvin_mpc.core.backend import Ops

Variant = Literal["sign-invariant", "fixed-inertia", "plain"]
VARIANTS: tuple[str, ...] = ("sign-invariant", "fixed-inertia", "plain")


class DictConfig:
    """``to_dict``/``from_dict`` of a frozen-dataclass model config (a checkpoint sidecar's ``model``),
    shared by every configuration space; ``from_dict`` rejects fields the class does not have."""

    #: Names the config in errors (``"unknown model config fields: …"``).
    CONFIG_NAME = "model"

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)  # type: ignore[call-overload]

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Any:
        unknown = set(data) - set(cls.__dataclass_fields__)  # type: ignore[attr-defined]
        if unknown:
            raise ValueError(f"unknown {cls.CONFIG_NAME} config fields: {sorted(unknown)}")
        return cls(**data)


def unit_axis(values: Any, name: str) -> tuple[float, float, float]:
    """``values`` as a unit 3-tuple of floats; ``ValueError`` naming ``name`` unless 3 finite numbers, not all 0."""
    axis = np.asarray(values, dtype=float)
    if axis.shape != (3,) or not np.all(np.isfinite(axis)) or not np.linalg.norm(axis) > 0.0:
        raise ValueError(f"{name} must be 3 finite numbers, not all zero; got {values!r}")
    return tuple(float(v) for v in axis / np.linalg.norm(axis))  # type: ignore[return-value]


def add_mlp_shapes(shapes: dict[str, tuple[int, ...]], name: str, inputs: int, outputs: int, hidden_width: int,
                   hidden_layers: int) -> None:
    """Add the weights ``{name}_w{i}`` ``(out, in)`` and ``{name}_b{i}`` of a tanh MLP to ``shapes``."""
    sizes = [inputs] + [hidden_width] * hidden_layers + [outputs]
    for i in range(len(sizes) - 1):
        shapes[f"{name}_w{i}"] = (sizes[i + 1], sizes[i])
        shapes[f"{name}_b{i}"] = (sizes[i + 1],)


def check_weight_shapes(weights: Mapping[str, Any], expected: Mapping[str, tuple[int, ...]],
                        config_name: str = "model") -> None:
    """Raise ``ValueError`` naming the first missing, unexpected or mis-shaped weight of ``weights``
    against ``expected`` (name → shape) of a ``config_name`` config."""
    missing = sorted(set(expected) - set(weights))
    extra = sorted(set(weights) - set(expected))
    if missing or extra:
        raise ValueError(f"weights do not match the {config_name} config: missing {missing}, unexpected {extra}")
    for name, shape in expected.items():
        actual = tuple(weights[name].shape)
        if actual != shape:
            raise ValueError(f"weight {name!r} has shape {actual}, expected {shape}")


#: The most unrolled Newton iterations a model may carry: K = 5 already solves the step to 1e-15
#: (DESIGN.md), and every iteration adds a copy of the implicit solve to the exported step (a sidecar's
#: K = 10⁶ would build for hours).
MAX_NEWTON_ITERS = 20


@dataclass(frozen=True)
class ModelFields(DictConfig):
    """The fields every configuration space's model config starts with, in this order (a checkpoint's
    sidecar lists them so); a space's config redeclares the defaults it changes and adds its own."""

    variant: str = "sign-invariant"
    control_dim: int = 1
    hidden_width: int = 10
    hidden_layers: int = 2
    step_size: float = 0.05
    newton_iters: int = 2

    def check_fields(self) -> None:
        """``ValueError`` unless the counts are whole numbers, ``K`` at most :data:`MAX_NEWTON_ITERS` and the
        step finite seconds: what a hand-edited sidecar may get wrong (``step_size: Infinity``,
        ``newton_iters: 1.5``), refused when the config is built rather than when the step runs."""
        for name in ("control_dim", "hidden_width", "hidden_layers", "newton_iters"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise ValueError(f"{name} must be a whole number, got {value!r}")
        if self.newton_iters > MAX_NEWTON_ITERS:
            raise ValueError(f"newton_iters must be at most {MAX_NEWTON_ITERS}, got {self.newton_iters}")
        step = self.step_size
        if isinstance(step, bool) or not isinstance(step, (int, float, np.floating)) or not (
                math.isfinite(step) and step > 0):
            raise ValueError(f"step_size must be finite seconds > 0, got {step!r}")


@dataclass(frozen=True)
class ModelConfig(ModelFields):
    """Architecture and integration settings of an S3FVIN model.

    Attributes:
        variant: ``"sign-invariant"`` (default; ``J``, ``U``, ``g`` averaged over ``q``
            and ``−q``, configuration-dependent ``J``), ``"fixed-inertia"`` (constant
            learned ``J``; ``U``, ``g`` not averaged) or ``"plain"`` (no restriction).
            Paper §4.
        control_dim: number of controls ``m``.
        hidden_width: width of every hidden layer.
        hidden_layers: number of hidden layers of each MLP.
        step_size: integrator step ``h`` (s); equals the data's control period.
        newton_iters: Newton iterations ``K`` unrolled per step.
        dissipation: learn a constant PSD damping ``D`` (force ``−Dω``); off for
            conservative scenes.
        inertia_epsilon: ``ε`` in ``J = LLᵀ + εI``.
        hinge_axis: the body's hinge axis in its own frame (stored unit), or ``None`` for a body that
            turns about any axis (a ball joint). A hinged model steps on the hinge only
            (:func:`fvin_mpc.core.fvin.hinge_step`): the terms across it, which hinge data cannot
            identify, never enter its predictions.
        vertical: world "up" (unit, against gravity), or ``None``. Given, the networks see the
            body-frame vertical ``R(q)ᵀ·vertical`` instead of ``q``: a body on a ball joint in uniform
            gravity, with body-fixed actuators and damping and no joint spring, moves the same however
            the world is turned about the vertical, so its terms depend on ``q`` only through that
            direction. Without it a network of ``q`` fitted a different potential at every turn about
            the vertical, and a body held upright while spinning about its long axis met a model error
            that turned with it (the two-motor ball scenes, held 0.05–0.1 rad off upright:
            docs/scene-families.md). The input is even in ``q`` already: no ``±q`` average.
        control_scale: per control, the size of a full control (the data's largest ``|u|``), or
            ``None`` (1). The gain network learns the force of a *full* control, ``g(q) = ĝ(q) / scale``:
            an actuator whose control range is ±0.05 with a gear of 35 would otherwise need the
            network's output near 70 from an initialization near 0.1, which training did not reach.
    """

    variant: Variant = "sign-invariant"
    dissipation: bool = False
    inertia_epsilon: float = 1e-3
    hinge_axis: tuple[float, float, float] | None = None
    control_scale: tuple[float, ...] | None = None
    vertical: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        self.check_fields()
        if self.hinge_axis is not None:
            object.__setattr__(self, "hinge_axis", unit_axis(self.hinge_axis, "hinge_axis"))
        if self.vertical is not None:
            object.__setattr__(self, "vertical", unit_axis(self.vertical, "vertical"))
        if self.control_scale is not None:
            scale = np.asarray(self.control_scale, dtype=float)
            if scale.shape != (self.control_dim,) or not np.all(np.isfinite(scale)) or not np.all(scale > 0.0):
                raise ValueError(f"control_scale must be {self.control_dim} positive numbers, "
                                 f"got {self.control_scale!r}")
            object.__setattr__(self, "control_scale", tuple(float(v) for v in scale))
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown variant {self.variant!r}; expected one of {VARIANTS}")
        if self.control_dim < 1:
            raise ValueError(f"control_dim must be >= 1, got {self.control_dim}")
        if self.hidden_width < 1 or self.hidden_layers < 1:
            raise ValueError("hidden_width and hidden_layers must be >= 1")
        if not self.step_size > 0:
            raise ValueError(f"step_size must be > 0, got {self.step_size}")
        if self.newton_iters < 1:
            raise ValueError(f"newton_iters must be >= 1, got {self.newton_iters}")

    @property
    def sign_invariant(self) -> bool:
        return self.variant == "sign-invariant"

    @property
    def constant_inertia(self) -> bool:
        return self.variant == "fixed-inertia"


def weight_shapes(config: ModelConfig) -> dict[str, tuple[int, ...]]:
    """Name → shape of every weight of a model with this config."""
    shapes: dict[str, tuple[int, ...]] = {}

    def mlp(name: str, outputs: int) -> None:
        inputs = 4 if config.vertical is None else 3
        add_mlp_shapes(shapes, name, inputs, outputs, config.hidden_width, config.hidden_layers)

    mlp("potential", 1)
    if config.constant_inertia:
        shapes["inertia_cholesky"] = (6,)
    else:
        mlp("inertia", 6)
    mlp("gain", 3 * config.control_dim)
    if config.dissipation:
        shapes["dissipation_cholesky"] = (6,)
    return shapes


def init_weights(config: ModelConfig, seed: int, initial_inertia: float = 0.3) -> dict[str, np.ndarray]:
    """Seeded initial weights: Glorot-uniform hidden layers with small random biases, small output
    layers, the inertia starting near ``initial_inertia · I`` and no damping."""
    rng = np.random.default_rng(seed)
    weights: dict[str, np.ndarray] = {}
    diag_root = np.sqrt(initial_inertia)
    for name, shape in weight_shapes(config).items():
        if name == "inertia_cholesky":
            weights[name] = np.array([diag_root] * 3 + [0.0] * 3)
        elif name == "dissipation_cholesky":
            weights[name] = np.array([0.1] * 3 + [0.0] * 3)
        elif len(shape) == 2:
            is_output = name.endswith(f"_w{config.hidden_layers}")
            limit = np.sqrt(6.0 / (shape[0] + shape[1])) * (0.1 if is_output else 1.0)
            weights[name] = rng.uniform(-limit, limit, size=shape)
        elif name.endswith(f"_b{config.hidden_layers}"):
            weights[name] = np.zeros(shape)
            if name == f"inertia_b{config.hidden_layers}":
                weights[name][:3] = diag_root
        else:
            # Hidden biases not zero: with zero biases a tanh MLP is odd in q, so the sign-invariant
            # average ½(f(q) + f(−q)) is identically 0 and every weight's gradient vanishes — the
            # potential and the gain could only start through their biases, and Levenberg–Marquardt
            # then drove those into tanh saturation (a dead potential) on hinge data.
            weights[name] = rng.uniform(-HIDDEN_BIAS_RANGE, HIDDEN_BIAS_RANGE, size=shape)
    return weights


#: Hidden-layer biases start uniform in ``±HIDDEN_BIAS_RANGE`` (see :func:`init_weights`).
HIDDEN_BIAS_RANGE = 0.5


def check_weights(weights: Mapping[str, Any], config: ModelConfig) -> None:
    """Raise ``ValueError`` naming the first missing, unexpected or mis-shaped weight."""
    check_weight_shapes(weights, weight_shapes(config))


def _mlp_hidden(weights: Mapping[str, Any], name: str, layers: int, x: Any, ops: Ops) -> list[Any]:
    activations = [x]
    for i in range(layers):
        activations.append(ops.tanh(ops.linear(activations[-1], weights[f"{name}_w{i}"], weights[f"{name}_b{i}"])))
    return activations


def mlp(weights: Mapping[str, Any], name: str, layers: int, x: Any, ops: Ops) -> Any:
    """The MLP ``name`` on the vector ``x``."""
    hidden = _mlp_hidden(weights, name, layers, x, ops)[-1]
    return ops.linear(hidden, weights[f"{name}_w{layers}"], weights[f"{name}_b{layers}"])


def scalar_mlp_value_and_gradient(
    weights: Mapping[str, Any], name: str, layers: int, x: Any, ops: Ops
) -> tuple[Any, Any]:
    """A scalar MLP and its input gradient in one pass (hand-written backpropagation,
    so every backend gets the same expression and torch needs no double backward)."""
    activations = _mlp_hidden(weights, name, layers, x, ops)
    value = ops.linear(activations[-1], weights[f"{name}_w{layers}"], weights[f"{name}_b{layers}"])
    upstream = ops.linear_transpose(0.0 * value + 1.0, weights[f"{name}_w{layers}"])
    for i in range(layers, 0, -1):
        a = activations[i]
        upstream = ops.linear_transpose(upstream * (1.0 - a * a), weights[f"{name}_w{i - 1}"])
    return value, upstream


def body_vertical(q: s3.Quat, vertical: Any) -> tuple[Any, Any, Any]:
    """``R(q)ᵀ v``: the world direction ``v`` in the body frame,
    ``(w² − |u|²) v + 2 (u·v) u − 2w (u × v)`` for ``q = (w, u)`` (quadratic in ``q``, even in its sign)."""
    w, u = q[0], q[1:]
    v = tuple(float(c) for c in vertical)
    along, turned = s3.dot(u, v), s3.cross(u, v)
    square = w * w - s3.dot(u, u)
    return tuple(square * v[i] + 2.0 * along * u[i] - 2.0 * w * turned[i] for i in range(3))  # type: ignore[return-value]


def body_vertical_gradient(q: s3.Quat, vertical: Any, g: Any) -> s3.Quat:
    """``∇_q (gᵀ R(q)ᵀ v)`` for a fixed ``g`` (3): the chain rule from a function of the body-frame
    vertical (:func:`body_vertical`) back to ``q``. With ``s = gᵀRᵀv = (w² − |u|²)(g·v) + 2(u·v)(u·g)
    − 2w u·(v × g)``: ``∂s/∂w = 2w(g·v) − 2u·(v × g)``, ``∂s/∂u = −2(g·v)u + 2(u·g)v + 2(u·v)g − 2w(v × g)``."""
    w, u = q[0], q[1:]
    v = tuple(float(c) for c in vertical)
    gv, ug, uv = s3.dot(g, v), s3.dot(u, g), s3.dot(u, v)
    vxg = s3.cross(v, g)
    return (2.0 * w * gv - 2.0 * s3.dot(u, vxg),
            *(-2.0 * gv * u[i] + 2.0 * ug * v[i] + 2.0 * uv * g[i] - 2.0 * w * vxg[i] for i in range(3)))  # type: ignore[return-value]


class LearnedTerms:
    """:class:`~fvin_mpc.core.fvin.RigidBodyTerms` of a learned model on one backend."""

    def __init__(self, weights: Mapping[str, Any], config: ModelConfig, ops: Ops) -> None:
        self.weights = weights
        self.config = config
        self.ops = ops
        self.control_dim = config.control_dim
        self.constant_inertia = config.constant_inertia
        self.hinge_axis = config.hinge_axis

    # -- helpers --------------------------------------------------------------
    @property
    def _averaged(self) -> bool:
        """Whether the networks are averaged over ``±q`` (the sign-invariant variant on ``q`` itself)."""
        return self.config.sign_invariant and self.config.vertical is None

    def _input(self, q: s3.Quat) -> Any:
        """What the networks see: ``q``, or the body-frame vertical (:attr:`ModelConfig.vertical`)."""
        vertical = self.config.vertical
        return self.ops.stack(q if vertical is None else body_vertical(q, vertical))

    def _vector_net(self, name: str, q: s3.Quat) -> tuple[Any, ...]:
        """Outputs of MLP ``name``, averaged over ``±q`` for the sign-invariant variant."""
        ops, layers = self.ops, self.config.hidden_layers
        out = ops.unstack(mlp(self.weights, name, layers, self._input(q), ops))
        if not self._averaged:
            return out
        mirrored = ops.unstack(mlp(self.weights, name, layers, ops.stack(s3.negate(q)), ops))
        return tuple(0.5 * (a + b) for a, b in zip(out, mirrored))

    def _cholesky_constant(self, name: str, q: s3.Quat) -> tuple[Any, ...]:
        zero = 0.0 * q[0]
        weights = self.weights[name]
        return tuple(zero + weights[i] for i in range(6))

    # -- RigidBodyTerms -------------------------------------------------------
    def inertia(self, q: s3.Quat) -> s3.Mat3:
        eps = self.config.inertia_epsilon
        if self.config.constant_inertia:
            return s3.symmetric_from_cholesky(self._cholesky_constant("inertia_cholesky", q), eps)
        ops, layers = self.ops, self.config.hidden_layers
        lower = ops.unstack(mlp(self.weights, "inertia", layers, self._input(q), ops))
        inertia = s3.symmetric_from_cholesky(lower, eps)
        if not self._averaged:
            return inertia
        mirrored_l = ops.unstack(mlp(self.weights, "inertia", layers, ops.stack(s3.negate(q)), ops))
        mirrored = s3.symmetric_from_cholesky(mirrored_l, eps)
        return tuple(tuple(0.5 * (a + b) for a, b in zip(ra, rb)) for ra, rb in zip(inertia, mirrored))  # type: ignore[return-value]

    def _potential_and_gradient(self, q: s3.Quat) -> tuple[Any, s3.Quat]:
        ops, layers = self.ops, self.config.hidden_layers
        value, grad = scalar_mlp_value_and_gradient(self.weights, "potential", layers, self._input(q), ops)
        value, grad = ops.unstack(value)[0], ops.unstack(grad)
        if self.config.vertical is not None:
            return value, body_vertical_gradient(q, self.config.vertical, grad)
        if self.config.sign_invariant:
            # Û(q) = ½(U(q) + U(−q))  ⇒  ∇Û(q) = ½(∇U(q) − ∇U(−q)).
            value_m, grad_m = scalar_mlp_value_and_gradient(
                self.weights, "potential", layers, ops.stack(s3.negate(q)), ops
            )
            value = 0.5 * (value + ops.unstack(value_m)[0])
            grad = tuple(0.5 * (a - b) for a, b in zip(grad, ops.unstack(grad_m)))
        return value, grad  # type: ignore[return-value]

    def potential(self, q: s3.Quat) -> Any:
        return self._potential_and_gradient(q)[0]

    def potential_gradient(self, q: s3.Quat) -> s3.Quat:
        return self._potential_and_gradient(q)[1]

    def control_gain(self, q: s3.Quat) -> tuple[tuple[Any, ...], ...]:
        flat = self._vector_net("gain", q)
        m, scale = self.control_dim, self.config.control_scale
        if scale is None:
            return tuple(tuple(flat[i * m + j] for j in range(m)) for i in range(3))
        return tuple(tuple(flat[i * m + j] / scale[j] for j in range(m)) for i in range(3))

    def dissipation(self, q: s3.Quat) -> s3.Mat3 | None:
        if not self.config.dissipation:
            return None
        return s3.symmetric_from_cholesky(self._cholesky_constant("dissipation_cholesky", q))
