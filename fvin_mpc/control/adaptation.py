"""Online adaptation of a few physical parameters of a model from recent transitions.

When the body changes in operation (a heavier bob, a weaker motor), an input-disturbance estimate
absorbs a constant offset but not a changed mass, whose effect depends on the state. Here a small
named parameter set of a pivoted (S³) or free (R³ × S³) model is re-fitted from a sliding window of measured
transitions ``(x_k, u_k, x_{k+1})`` by damped Gauss–Newton (Levenberg–Marquardt), one bounded
iteration per call, so that it can run in a control period's spare time. The estimator is told
nothing about when or what changed: it sees only the window, whose length sets how fast old
transitions are forgotten.

The parameters act on the model's terms (:class:`ScaledTerms`, any backend, learned or closed form):

* ``mass`` — multiplies the inertia ``J`` and the potential ``U`` together: the body made uniformly
  denser or lighter (a pivoted rod whose density doubles, a point bob whose mass doubles);
* ``gain<i>`` — multiplies column ``i`` of the control gain ``g``: actuator ``i``'s strength;
* ``damping`` — joint damping added to the model's own dissipation, in the model's force units (the
  dissipation ``D`` gets ``2·damping·I``: the factor of two of ``DESIGN.md``).

**The free scale.** Multiplying ``J``, ``U``, ``g`` and ``D`` by one constant leaves every motion
unchanged (the step's equations are homogeneous in them), so ``mass``, the gains and ``damping``
cannot all be estimated at once: only ratios are observable. The estimator fits only the parameters
named ``free`` and holds the others at their values; the default set pins the gains at 1 — the motor's
torque constant is taken as known, the body is what changes — so ``mass`` is the body's mass relative
to the model's (for a learned model, relative to the body it was trained on, whatever scale it learned)
and ``damping`` is in that model's units. If actuators and body may both change, pin one of them: a
fitted ``mass`` with the gains pinned is the true mass ratio divided by the true gain ratio.

Physical bounds: ``mass`` and the gains stay within ``[MINIMUM_SCALE, 1 / MINIMUM_SCALE]`` of the model's
(positive inertia and potential, actuators that still push the way the model says), ``damping`` keeps the
total dissipation positive semi-definite. A step that leaves the bounds is projected onto them; a step that
does not lower the window's prediction error is rejected (the parameters stay, the damping grows).

Excitation: a window in which a parameter barely moves the predictions says nothing about it — a body
held still at upright swings the same whatever its mass — and fitting it there only chases the model's own
one-step error (half a second near upright with next to no torque: mass 9.8 and damping 16 after ten
steps, tests/test_adaptation.py). So a parameter is fitted only while a *relevant change* of it
(:data:`RELEVANT_CHANGE`: 10 % of a mass or gain; a damping that changes the decay rate by 0.1 s⁻¹) would
move the window's predictions by at least ``min_effect`` (rad/s, RMS over the window); otherwise it is
held this call.

**A free body** (R³ × S³: a craft): the parameters are ``mass`` — the mass matrix, the whole potential
(a payload: gravity's pull grows with it) and the rotational inertia together, the body made uniformly denser
as a pivoted body's ``mass`` —, ``inertia`` (the rotational inertia relative to that) and ``gain<i>``, and they
act through the model's run-time parameters (:func:`free_body_vector`: a learned model's Cholesky factors take
the square root, its potential's uniform field and output layer the mass; a closed form's ``mass`` and
``inertia`` directly),
so the estimator differentiates the very step the real-time MPC plans with. The residual adds the position
over the step (m/s) to the pivoted one's. The default fits the mass alone, the gains pinned for the free
scale (:func:`default_free`), on the translation's rows of the residual (:data:`TRANSLATION_ROWS`). A
hovering craft shows its mass — thrust against weight — so the excitation gate rarely holds it.

**Low-rank corrections of the networks** (a learned free body exported with ``low_rank`` ``r``,
:func:`~fvin_mpc.core.model_parameters.low_rank_blocks`): the entries of ``C`` in ``W → W + C Σ_r V_rᵀ`` of each
output layer but the potential's, additive (zero: the model as trained), unbounded, fitted on every residual row —
``free=("lowrank",)`` or a block's name. A black-box set beside the physical ones: it knows no mass, so the control
cost's effect (``MPCSettings.control_cost``) does not follow it.

The interface is a plain ``{name: value}`` dict (:attr:`ParameterEstimator.parameters`), for a real-time
MPC that takes model parameters at run time to read at its next preparation.

**In the loop** (:class:`AdaptiveRTI`): a real-time MPC wrapped so that each period, after its control is
sent, the transition that just ended joins the window, the estimator takes at most one step, and the
estimate goes to the MPC through ``set_parameters`` (:func:`rti_parameters`), which its next preparation
uses without recompiling. The MPC's model parameters are not the estimator's: they have a per-actuator
``gain_scale`` and the model's own explicit values, no ``mass``. The step being invariant under one common
factor on ``J``, ``U``, ``g`` and ``D``, a body ``m`` times heavier with gains ``g_i`` and added damping ``d``
steps exactly like the unchanged body with ``gain_scale_i = g_i / m`` and dissipation ``(D + 2·d·I) / m`` —
so the mass reaches the MPC as a gain scale, and the model's inertia and potential stay as exported.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, replace
from typing import Any, Mapping, Sequence

import casadi as ca
import numpy as np

from fvin_mpc.control.model_export import ExportedModel, compile_functions
from fvin_mpc.core import s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.model_parameters import GAIN_SCALE, LOW_RANK_PREFIX
from fvin_mpc.core.space import R3S3, S3

CA = get_ops("casadi")
#: The smallest value ``mass`` and a gain may take: a tenth of the model's (the largest: ten times).
MINIMUM_SCALE = 0.1
#: The change of each kind of parameter that matters: 10 % of a mass or a gain; for ``damping``, the
#: damping that changes the decay rate ``d/J`` by 0.1 s⁻¹ (times the model's inertia, in its units); for an
#: entry of a low-rank output-layer correction, a tenth of a unit direction's entry (``0.1/√out``: the
#: correction ``C = α U_r`` scales the layer's strongest directions by ``1 + α``, and ``U_r``'s columns have
#: unit norm).
RELEVANT_CHANGE = {"mass": 0.1, "gain": 0.1, "damping_rate": 0.1, "low_rank": 0.1}
#: ``min_effect``'s default (rad/s): the learned pendulum's own one-step RMS prediction error near upright
#: (2.0e-3 rad/s, checked in tests/test_adaptation.py) — a parameter that moves the predictions by less than
#: the model's own error cannot be told from it.
MIN_EFFECT = 2e-3
#: ``min_effect``'s default on a free body (m/s and rad/s together: the RMS over the window of the 12-entry
#: residual's norm): the learned quadrotor's own one-step error in hover on MuJoCo, 5.5e-4
#: (tests/test_adaptation_free_body.py checks it). A hovering craft shows its mass (thrust against weight): a
#: tenth more moves its predictions by 2.2e-2, forty times that.
FREE_BODY_MIN_EFFECT = 5e-4


def parameter_names(control_dim: int) -> tuple[str, ...]:
    """Every parameter a model with ``control_dim`` actuators has, in vector order."""
    return ("mass", *(f"gain{i}" for i in range(control_dim)), "damping")


def nominal_parameters(control_dim: int) -> dict[str, float]:
    """The values that leave a model as it is."""
    return {name: (0.0 if name == "damping" else 1.0) for name in parameter_names(control_dim)}


#: A free body's (R³ × S³) estimator parameters, per kind of run-time parameter block: which estimates scale
#: the block and with which powers (a Cholesky factor takes the square root). ``mass`` scales the mass matrix,
#: the whole potential (gravity's pull grows with the mass: a payload) and the rotational inertia together —
#: the body made uniformly denser, as a pivoted body's ``mass`` — and ``inertia`` the rotational inertia on top
#: of it (``J · mass · inertia``): a fitted mass alone then keeps the model's inertia per kilogram, and the step
#: of ``mass`` ``b`` is the unchanged body's on ``u / b``. A learned model's potential network enters through
#: its output layer (``potential_w…``, linear in ``U``). ``ε`` of a Cholesky parametrization (1e-6 of the mass,
#: 1e-8 of the inertia) does not scale.
FREE_BODY_SCALING: dict[str, tuple[tuple[str, float], ...]] = {
    "mass": (("mass", 1.0),), "mass_cholesky": (("mass", 0.5),), "potential_linear": (("mass", 1.0),),
    "potential_w": (("mass", 1.0),), "inertia": (("mass", 1.0), ("inertia", 1.0)),
    "inertia_cholesky": (("mass", 0.5), ("inertia", 0.5))}


#: The rows of a free body's residual (:func:`free_body_residual`) that a fit of its mass alone reads: the
#: translation (position over the step, then velocity). Thrust against weight shows the mass there and nothing
#: else; the rotation's rows also carry torques no mass explains — a worn rotor's, which the disturbance
#: estimate absorbs — and with the mass scaling the inertia too they pulled the estimate to 2.7–3.6 for one
#: rotor at 70 % and the craft fell (docs/adaptation.md). A free inertia or gain is fitted on every row.
TRANSLATION_ROWS = (0, 1, 2, 6, 7, 8)


def free_body_parameter_names(model: ExportedModel) -> tuple[str, ...]:
    """Every estimator parameter of a free body, in vector order: ``mass``, ``inertia``, ``gain<i>``, then the
    entries of the low-rank output-layer corrections a learned model exported with ``low_rank`` carries
    (:func:`low_rank_names`)."""
    return ("mass", "inertia", *(f"gain{i}" for i in range(model.control_dim)), *low_rank_names(model))


def low_rank_names(model: ExportedModel) -> tuple[str, ...]:
    """The flat names of ``model``'s low-rank output-layer corrections
    (:func:`~fvin_mpc.core.model_parameters.low_rank_blocks`: ``lowrank_gain_w2[0,0]``, …), additive, zero
    when nothing changed; ``()`` for a model exported without them."""
    return tuple(name for block in model.model_parameters.blocks if block.name.startswith(LOW_RANK_PREFIX)
                 for name in block.flat_names)


def _pivot_estimator(model: ExportedModel) -> bool:
    """Whether ``model`` takes the pivoted body's estimator (S³ terms: mass, gains, damping) rather than the free
    body's (its run-time parameter blocks)."""
    return model.space is S3


