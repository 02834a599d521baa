"""The step's own equations as the real-time iteration's dynamics constraint, with shared node terms.

The default real-time iteration (:mod:`fvin_mpc.control.rti`, ``rti.dynamics="unrolled"``)
linearizes the exported step ``x_{k+1} = F(x_k, u_k)`` — K Newton iterations unrolled — at every
stage. Its Jacobian differentiates the learned terms ``J``, ``∇U``, ``g`` twice per stage (at
``q_k`` and at the step's end ``q_{k+1} = F(x_k)``) in all 7 directions of ``(δ_k, Δu_k)``, and
a sign-invariant model evaluates each network twice more (``±q``): that is most of a learned
model's period (``python -m benchmarks ops``).

``rti.dynamics="implicit"`` imposes instead the step's equations between consecutive plan nodes,
:func:`fvin_mpc.core.fvin.step_residual` ``G(x_k, u_k, x_{k+1}) = 0`` (the discrete
Euler–Lagrange equations as constraints, as in discrete mechanics and optimal control; Ober-Blöbaum,
Junge & Marsden 2011). Both ends of a stage are plan nodes, so the terms are needed at the nodes
only: :func:`node_terms_function` evaluates ``J``, ``∇U``, ``g`` (and ``D``) once per node with
their derivatives in the node's 3 chart directions, and each stage reads the two nodes' values
through their first-order expansions. The linearized constraint
``G + G_x δ_k + G_u Δu_k + G_y δ_{k+1} = 0`` gives the QP's stage form
``δ_{k+1} = A_k δ_k + B_k Δu_k + c_k`` with ``[A_k B_k] = −G_y⁻¹ [G_x G_u]`` and ``c_k = −G_y⁻¹ G``
(``G_y`` is block-triangular and regular wherever the step is solvable: ``∂Φ/∂ξ`` and
``2J + (h/2)D``).

What changes for the controller: the plan satisfies the converged step (K → ∞) instead of the
K-unrolled one — the two differ by the Newton error (DESIGN.md: 5e-4 rad/s per step at K = 2,
|ω| ≤ 8) — and ``c_k`` is one Newton step on ``G`` from ``x̄_{k+1}`` instead of the exact gap
``F(x̄_k, ū_k) − x̄_{k+1}``: both vanish together, and the iterations close the gaps as they close
the Newton residual. Predictions (the shifted plan's last node, the disturbance estimate) still
use the exported step. Pivoted bodies (``x = (q, ω)``) only. A model whose terms are not
sign-invariant reads them at each node's own sign; the controller keeps the plan's nodes on one
sheet of S³ (:meth:`fvin_mpc.control.rti.RealTimeMPC._linearize_at`).

Where it does not pay (measured, docs/realtime.md): its region of convergence is smaller. ``c_k`` is
linear in the gap only near consistent nodes; from plans whose nodes disagree with the step by a
rotation of a few tenths of a radian it overshoots, most along a small principal inertia. On the
ball joint (``J_z = 0.017`` against 0.5) the cold plans are that far off and the iterations
diverged; that scene keeps the unrolled step. The planar pendulum converges with it from every
start measured.
"""

from __future__ import annotations

from typing import Any

import casadi as ca

from fvin_mpc.control.model_export import GENERATED_SX_OPTIONS
from fvin_mpc.core import fvin, s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.space import PIVOTED

#: The one attitude block of a pivoted state (the implicit dynamics are the S³ step's equations on ``(q, ω)``).
ATTITUDE = PIVOTED.slots[0].block

CA = get_ops("casadi")


