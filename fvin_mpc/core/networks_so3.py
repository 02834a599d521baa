"""The learned SO3FVIN terms ``J(R)``, ``U(R)``, ``τ(R)`` from weights — the paper's baseline (§4).

The networks are :mod:`fvin_mpc.core.networks`' tanh MLPs (same names, shapes ``(out, in)``, the
same hand-written input gradient), fed with what the variant reads:

* ``"so3-matrix"`` — the nine entries of ``R`` (row-major), as Duruisseaux et al.'s SO3FVIN;
* ``"so3-quaternion"`` — a unit-quaternion preimage ``q`` of ``R``
  (:func:`fvin_mpc.core.so3.quaternion_from_rotation`), the paper's variant with the conversion
  ``R ↦ q`` inside. The networks are not averaged over ``±q`` (the paper's choice), so they see the
  preimage's sign jump where Shepperd's branch changes; averaged, this variant would be the
  sign-invariant S3FVIN exactly (the two steps are the same map, :mod:`fvin_mpc.core.fvin_so3`).

Outputs: ``inertia`` (6, the lower triangle of ``L``, ``J = LLᵀ + εI``), ``potential`` (1),
``gain`` (3m, row-major 3×m — the body torque per unit control, half the S³ model's ``g``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, Mapping

import numpy as np

from fvin_mpc.core import networks, s3, so3
from fvin_mpc.core.backend import Ops
from fvin_mpc.core.fvin_so3 import torque_from_euclidean_gradient

SO3Variant = Literal["so3-matrix", "so3-quaternion"]
SO3_VARIANTS: tuple[str, ...] = ("so3-matrix", "so3-quaternion")
#: Network inputs per variant.
INPUTS = {"so3-matrix": 9, "so3-quaternion": 4}
_NETS = ("potential", "inertia", "gain")


@dataclass(frozen=True)
class SO3ModelConfig(networks.ModelFields):
    """Architecture and integration settings of an SO3FVIN model.

    Attributes:
        variant: what the networks read: ``"so3-matrix"`` (the 9 entries of ``R``) or
            ``"so3-quaternion"`` (a quaternion preimage of ``R``). ``J``, ``U`` and the gain are
            configuration-dependent networks in both.
        control_dim: number of controls ``m``.
        hidden_width: width of every hidden layer.
        hidden_layers: number of hidden layers of each MLP.
        step_size: integrator step ``h`` (s); equals the data's control period.
        newton_iters: Newton iterations ``K`` unrolled per step.
        inertia_epsilon: ``ε`` in ``J = LLᵀ + εI``.
    """

    variant: SO3Variant = "so3-matrix"
    inertia_epsilon: float = 1e-3

    def __post_init__(self) -> None:
        if self.variant not in SO3_VARIANTS:
            raise ValueError(f"unknown SO3FVIN variant {self.variant!r}; expected one of {SO3_VARIANTS}")
        # The remaining fields mean what ModelConfig's mean: let it validate them.
        self.s3_equivalent()

    CONFIG_NAME = "SO3 model"
    #: Never sign-averaged, never a constant inertia (the paper's SO3FVIN).
    sign_invariant = False
    constant_inertia = False
    dissipation = False

    @property
    def inputs(self) -> int:
        return INPUTS[self.variant]

    def s3_equivalent(self) -> networks.ModelConfig:
        """The plain S3FVIN config with the same widths and step (its initialization is reused)."""
        return networks.ModelConfig(variant="plain", control_dim=self.control_dim, hidden_width=self.hidden_width,
                                    hidden_layers=self.hidden_layers, step_size=self.step_size,
                                    newton_iters=self.newton_iters, inertia_epsilon=self.inertia_epsilon)



def weight_shapes(config: SO3ModelConfig) -> dict[str, tuple[int, ...]]:
    """Name → shape: :func:`fvin_mpc.core.networks.weight_shapes` of the plain S³ model with
    ``config.inputs`` network inputs."""
    shapes = networks.weight_shapes(config.s3_equivalent())
    for net in _NETS:
        shapes[f"{net}_w0"] = (config.hidden_width, config.inputs)
    return shapes


def init_weights(config: SO3ModelConfig, seed: int, initial_inertia: float = 0.3) -> dict[str, np.ndarray]:
    """The plain S3FVIN's seeded initialization (:func:`fvin_mpc.core.networks.init_weights`); for
    nine inputs the first layers are drawn anew, Glorot-uniform, from a generator seeded by ``seed``.
    The quaternion variant thus starts exactly where the plain S3FVIN of the same seed starts."""
    weights = networks.init_weights(config.s3_equivalent(), seed, initial_inertia)
    if config.inputs != 4:
        rng = np.random.default_rng([seed, config.inputs])
        limit = np.sqrt(6.0 / (config.hidden_width + config.inputs))
        for net in _NETS:
            weights[f"{net}_w0"] = rng.uniform(-limit, limit, size=(config.hidden_width, config.inputs))
    return weights


def check_weights(weights: Mapping[str, Any], config: SO3ModelConfig) -> None:
    """Raise ``ValueError`` naming the first missing, unexpected or mis-shaped weight."""
    networks.check_weight_shapes(weights, weight_shapes(config), SO3ModelConfig.CONFIG_NAME)


class LearnedSO3Terms:
    """:class:`~fvin_mpc.core.fvin_so3.RotationTerms` of a learned SO3FVIN on one backend."""

    constant_inertia = False

    def __init__(self, weights: Mapping[str, Any], config: SO3ModelConfig, ops: Ops) -> None:
        self.weights = weights
        self.config = config
        self.ops = ops
        self.control_dim = config.control_dim

    def features(self, r: so3.Mat3) -> tuple[Any, ...]:
        """What the networks read: ``R``'s nine entries or a quaternion preimage of ``R``."""
        if self.config.variant == "so3-matrix":
            return tuple(r[i][j] for i in range(3) for j in range(3))
        return so3.quaternion_from_rotation(r, self.ops)

    def _net(self, name: str, r: so3.Mat3) -> tuple[Any, ...]:
        ops = self.ops
        return ops.unstack(
            networks.mlp(self.weights, name, self.config.hidden_layers, ops.stack(self.features(r)), ops)
        )

    def inertia(self, r: so3.Mat3) -> so3.Mat3:
        return s3.symmetric_from_cholesky(self._net("inertia", r), self.config.inertia_epsilon)

    def _potential_and_gradient(self, r: so3.Mat3) -> tuple[Any, tuple[Any, ...], tuple[Any, ...]]:
        ops = self.ops
        features = self.features(r)
        value, gradient = networks.scalar_mlp_value_and_gradient(
            self.weights, "potential", self.config.hidden_layers, ops.stack(features), ops)
        return ops.unstack(value)[0], ops.unstack(gradient), features

    def potential(self, r: so3.Mat3) -> Any:
        return self._potential_and_gradient(r)[0]

    def potential_torque(self, r: so3.Mat3) -> so3.Vec3:
        _, gradient, features = self._potential_and_gradient(r)
        if self.config.variant == "so3-matrix":
            rows = tuple(tuple(gradient[3 * i + j] for j in range(3)) for i in range(3))
            return torque_from_euclidean_gradient(r, rows)  # type: ignore[arg-type]
        # Within a branch the preimage moves as q ⊗ exp(ε η / 2) when R moves as R exp(ε[η]×), so
        # d/dε U = ½ ηᵀ H(q) ∇U(q): the torque is −½ H(q) ∇U(q) (no derivative of the branch choice).
        return s3.scale(-0.5, s3.H_apply(features, gradient))  # type: ignore[arg-type,return-value]

    def control_gain(self, r: so3.Mat3) -> tuple[tuple[Any, ...], ...]:
        flat = self._net("gain", r)
        m = self.control_dim
        return tuple(tuple(flat[i * m + j] for j in range(m)) for i in range(3))

    def dissipation(self, r: so3.Mat3) -> so3.Mat3 | None:
        return None