def nominal_estimate(model: ExportedModel) -> dict[str, float]:
    """The estimate that leaves ``model`` as it is, pivoted (:func:`nominal_parameters`) or free (every scale 1,
    every low-rank correction 0)."""
    if _pivot_estimator(model):
        return nominal_parameters(model.control_dim)
    additive = set(low_rank_names(model))
    return {name: 0.0 if name in additive else 1.0 for name in free_body_parameter_names(model)}


def _free_body_scaling(block_name: str) -> tuple[tuple[str, float], ...]:
    if block_name.startswith("potential_w"):
        return FREE_BODY_SCALING["potential_w"]
    return FREE_BODY_SCALING.get(block_name, ())


def free_body_vector(model: ExportedModel, estimate: Sequence[Any]) -> list[Any]:
    """The run-time parameter vector (entries: numbers or CasADi symbols, as ``estimate``'s) of a free body's
    ``model`` that steps like the body with the estimator's ``estimate`` (:func:`free_body_parameter_names`'
    order): each block of :data:`FREE_BODY_SCALING` at its own value times its scales, the gain scale times
    the gains, a low-rank correction as estimated, every other block (gravity, a drag's dissipation) at the
    model's value."""
    names = free_body_parameter_names(model)
    value = dict(zip(names, estimate))
    entries: list[Any] = []
    for block in model.model_parameters.blocks:
        own = np.ravel(block.default)
        if block.name == GAIN_SCALE:
            entries += [own[i] * value[f"gain{i}"] for i in range(own.size)]
            continue
        if block.name.startswith(LOW_RANK_PREFIX):
            entries += [value[name] for name in block.flat_names]
            continue
        factor: Any = 1.0
        for name, power in _free_body_scaling(block.name):
            factor = factor * (value[name] if power == 1.0 else value[name] ** power)
        entries += [float(entry) * factor for entry in own]
    return entries