class _ExpandedTerms:
    """:class:`~fvin_mpc.core.fvin.RigidBodyTerms` near one node: each term's value at the node plus
    its derivative times the node's chart step ``δ`` — exact in value and first derivative at
    ``δ = 0``, which is all a linearization there reads. A constant ``J`` comes from ``terms``."""

    def __init__(self, terms: Any, layout: TermLayout, values: Any, derivatives: Any, delta: Any) -> None:
        self._terms, self._layout = terms, layout
        self._entries = values + ca.mtimes(derivatives, delta)
        self.control_dim = terms.control_dim
        self.constant_inertia = terms.constant_inertia
        self.hinge_axis = fvin.hinge_axis_of(terms)

    def _matrix(self, start: int) -> s3.Mat3:
        e = self._entries
        return tuple(tuple(e[start + 3 * i + j] for j in range(3)) for i in range(3))  # type: ignore[return-value]

    def inertia(self, q: s3.Quat) -> s3.Mat3:
        return self._terms.inertia(q) if self.constant_inertia else self._matrix(self._layout.inertia)

    def potential(self, q: s3.Quat) -> Any:
        raise NotImplementedError("the implicit dynamics need ∇U only")

    def potential_gradient(self, q: s3.Quat) -> s3.Quat:
        start = self._layout.potential_gradient
        return tuple(self._entries[start + i] for i in range(4))  # type: ignore[return-value]

    def control_gain(self, q: s3.Quat) -> tuple[tuple[Any, ...], ...]:
        start, m = self._layout.control_gain, self.control_dim
        return tuple(tuple(self._entries[start + m * i + j] for j in range(m)) for i in range(3))

    def dissipation(self, q: s3.Quat) -> s3.Mat3 | None:
        return None if self._layout.dissipation is None else self._matrix(self._layout.dissipation)


class TermLayout:
    """Where each term sits in a node's flat vector: ``J`` (9, absent when constant), ``∇U`` (4),
    ``g`` (3·m, rows), ``D`` (9, absent when the model has none)."""

    def __init__(self, terms: Any, q: s3.Quat) -> None:
        size = 0
        self.inertia = None if terms.constant_inertia else size
        size += 0 if terms.constant_inertia else 9
        self.potential_gradient, size = size, size + 4
        self.control_gain, size = size, size + 3 * terms.control_dim
        self.has_dissipation = terms.dissipation(q) is not None
        self.dissipation = size if self.has_dissipation else None
        self.size = size + (9 if self.has_dissipation else 0)

    def flatten(self, terms: Any, q: s3.Quat) -> Any:
        parts: list[Any] = []
        if self.inertia is not None:
            parts += [entry for row in terms.inertia(q) for entry in row]
        parts += list(terms.potential_gradient(q))
        parts += [entry for row in terms.control_gain(q) for entry in row]
        if self.has_dissipation:
            parts += [entry for row in terms.dissipation(q) for entry in row]
        return ca.vertcat(*parts)


def node_terms_function(terms: Any, parameters: Any = None,
                        derivatives: bool = True) -> tuple[ca.Function, TermLayout]:
    """``node(q̄[4]) -> (T[s], ∂T/∂δ[s×3])``: the terms at ``q̄`` and their derivatives along the chart
    ``q = retract(q̄, δ)`` (:data:`~fvin_mpc.core.space.PIVOTED`'s chart) at ``δ = 0``; ``terms`` on the CasADi
    backend. With ``parameters`` (an
    :class:`~fvin_mpc.control.model_export.ExportedModel`) the terms are its :meth:`terms_at` the model
    parameters, an input: ``node(q̄, p)``. ``derivatives=False``: ``T`` alone, the same expression (the same
    to the bit)."""
    q_bar, delta = ca.SX.sym("q_bar", 4), ca.SX.sym("delta", 3)
    inputs, names = [q_bar], ["q_bar"]
    if parameters is not None:
        p = ca.SX.sym("p", parameters.model_parameters.size)
        terms = parameters.terms_at(p)
        inputs, names = [q_bar, p], ["q_bar", "p"]
    q_components = ATTITUDE.retract(ca.vertsplit(q_bar), ca.vertsplit(delta), CA)
    layout = TermLayout(terms, q_components)
    flat = layout.flatten(terms, q_components)
    outputs = ca.substitute([flat, ca.jacobian(flat, delta)] if derivatives else [flat], [delta], [ca.DM.zeros(3)])
    node_terms = ca.Function("rti_node_terms" if derivatives else "rti_node_values", inputs, outputs, names,
                             ["T", "dT"][:len(outputs)], GENERATED_SX_OPTIONS)
    return node_terms, layout


