"""The unstructured baseline: an MLP that predicts the increment of the state ``(q, ω)``.

``x_{k+1} = F(x_k, u_k)`` with

    q_{k+1} = normalize(q_k + h·a(q_k, ω_k, u_k)),     ω_{k+1} = ω_k + h·s·b(q_k, ω_k, u_k)

where ``(a, b)`` (4 + 3 outputs) is one tanh MLP of the features ``(q, ω/s, u/u_s)`` and ``s`` is a
fixed speed scale (so the inputs and outputs are O(1)). There is no energy, no inertia, no
variational structure: what the S3FVIN's structure buys is measured against this model
(``docs/data-efficiency.md``).

Sign consistency (our choice, stated): ``q`` and ``−q`` are the same rotation, so the MLP is made
*sign-equivariant* the way the S3FVIN's sign-invariant variant is — by symmetrizing over ``±q``:
``a(q) = ½(n_a(q) − n_a(−q))`` and ``b(q) = ½(n_b(q) + n_b(−q))``, whence ``F(−q, ω, u) = (−q', ω')``.
Without it the network would have to learn the same map twice (the data's ``q`` covers both
signs), which would charge the baseline for a symmetry the S3FVIN gets for free.

Training goes through the package's one loop (:func:`fvin_mpc.learning.training.train` with
``model_factory=IncrementMLP``): same windows, same multi-step rollout loss, same optimizer (LM),
same early stopping. :func:`benchmarks.data_efficiency.export_mlp` builds the same step in CasADi as an
:class:`~fvin_mpc.control.model_export.ExportedModel` with the S3FVIN's call signature
``F(x[7], u[m]) -> (x_next, residual)`` (``residual`` is 0: no implicit solve), so the *same*
MPC runs on it.

Energy: the MPC's terminal energy-deficit cost needs the model's energy, which this model does not
have. :func:`benchmarks.data_efficiency.export_mlp` takes the energy from a closed-form body (the scene's,
read off the MJCF)
and says so in the model's name: privileged information that favours the baseline.

Float64 throughout (the torch parameters are ``torch.float64``).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fvin_mpc.core.networks import DictConfig, add_mlp_shapes, check_weight_shapes
from fvin_mpc.learning.training import train

#: ``ModelConfig``-like name of the baseline (progress bars, reports).
MLP_VARIANT = "mlp"
STATE_FEATURES, Q_OUTPUTS, OMEGA_OUTPUTS = 7, 4, 3


@dataclass(frozen=True)
class MLPConfig(DictConfig):
    """Architecture of :class:`IncrementMLP`.

    Attributes:
        control_dim: number of controls ``m``.
        hidden_width, hidden_layers: the tanh MLP's hidden layers.
        step_size: ``h`` (s), the data's control period.
        omega_scale: ``s`` (rad/s): the network sees ``ω/s`` and its ``ω`` output is scaled by ``s``.
        control_scale: ``u_s``: the network sees ``u/u_s`` (the actuator bound is a good choice).
        sign_symmetric: symmetrize over ``±q`` (module docstring); ``False``: the bare MLP.
    """

    CONFIG_NAME = "MLP baseline"

    control_dim: int = 1
    hidden_width: int = 32
    hidden_layers: int = 2
    step_size: float = 0.05
    omega_scale: float = 10.0
    control_scale: float = 2.0
    sign_symmetric: bool = True

    def __post_init__(self) -> None:
        if self.control_dim < 1 or self.hidden_width < 1 or self.hidden_layers < 1:
            raise ValueError("control_dim, hidden_width and hidden_layers must be >= 1")
        if not (self.step_size > 0 and self.omega_scale > 0 and self.control_scale > 0):
            raise ValueError("step_size, omega_scale and control_scale must be > 0")

    @property
    def variant(self) -> str:
        return MLP_VARIANT

    @property
    def inputs(self) -> int:
        return STATE_FEATURES + self.control_dim


def mlp_shapes(config: MLPConfig) -> dict[str, tuple[int, ...]]:
    shapes: dict[str, tuple[int, ...]] = {}
    add_mlp_shapes(shapes, "increment", config.inputs, Q_OUTPUTS + OMEGA_OUTPUTS, config.hidden_width,
                   config.hidden_layers)
    return shapes


def init_mlp_weights(config: MLPConfig, seed: int = 0) -> dict[str, np.ndarray]:
    """Glorot-uniform hidden layers and a last layer 100× smaller: the untrained model is close to
    ``x_{k+1} = x_k`` (renormalized), a sane start for multi-step rollouts."""
    rng = np.random.default_rng(seed)
    shapes = mlp_shapes(config)
    last = config.hidden_layers
    weights = {}
    for name, shape in shapes.items():
        if "_b" in name:
            weights[name] = np.zeros(shape)
            continue
        limit = np.sqrt(6.0 / sum(shape))
        weights[name] = rng.uniform(-limit, limit, size=shape) * (0.01 if name.endswith(f"_w{last}") else 1.0)
    return weights


def check_mlp_weights(weights: Mapping[str, Any], config: MLPConfig) -> None:
    check_weight_shapes(weights, mlp_shapes(config), MLPConfig.CONFIG_NAME)


def _layers(weights: Mapping[str, Any], config: MLPConfig) -> list[tuple[Any, Any]]:
    return [(weights[f"increment_w{i}"], weights[f"increment_b{i}"]) for i in range(config.hidden_layers + 1)]


# ----------------------------------------------------------------------------- torch
def _torch_model_class() -> Any:
    """The torch class, defined on first use so that the CasADi export needs no torch."""
    import torch

    from fvin_mpc.learning.model import LearnedModel, TorchStep, rollout_with_step

    class IncrementMLP(LearnedModel):
        """The baseline in torch (float64, batched): ``step(q (B,4), ω (B,3), u (B,m))``, ``rollout``
        as :class:`~fvin_mpc.learning.model.S3FVIN`'s, so :func:`~fvin_mpc.learning.training.train`
        trains it unchanged."""

        def __init__(self, config: MLPConfig, weights: Mapping[str, np.ndarray] | None = None, seed: int = 0) -> None:
            super().__init__(config, weights, seed, init_mlp_weights, check_mlp_weights)

        def _network(self, q: Any, omega: Any, u: Any) -> Any:
            hidden = torch.cat([q, omega / self.config.omega_scale, u / self.config.control_scale], dim=-1)
            layers = _layers(self.weights, self.config)
            for weight, bias in layers[:-1]:
                hidden = torch.tanh(hidden @ weight.T + bias)
            weight, bias = layers[-1]
            return hidden @ weight.T + bias

        def increments(self, q: Any, omega: Any, u: Any) -> tuple[Any, Any]:
            """``(a, b)``: the quaternion and angular-velocity rates, symmetrized over ``±q`` if asked."""
            out = self._network(q, omega, u)
            if self.config.sign_symmetric:
                mirrored = self._network(-q, omega, u)
                return 0.5 * (out[..., :4] - mirrored[..., :4]), 0.5 * (out[..., 4:] + mirrored[..., 4:])
            return out[..., :4], out[..., 4:]

        def step(self, q: Any, omega: Any, u: Any, with_residual: bool = False, newton_iters: int | None = None) -> Any:
            a, b = self.increments(q, omega, u)
            h = self.config.step_size
            p = q + h * a
            q_next = p / torch.sqrt((p * p).sum(-1, keepdim=True))
            residual = torch.zeros(q.shape[:-1], dtype=q.dtype) if with_residual else None
            return TorchStep(q_next, omega + h * self.config.omega_scale * b, residual)

        def rollout(self, q0: Any, omega0: Any, controls: Any, step: Any = None) -> tuple[Any, Any]:
            return rollout_with_step(step or self.step, q0, omega0, controls)

        def forward(self, q: Any, omega: Any, u: Any) -> tuple[Any, Any]:
            out = self.step(q, omega, u)
            return out.q, out.omega

    return IncrementMLP


def IncrementMLP(config: MLPConfig, weights: Mapping[str, np.ndarray] | None = None, seed: int = 0) -> Any:
    """A torch :class:`IncrementMLP` (a factory for ``train(model_factory=...)``)."""
    return _torch_model_class()(config, weights, seed)


def train_mlp(data: Any, config: MLPConfig, settings: Any, progress: bool = True) -> tuple[Any, dict[str, Any]]:
    """Train the baseline through the package's loop; returns ``(model, report)`` as ``train``."""

    return train(data, config, settings, progress=progress, model_factory=IncrementMLP)