def free_body_residual(model: ExportedModel) -> ca.Function:
    """``r(x[13], u[m], x_next[13], θ) -> (r[12], ∂r/∂θ)`` of a free body, ``θ`` in
    :func:`free_body_parameter_names`' order: the measured next state against the one the model with ``θ``
    predicts (through its run-time parameters, :func:`free_body_vector`) from the measured ``x``, ``u``, in the
    predicted state's chart — position and rotation over the step divided by ``h`` (m/s and rad/s, like the
    rates), then ``v`` and ``ω``."""
    model.require(R3S3, by="the free-body parameter estimator")
    layout, h = model.space.layout, model.step_size
    n, m = model.state_dim, model.control_dim
    x, x_next, u = ca.SX.sym("x", n), ca.SX.sym("x_next", n), ca.SX.sym("u", m)
    theta = ca.SX.sym("theta", len(free_body_parameter_names(model)))
    p = ca.vertcat(*free_body_vector(model, [theta[i] for i in range(theta.shape[0])]))
    predicted = model.parametric_step(x, u, p)[0]
    r = layout.rates_over_step(layout.local(predicted, x_next, CA), h, CA)
    return ca.Function("free_body_residual", [x, u, x_next, theta], [r, ca.jacobian(r, theta)],
                       ["x", "u", "x_next", "p"], ["r", "dr_dp"])


class ScaledTerms:
    """A pivoted model's terms (``inertia``, ``potential``, ``control_gain``, ``dissipation``) with the
    parameters of the module docstring applied; ``parameters`` in :func:`parameter_names`' order, numbers
    or symbols of the terms' backend."""

    def __init__(self, terms: Any, parameters: Sequence[Any]) -> None:
        self.terms = terms
        self.control_dim = terms.control_dim
        self.constant_inertia = terms.constant_inertia
        # A model that steps on a hinge must keep doing so with its parameters changed.
        self.hinge_axis = getattr(terms, "hinge_axis", None)
        self.mass, *gains, self.damping = parameters
        self.gains = tuple(gains)

    def inertia(self, q: s3.Quat) -> s3.Mat3:
        return tuple(tuple(self.mass * entry for entry in row) for row in self.terms.inertia(q))  # type: ignore[return-value]

    def potential(self, q: s3.Quat) -> Any:
        return self.mass * self.terms.potential(q)

    def potential_gradient(self, q: s3.Quat) -> s3.Quat:
        return s3.scale(self.mass, self.terms.potential_gradient(q))

    def control_gain(self, q: s3.Quat) -> tuple[tuple[Any, ...], ...]:
        return tuple(tuple(entry * gain for entry, gain in zip(row, self.gains)) for row in self.terms.control_gain(q))

    def dissipation(self, q: s3.Quat) -> s3.Mat3:
        own = self.terms.dissipation(q)
        added = 2.0 * self.damping
        return tuple(tuple((0.0 if own is None else own[i][j]) + (added if i == j else 0.0) for j in range(3))
                     for i in range(3))  # type: ignore[return-value]