def implicit_stage_function(terms: Any, layout: TermLayout, step_size: float,
                            parameters: Any = None) -> ca.Function:
    """``stage(x̄_k, ū_k, x̄_{k+1}, d, T_k, dT_k, T_{k+1}, dT_{k+1}) -> (c[6], [A B][6×(6+m)])`` in the
    chart of :data:`~fvin_mpc.core.space.PIVOTED` (``q = retract(q̄, θ)``, ``ω = ω̄ + ν``); module docstring. With
    ``parameters`` (as :func:`node_terms_function`) a last input ``p``: the gain scale multiplies the
    controls and a constant inertia is the parametrized one."""
    m = terms.control_dim
    extra_inputs, extra_names = [], []
    if parameters is not None:
        p = ca.SX.sym("p", parameters.model_parameters.size)
        terms = parameters.terms_at(p)
        extra_inputs, extra_names = [p], ["p"]
    x_bar, x_next_bar = ca.SX.sym("x_bar", PIVOTED.state_dim), ca.SX.sym("x_next_bar", PIVOTED.state_dim)
    u_bar, d = ca.SX.sym("u_bar", m), ca.SX.sym("d", m)
    values, values_next = ca.SX.sym("T", layout.size), ca.SX.sym("T_next", layout.size)
    slopes, slopes_next = ca.SX.sym("dT", layout.size, 3), ca.SX.sym("dT_next", layout.size, 3)
    theta, nu, du = ca.SX.sym("theta", 3), ca.SX.sym("nu", 3), ca.SX.sym("du", m)
    theta_next, nu_next = ca.SX.sym("theta_next", 3), ca.SX.sym("nu_next", 3)

    def node(state: Any, chart: Any, velocity: Any) -> tuple[s3.Quat, s3.Vec3]:
        x = PIVOTED.retract(state, ca.vertcat(chart, velocity), CA)
        return tuple(x[i] for i in range(4)), tuple(x[4 + i] for i in range(3))  # type: ignore[return-value]

    q, omega = node(x_bar, theta, nu)
    q_next, omega_next = node(x_next_bar, theta_next, nu_next)
    actuated = u_bar + du + d
    if parameters is not None:
        actuated = parameters.model_parameters.actuated(actuated, p)
    u = tuple(actuated[i] for i in range(m))
    here = _ExpandedTerms(terms, layout, values, slopes, theta)
    there = _ExpandedTerms(terms, layout, values_next, slopes_next, theta_next)
    residual = ca.vertcat(*fvin.step_residual(q, omega, u, q_next, omega_next, here, step_size, CA, terms_next=there))
    start, end = ca.vertcat(theta, nu, du), ca.vertcat(theta_next, nu_next)
    zero = [ca.DM.zeros(3), ca.DM.zeros(3), ca.DM.zeros(m), ca.DM.zeros(3), ca.DM.zeros(3)]
    g, g_start, g_end = ca.substitute([residual, ca.jacobian(residual, start), ca.jacobian(residual, end)],
                                      [theta, nu, du, theta_next, nu_next], zero)
    # G_y = [[∂Φ/∂θ', 0], [∗, −(2J + (h/2)D)]]: two 3×3 solves, not a 6×6 one.
    kinematic, dynamic = g_end[:3, :3], g_end[3:, 3:]
    rhs = -ca.horzcat(g, g_start)
    top = ca.solve(kinematic, rhs[:3, :])
    bottom = ca.solve(dynamic, rhs[3:, :] - ca.mtimes(g_end[3:, :3], top))
    solution = ca.vertcat(top, bottom)
    return ca.Function("rti_implicit_dynamics",
                       [x_bar, u_bar, x_next_bar, d, values, slopes, values_next, slopes_next, *extra_inputs],
                       [solution[:, 0], solution[:, 1:]],
                       ["x_bar", "u_bar", "x_next_bar", "d", "T", "dT", "T_next", "dT_next", *extra_names], ["c", "AB"],
                       GENERATED_SX_OPTIONS)