# ----------------------------------------------------------------------------- files
def save_mlp(path: str | Path, config: MLPConfig, weights: Mapping[str, np.ndarray], **metadata: Any) -> Path:
    """``<stem>.npz`` (float64 weights) and ``<stem>.json`` (config and ``metadata``); returns the stem."""
    stem = Path(path).with_suffix("")
    stem.parent.mkdir(parents=True, exist_ok=True)
    check_mlp_weights(weights, config)
    np.savez(stem.with_suffix(".npz"), **{k: np.asarray(v, dtype=np.float64) for k, v in weights.items()})
    stem.with_suffix(".json").write_text(json.dumps({"model": config.to_dict(), **metadata}, indent=1) + "\n")
    return stem


def load_mlp(path: str | Path) -> tuple[MLPConfig, dict[str, np.ndarray]]:
    stem = Path(path).with_suffix("")
    config = MLPConfig.from_dict(json.loads(stem.with_suffix(".json").read_text())["model"])
    with np.load(stem.with_suffix(".npz")) as archive:
        weights = {name: archive[name].astype(np.float64) for name in archive.files}
    check_mlp_weights(weights, config)
    return config, weights


# ----------------------------------------------------------------------------- CasADi export
def mlp_step_function(weights: Mapping[str, np.ndarray], config: MLPConfig, name: str = "mlp_step") -> Any:
    """``F(x[7], u[m]) -> (x_next[7], residual)`` as an SX function (``residual`` ≡ 0), the same
    arithmetic as :class:`IncrementMLP`'s step."""
    import casadi as ca

    layers = [
        (ca.DM(np.asarray(w, dtype=float)), ca.DM(np.asarray(b, dtype=float))) for w, b in _layers(weights, config)
    ]

    def network(q: Any, omega: Any, u: Any) -> Any:
        hidden = ca.vertcat(q, omega / config.omega_scale, u / config.control_scale)
        for weight, bias in layers[:-1]:
            hidden = ca.tanh(ca.mtimes(weight, hidden) + bias)
        weight, bias = layers[-1]
        return ca.mtimes(weight, hidden) + bias

    x = ca.SX.sym("x", STATE_FEATURES)
    u = ca.SX.sym("u", config.control_dim)
    q, omega = x[:4], x[4:]
    out = network(q, omega, u)
    a, b = out[:4], out[4:]
    if config.sign_symmetric:
        mirrored = network(-q, omega, u)
        a, b = 0.5 * (a - mirrored[:4]), 0.5 * (b + mirrored[4:])
    p = q + config.step_size * a
    x_next = ca.vertcat(p / ca.sqrt(ca.sumsqr(p)), omega + config.step_size * config.omega_scale * b)
    return ca.Function(name, [x, u], [x_next, ca.SX(0)], ["x", "u"], ["x_next", "residual"])