def prediction_residual(model: ExportedModel) -> ca.Function:
    """``r(x[7], u[m], x_next[7], p) -> (r[6], ∂r/∂p)``: the measured next state against the one the model
    with parameters ``p`` predicts from the measured ``x``, ``u`` — orientation as the chart's rotation over
    the step (``2·Im/Re`` of ``q_pred* ⊗ q_meas`` divided by ``h``: rad/s, like the rate part), then
    ``ω_meas − ω_pred``."""
    model.require(S3, by="the parameter estimator")
    if model.casadi_terms is None:
        raise ValueError(f"model {model.name!r} has no rigid-body terms to put parameters on")
    layout, m = S3.layout, model.control_dim
    x, x_next = ca.SX.sym("x", layout.state_dim), ca.SX.sym("x_next", layout.state_dim)
    u, p = ca.SX.sym("u", m), ca.SX.sym("p", len(parameter_names(m)))
    terms = ScaledTerms(model.casadi_terms, [p[i] for i in range(p.shape[0])])
    predicted, _ = S3.step(x, u, terms, model.step_size, model.newton_iters, CA)
    r = layout.rates_over_step(layout.local(predicted, x_next, CA), model.step_size, CA)
    return ca.Function("prediction_residual", [x, u, x_next, p], [r, ca.jacobian(r, p)],
                       ["x", "u", "x_next", "p"], ["r", "dr_dp"])


def expand_free(model: ExportedModel, free: Sequence[str]) -> tuple[str, ...]:
    """``free`` with each low-rank block's name (``lowrank_gain_w2``) or ``"lowrank"`` (all of them) replaced by
    its entries' flat names; the other names as given."""
    blocks = {block.name: block.flat_names for block in model.model_parameters.blocks
              if block.name.startswith(LOW_RANK_PREFIX)}
    expanded: list[str] = []
    for name in free:
        if name != "lowrank":
            expanded += blocks.get(name, (name,))
        elif blocks:
            expanded += [entry for entries in blocks.values() for entry in entries]
        else:
            raise ValueError(f"model {model.name!r} carries no low-rank corrections; export it with low_rank > 0")
    return tuple(expanded)


def default_free(model: ExportedModel) -> tuple[str, ...]:
    """The parameters fitted unless told otherwise: the body's, the actuators pinned (the free scale) —
    ``("mass", "damping")`` on a pivoted body, ``("mass",)`` on a free one (its inertia follows the mass: uniformly
    denser). A free body's ``inertia`` and gains are opt-in: on the quadrotor's payload they track as the mass
    alone does, and four free gains track a worn rotor worse than it (1.62× against 1.20× the unchanged craft's
    figure-eight error, docs/adaptation.md)."""
    return ("mass", "damping") if _pivot_estimator(model) else ("mass",)


#: The identity orientation as a one-sample NumPy quaternion, where a model's constant terms are read.
_IDENTITY = (np.ones(1), np.zeros(1), np.zeros(1), np.zeros(1))


class TransitionWindow:
    """The last ``capacity`` measured transitions ``(x_k, u_k, x_{k+1})``, oldest dropped first."""

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"a window holds at least one transition, got capacity {capacity}")
        self.capacity = capacity
        self._items: deque[tuple[np.ndarray, np.ndarray, np.ndarray]] = deque(maxlen=capacity)

    def add(self, x: Any, u: Any, x_next: Any) -> None:
        self._items.append((np.asarray(x, dtype=float).copy(), np.atleast_1d(np.asarray(u, dtype=float)).copy(),
                            np.asarray(x_next, dtype=float).copy()))

    def __len__(self) -> int:
        return len(self._items)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(X (7, N), U (m, N), X_next (7, N))``, columns oldest first."""
        x, u, x_next = zip(*self._items)
        return np.array(x).T, np.array(u).T, np.array(x_next).T


@dataclass(frozen=True)
class Update:
    """What one call of :meth:`ParameterEstimator.update` did.

    Attributes:
        accepted: whether the step lowered the window's prediction error (and was kept).
        parameters: the estimate after the call.
        error_before: the window's mean squared prediction error (rad²/s²) at the old parameters.
        error_after: the same at the kept parameters (``error_before`` when rejected).
        candidate_error: the error the proposed step would have given.
        damping: the Levenberg–Marquardt damping after the call.
        fitted: the free parameters the window excited enough to be fitted (``()``: none, nothing proposed).
    """

    accepted: bool
    parameters: dict[str, float]
    error_before: float
    error_after: float
    candidate_error: float
    damping: float
    fitted: tuple[str, ...] = ()


class ParameterEstimator:
    """Levenberg–Marquardt on the one-step prediction error of a sliding window.

    Args:
        model: a pivoted (S³) model with rigid-body terms, or a free body (R³ × S³) whose run-time parameters
            carry its mass and inertia (module docstring, "A free body"); learned or closed form.
        free: the parameters to fit (default :func:`default_free`: the gains pinned, see the module
            docstring on the free scale); the others keep their values in ``initial``.
        initial: starting values (default: :func:`nominal_parameters`; a free body: every scale 1).
        damping: the Levenberg–Marquardt damping λ to start with (relative to ``diag(JᵀJ)``).
        min_effect: a parameter is fitted only while a relevant change of it moves the window's predictions
            by at least this (RMS over the window; module docstring, "Excitation"); 0 fits whatever the
            window; default :data:`MIN_EFFECT` (rad/s), a free body :data:`FREE_BODY_MIN_EFFECT`.
        compiled_window: compile the residual over a window of this many transitions to C once, here (a
            cached library; a shorter window is padded and cut): the learned quadrotor's step over 40
            transitions took 21 ms as a CasADi SX function, more than its 20 ms period. ``None``: uncompiled.
    """

    def __init__(self, model: ExportedModel, free: Sequence[str] | None = None,
                 initial: Mapping[str, float] | None = None, damping: float = 1e-3,
                 min_effect: float | None = None, compiled_window: int | None = None) -> None:
        pivoted = _pivot_estimator(model)
        self.names = parameter_names(model.control_dim) if pivoted else free_body_parameter_names(model)
        free = default_free(model) if free is None else expand_free(model, free)
        unknown = [name for name in (*free, *(initial or {})) if name not in self.names]
        if unknown or not free:
            raise ValueError(f"unknown or no free parameters {unknown or list(free)}; expected some of {self.names}")
        if not pivoted:
            carried = {name for block in model.model_parameters.blocks for name, _ in _free_body_scaling(block.name)}
            missing = [name for name in free if name in ("mass", "inertia") and name not in carried]
            if missing:
                raise ValueError(f"model {model.name!r} has no run-time parameter block that carries its "
                                 f"{' or '.join(missing)}; leave {missing} out of free")
        self.free = tuple(free)
        self._free_index = np.array([self.names.index(name) for name in self.free])
        full = prediction_residual(model) if pivoted else free_body_residual(model)
        # The Jacobian with respect to the free parameters only: a free body's step differentiated for its one
        # free mass costs a third of the one for all six parameters (the learned quadrotor, 40 transitions).
        inputs = full.sx_in()  # an SX call inlines the graph
        r = full(*inputs)[0]
        #: the residual's rows the fit reads (:data:`TRANSLATION_ROWS` for a free body's mass alone), else all
        self.rows = TRANSLATION_ROWS if not pivoted and set(self.free) <= {"mass"} else tuple(range(r.shape[0]))
        r = r[list(self.rows)]
        self._residual = ca.Function(f"{full.name()}_free", inputs,
                                     [r, ca.jacobian(r, ca.vertcat(*[inputs[3][i] for i in self._free_index]))])
        self._residual_size = self._residual.size1_out(0)
        self._mapped: dict[int, ca.Function] = {}
        self._compiled: tuple[int, ca.Function, ca.Function] | None = None
        if compiled_window is not None:
            values = ca.Function(f"{full.name()}_value", inputs, [r])  # a candidate is judged by r alone
            mapped = [function.map(compiled_window) for function in (self._residual, values)]
            loaded, _ = compile_functions(mapped, f"adaptation_{'pivoted' if pivoted else 'free'}")
            self._compiled = (compiled_window, *(loaded[function.name()] for function in mapped))
        if pivoted:
            self._lower, self._relevant = self._lower_bounds(model), self._relevant_changes(model)
            self._upper = np.where(np.arange(len(self.names)) == len(self.names) - 1, np.inf, 1.0 / MINIMUM_SCALE)
        else:
            scales, additive = 2 + model.control_dim, len(self.names) - 2 - model.control_dim  # mass, inertia, gains
            self._lower = np.concatenate([np.full(scales, MINIMUM_SCALE), np.full(additive, -np.inf)])
            self._upper = np.concatenate([np.full(scales, 1.0 / MINIMUM_SCALE), np.full(additive, np.inf)])
            low_rank = [RELEVANT_CHANGE["low_rank"] / math.sqrt(block.default.shape[0])
                        for block in model.model_parameters.blocks if block.name.startswith(LOW_RANK_PREFIX)
                        for _ in range(block.size)]
            self._relevant = np.array([RELEVANT_CHANGE["mass"], RELEVANT_CHANGE["mass"],
                                       *[RELEVANT_CHANGE["gain"]] * model.control_dim, *low_rank])
        self.min_effect = float((MIN_EFFECT if pivoted else FREE_BODY_MIN_EFFECT) if min_effect is None else min_effect)
        values = {**nominal_estimate(model), **(initial or {})}
        self._p = np.array([float(values[name]) for name in self.names])
        if np.any(self._p < self._lower - 1e-12) or np.any(self._p > self._upper + 1e-12):
            raise ValueError(f"initial parameters {values} are outside their physical bounds")
        self.damping = float(damping)
        self._initial = (self._p.copy(), self.damping)

    def reset(self) -> None:
        """Back to the initial estimate and damping (a new episode of a body that may differ again)."""
        self._p, self.damping = self._initial[0].copy(), self._initial[1]

    def _relevant_changes(self, model: ExportedModel) -> np.ndarray:
        inertia = np.array(model.numpy_terms.inertia(_IDENTITY), dtype=float)[..., 0]
        scale = RELEVANT_CHANGE["damping_rate"] * float(np.trace(inertia)) / 3.0
        return np.array([RELEVANT_CHANGE["mass"]] + [RELEVANT_CHANGE["gain"]] * (len(self.names) - 2) + [scale])

    def _lower_bounds(self, model: ExportedModel) -> np.ndarray:
        lower = np.full(len(self.names), MINIMUM_SCALE)
        own = model.numpy_terms.dissipation(_IDENTITY)
        # The added damping may take away at most what the model's own (constant) dissipation has.
        smallest = 0.0 if own is None else float(np.linalg.eigvalsh(np.array(own, dtype=float)[..., 0]).min())
        lower[-1] = -max(smallest, 0.0) / 2.0
        return lower

    @property
    def parameters(self) -> dict[str, float]:
        """The current estimate, ``{name: value}``."""
        return {name: float(value) for name, value in zip(self.names, self._p)}

    def _evaluate(self, window: TransitionWindow, p: np.ndarray,
                  jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
        x, u, x_next = window.arrays()
        n = x.shape[1]
        if self._compiled is not None and n <= self._compiled[0]:
            # the compiled map takes a whole window: pad with copies of the last transition, cut after
            pad = self._compiled[0] - n
            columns = [np.concatenate([a, np.repeat(a[:, -1:], pad, axis=1)], axis=1) for a in (x, u, x_next)]
            if not jacobian:
                r = np.asarray(self._compiled[2](*columns, p))[:, :n]
                return np.asarray(r, dtype=float).T.reshape(-1), None
            r, dr = self._compiled[1](*columns, p)
            r, dr = np.asarray(r)[:, :n], np.asarray(dr)[:, :n * self._free_index.size]
        else:
            if n not in self._mapped:
                self._mapped[n] = self._residual.map(n)
            r, dr = self._mapped[n](x, u, x_next, p)
        r = np.asarray(r, dtype=float).T.reshape(-1)  # transition after transition
        if not jacobian:
            return r, None
        size, free = self._residual_size, self._free_index.size
        # the map stacks the (size, free) blocks side by side
        blocks = np.asarray(dr, dtype=float).reshape(size, n, free)
        return r, blocks.transpose(1, 0, 2).reshape(size * n, free)

    def prediction_error(self, window: TransitionWindow, parameters: Mapping[str, float] | None = None) -> float:
        """The window's mean squared one-step prediction error at ``parameters`` (default: the estimate)."""
        p = self._p if parameters is None else np.array([float({**self.parameters, **parameters}[k])
                                                          for k in self.names])
        r, _ = self._evaluate(window, p, jacobian=False)
        return float(np.mean(r * r)) if np.all(np.isfinite(r)) else math.inf

    def update(self, window: TransitionWindow) -> Update:
        """One damped Gauss–Newton step on ``window``, kept only if it lowers the prediction error."""
        if len(window) == 0:
            raise ValueError("the window holds no transitions")
        r, jac = self._evaluate(window, self._p, jacobian=True)
        before = float(np.mean(r * r))
        # How far a relevant change of each free parameter moves the window's predictions (rad/s, RMS).
        effect = np.linalg.norm(jac, axis=0) / math.sqrt(len(window)) * self._relevant[self._free_index]
        excited = effect >= self.min_effect
        if not np.any(excited):
            return Update(accepted=False, parameters=self.parameters, error_before=before, error_after=before,
                          candidate_error=before, damping=self.damping, fitted=())
        jac = jac[:, excited]
        normal = jac.T @ jac
        # Marquardt's scaling (λ·diag) makes the step independent of the parameters' units; the tiny
        # absolute term keeps it solvable.
        regular = normal + self.damping * np.diag(np.diag(normal)) + 1e-12 * np.eye(int(excited.sum()))
        step = -np.linalg.solve(regular, jac.T @ r)
        candidate = self._p.copy()
        candidate[self._free_index[excited]] += step
        candidate = np.clip(candidate, self._lower, self._upper)
        update = self.consider(window, candidate, before)
        return replace(update, fitted=tuple(name for name, on in zip(self.free, excited) if on))

    def consider(self, window: TransitionWindow, candidate: Mapping[str, float] | np.ndarray,
                 error_before: float | None = None) -> Update:
        """Keep ``candidate`` (a ``{name: value}`` or a full vector) if it is within the bounds and lowers the
        window's prediction error; otherwise keep the estimate and raise the damping."""
        if isinstance(candidate, Mapping):
            candidate = np.array([float({**self.parameters, **candidate}[k]) for k in self.names])
        candidate = np.asarray(candidate, dtype=float)
        before = self.prediction_error(window) if error_before is None else error_before
        within = bool(np.all(candidate >= self._lower - 1e-12) and np.all(candidate <= self._upper + 1e-12))
        r, _ = self._evaluate(window, candidate, jacobian=False)
        after = float(np.mean(r * r)) if np.all(np.isfinite(r)) else math.inf
        accepted = within and after < before
        if accepted:
            self._p = candidate
            self.damping = max(self.damping / 3.0, 1e-9)
        else:
            self.damping = min(self.damping * 4.0, 1e9)
        return Update(accepted=accepted, parameters=self.parameters, error_before=before,
                      error_after=after if accepted else before, candidate_error=after, damping=self.damping,
                      fitted=self.free)


#: The blocks of a model's run-time parameters that carry its dissipation (closed form: ``D = 2·damping·I``;
#: learned: ``D = L Lᵀ`` from the Cholesky factor): the only way an estimated ``damping`` reaches the MPC.
DISSIPATION_BLOCKS = ("damping", "dissipation_cholesky")


def dissipation_block(model: ExportedModel) -> str | None:
    """The block of ``model``'s run-time parameters that carries its dissipation, ``None`` if it has none (a
    model without damping keeps none: a term switched off stays off)."""
    names = {block.name for block in model.model_parameters.blocks}
    return next((name for name in DISSIPATION_BLOCKS if name in names), None)


def rti_parameters(model: ExportedModel, estimate: Mapping[str, float]) -> np.ndarray:
    """The run-time parameter vector of ``model`` (:mod:`fvin_mpc.core.model_parameters`) that steps exactly
    like the estimator's ``estimate`` (``mass``, ``gain<i>``, ``damping``): ``gain_scale_i = gain_i / mass``,
    the dissipation ``(D + 2·damping·I) / mass`` (module docstring, "In the loop"); every other block at the
    model's own value. ``ValueError`` for a non-zero ``damping`` on a model with no dissipation block. A free
    body's estimate (``mass``, ``inertia``, ``gain<i>``) maps block by block (:func:`free_body_vector`)."""
    if not _pivot_estimator(model):
        names = free_body_parameter_names(model)
        return model.model_parameters.check(free_body_vector(model, [float(estimate[name]) for name in names]))
    parameters = model.model_parameters
    mass = float(estimate["mass"])
    gains = np.array([float(estimate[f"gain{i}"]) for i in range(model.control_dim)])
    vector = parameters.values(**{GAIN_SCALE: gains / mass})
    added = float(estimate.get("damping", 0.0))
    block = dissipation_block(model)
    if block is None:
        if added != 0.0:
            raise ValueError(f"model {model.name!r} has no dissipation among its run-time parameters; an "
                             f"estimated damping ({added:g}) cannot reach the controller: fit free=('mass',)")
        return vector
    where = parameters.slice(block)
    own = vector[where]
    if block == "damping":  # the closed form's D = 2·damping·I
        vector[where] = (own + added) / mass
        return vector
    dissipation = np.array(s3.symmetric_from_cholesky(tuple(own)), dtype=float)
    lower = np.linalg.cholesky((dissipation + 2.0 * added * np.eye(3)) / mass)
    vector[where] = [lower[0, 0], lower[1, 1], lower[2, 2], lower[1, 0], lower[2, 0], lower[2, 1]]
    return vector


class AdaptiveRTI:
    """A real-time MPC (:class:`~fvin_mpc.control.rti.RealTimeMPC` or its C twin) that re-fits its model's
    mass (and damping, where the model carries one) while it runs (module docstring, "In the loop").

    The closed loop sees the wrapped controller: ``u, info = adaptive(x)``, then ``adaptive.prepare()``
    after the control is sent — the window, one estimator update and ``set_parameters`` happen there,
    before the controller's own preparation, in the period's spare time, not in the latency of a control.
    ``set_time`` (which :func:`~fvin_mpc.control.closed_loop.run_episode` calls) tells it which
    observations are one period apart: a transition across a skipped period (a deadline miss) is not one
    step of the model and is left out. It is told nothing about when or what changes. The input-disturbance
    estimate of the wrapped controller runs as before, on the adapted model.

    The control a transition records is the one the plant received over the period, when the loop tells it
    (``observe_applied``, which :func:`~fvin_mpc.control.closed_loop.run_episode` calls: with a latency the
    previous control acts for the period's first sub-steps); else the one commanded.

    Args:
        controller: a real-time MPC built with run-time model parameters (``rti.model_parameters``, the
            default).
        window: the sliding window's length (transitions).
        free: the estimator's free parameters; default on a pivoted body ``("mass", "damping")`` where the
            model carries a dissipation block, else ``("mass",)``; on a free body ``("mass",)``.
        min_effect: the estimator's excitation gate (:class:`ParameterEstimator`; ``None``: its default).
    """

    def __init__(self, controller: Any, window: int = 40, free: Sequence[str] | None = None,
                 min_effect: float | None = None) -> None:
        model = controller.model
        if free is None and _pivot_estimator(model):
            free = ("mass", "damping") if dissipation_block(model) is not None else ("mass",)
        if _pivot_estimator(model) and "damping" in free and dissipation_block(model) is None:
            raise ValueError(f"model {model.name!r} has no dissipation among its run-time parameters; an "
                             f"estimated damping could not reach the controller: leave 'damping' out of free")
        self.controller = controller
        self.model = model
        # The estimator's residual is compiled where the controller's functions are (``settings.compile``).
        settings = getattr(controller, "settings", None)
        compiled = window if getattr(settings, "compile", "none") != "none" else None
        self.estimator = ParameterEstimator(model, free=free, min_effect=min_effect, compiled_window=compiled)
        self.window = TransitionWindow(window)
        controller.set_parameters(rti_parameters(model, self.estimator.parameters))
        self._previous: tuple[np.ndarray, np.ndarray, float | None] | None = None
        self._observed: tuple[np.ndarray, float | None] | None = None
        self._sent = np.zeros(model.control_dim)
        self._applied: np.ndarray | None = None
        self._time: float | None = None
        #: per adapting period: ``(time s, estimate, update s, Update or None)``
        self.history: list[tuple[float | None, dict[str, float], float, Update | None]] = []

    def reset(self) -> None:
        """A new episode: the controller reset, the window emptied, the estimate and the controller's
        parameters back to the initial ones."""
        self.controller.reset()
        self.window = TransitionWindow(self.window.capacity)
        self.estimator.reset()
        self.controller.set_parameters(rti_parameters(self.model, self.estimator.parameters))
        self._previous = self._observed = self._time = self._applied = None
        self.history = []

    def set_time(self, time_s: float) -> None:
        self._time = float(time_s)
        forward = getattr(self.controller, "set_time", None)
        if forward is not None:
            forward(time_s)

    def __call__(self, x: Any) -> tuple[np.ndarray, dict[str, Any]]:
        x = np.asarray(x, dtype=float)
        u, info = self.controller(x)
        self._observed = (x.copy(), self._time)
        self._sent = np.atleast_1d(np.asarray(u, dtype=float)).copy()
        return u, info

    def observe_applied(self, u: Any) -> None:
        """The control the plant received over the period that just ended (the closed loop's report)."""
        self._applied = np.atleast_1d(np.asarray(u, dtype=float)).copy()

    @property
    def parameters(self) -> dict[str, float]:
        """The current estimate (:attr:`ParameterEstimator.parameters`)."""
        return self.estimator.parameters

    def prepare(self) -> None:
        """After the control is sent: the transition that just ended into the window, at most one estimator
        update, the estimate to the controller, then the controller's own preparation."""
        if self._observed is not None:
            x, time_s = self._observed
            start = time.perf_counter()
            update = None
            if self._previous is not None and self._one_period_apart(self._previous[2], time_s):
                received = self._previous[1] if self._applied is None else self._applied
                self.window.add(self._previous[0], received, x)
                update = self.estimator.update(self.window)
                if update.accepted:
                    self.controller.set_parameters(rti_parameters(self.model, update.parameters))
            self.history.append((time_s, self.estimator.parameters, time.perf_counter() - start, update))
            self._previous = (x, self._sent, time_s)
            self._observed = self._applied = None
        prepare = getattr(self.controller, "prepare", None)
        if prepare is not None:
            prepare()

    def _one_period_apart(self, before: float | None, after: float | None) -> bool:
        if before is None or after is None:  # no clock told: consecutive calls are consecutive periods
            return True
        return abs(after - before - self.model.step_size) < 0.25 * self.model.step_size

    def __getattr__(self, name: str) -> Any:
        # Whatever else the closed loop or a report reads (settings, disturbance, compile_report…) is the
        # wrapped controller's.
        if name == "controller":
            raise AttributeError(name)
        return getattr(self.controller, name)
