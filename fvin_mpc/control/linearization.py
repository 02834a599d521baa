"""The real-time iteration's linearization, as generated CasADi functions (:mod:`fvin_mpc.control.rti` drives them).

* **A stage** of the unrolled dynamics (:func:`unrolled_stage_function`): the gap ``c`` between the model's step
  from the node ``x̄_k`` and the next node ``x̄_{k+1}``, in ``x̄_{k+1}``'s chart, and ``[A B]``, its derivatives in
  the local coordinates ``(δ_k, Δu_k)`` — the blocks' chart (:class:`~fvin_mpc.core.blocks.StateLayout`), so any
  product of blocks linearizes the same way.
* **The trust region** of one iteration, one number per entry of ``δ`` by its unit (:func:`step_limits`), and the
  clip of planned angular rates inside the step's solvability limit (:func:`clip_rows`).
* **Kept Jacobians** (``RTIOptions.relinearize_every``): which items a linearization renews
  (:func:`relinearized`, :func:`shifted_items`), a stage or node that computes its derivatives only where told
  (:func:`kept_jacobian_switch`, :func:`renewing_item_function`), and how far an item moved from the point its
  kept Jacobians were computed at (:func:`stage_distance_function`, :func:`node_distance_function`).
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from fvin_mpc.control.model_export import GENERATED_SX_OPTIONS, ExportedModel
from fvin_mpc.control.term_expansion import FirstOrderTerms
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.space import StateLayout, chart_local

CA = get_ops("casadi")

#: Trust region of one iteration, per stage: largest ``|θ_i|`` (Gibbs vector, ≈ half the turn in rad) …
STEP_LIMIT_ANGLE = 0.5
#: … largest ``|Δω_i|`` as a fraction of the ``ω`` bound; larger state steps are clipped …
STEP_LIMIT_OMEGA = 0.5
#: … and, for a free body, largest ``|Δx_i|`` (m) …
STEP_LIMIT_POSITION = 1.0
#: … and ``|Δv_i|`` (m/s).
STEP_LIMIT_VELOCITY = 2.0


# ----------------------------------------------------------------------------- the trust region
def step_limits(layout: StateLayout, omega_step: float) -> np.ndarray:
    """The trust region of one iteration per entry of ``δ``, by unit (:meth:`StateLayout.tangent_limits`):
    :data:`STEP_LIMIT_POSITION`, :data:`STEP_LIMIT_ANGLE`, :data:`STEP_LIMIT_VELOCITY`, ``omega_step`` for
    angular rates."""
    return layout.tangent_limits(STEP_LIMIT_POSITION, STEP_LIMIT_ANGLE, STEP_LIMIT_VELOCITY, omega_step)


def clip_rows(matrix: Any, rows: slice | list[int], bound: float) -> Any:
    """``matrix`` (CasADi, a state per column) with ``rows`` clipped to ``±bound``."""
    clipped = ca.fmin(ca.fmax(matrix, -bound), bound)
    chosen = np.zeros(matrix.shape[0], dtype=bool)
    chosen[rows] = True
    if isinstance(rows, slice) and rows.stop == matrix.shape[0]:  # rates last: two blocks
        return ca.vertcat(matrix[:rows.start, :], clipped[rows.start:, :])
    return ca.vertcat(*[clipped[i, :] if chosen[i] else matrix[i, :] for i in range(matrix.shape[0])])


# ----------------------------------------------------------------------------- compiled QP + update
def unrolled_stage_function(step: ca.Function, layout: StateLayout, m: int, jacobian: bool = True,
                            model: ExportedModel | None = None) -> ca.Function:
    """``stage(x̄_k, ū_k, x̄_{k+1}, d) -> (c, [A B])`` of the unrolled dynamics: ``c`` the gap between
    ``F(x̄_k, ū_k + d)`` and ``x̄_{k+1}`` in ``x̄_{k+1}``'s chart, ``[A B]`` its derivatives in ``(δ_k, Δu_k)``.
    A ``step`` with a third input (the model parameters ``p``,
    :attr:`~fvin_mpc.control.model_export.ExportedModel.parametric_step`) gives ``stage(…, d, p)``.
    ``jacobian=False``: ``c`` alone, the same expression (the same to the bit). ``model``: the model ``step``
    was made from; where it has rigid-body terms, ``[A B]`` is taken of the same step on their first-order
    expansions (:mod:`fvin_mpc.control.term_expansion`: the same derivatives, fewer operations).

    The derivatives are taken in reverse mode (one sweep per entry of ``c``: ``n_δ`` sweeps against ``n_δ + m``
    directions; the instruction counts against CasADi's forward choice, by scene: docs/c-controller.md, "Fewer
    operations, again"). What the expansions save: :mod:`fvin_mpc.control.term_expansion`."""
    x_bar, x_next_bar = ca.SX.sym("x_bar", layout.state_dim), ca.SX.sym("x_next_bar", layout.state_dim)
    u_bar, d = ca.SX.sym("u_bar", m), ca.SX.sym("d", m)
    delta, du = ca.SX.sym("delta", layout.tangent_dim), ca.SX.sym("du", m)
    parameters = [ca.SX.sym("p", step.size1_in(2))] if step.n_in() == 3 else []
    x, u = layout.retract(x_bar, delta, CA), u_bar + du + d
    gap = layout.local(x_next_bar, step(x, u, *parameters)[0], CA)
    outputs = [gap]
    if jacobian:
        differentiated = gap
        if model is not None and model.casadi_terms is not None:
            x_next, _ = model.step_on_terms(x, u, *parameters, wrap=lambda terms: FirstOrderTerms(terms, [delta, du]))
            differentiated = layout.local(x_next_bar, x_next, CA)
        outputs.append(ca.jacobian(differentiated, ca.vertcat(delta, du), {"helper_options": {"ad_weight": 1.0}}))
    outputs = ca.substitute(outputs, [delta, du], [ca.DM.zeros(layout.tangent_dim), ca.DM.zeros(m)])
    return ca.Function("rti_dynamics" if jacobian else "rti_dynamics_value", [x_bar, u_bar, x_next_bar, d, *parameters],
                       outputs, ["x_bar", "u_bar", "x_next_bar", "d", "p"][:4 + len(parameters)],
                       ["c", "AB"][:len(outputs)], GENERATED_SX_OPTIONS)


def kept_jacobian_switch(name: str, full: ca.Function, value: ca.Function) -> ca.Function:
    """``name(fresh, *inputs, J) → (*values, J)``: where ``fresh`` is non-zero ``full(*inputs) → (*values, J)``
    (``J`` the derivatives, its last output), else ``value(*inputs) → (*values)`` with the given ``J`` passed
    through — one stage (or node) of a linearization that keeps the Jacobians of the previous one
    (:attr:`~fvin_mpc.control.mpc.RTIOptions.relinearize_every`). Only the branch taken runs."""
    inputs = full.sx_in()
    kept = ca.SX.sym("J", full.sparsity_out(full.n_out() - 1))
    names = [*full.name_in(), "J"]
    computed = ca.Function(f"{name}_fresh", [*inputs, kept], full.call(inputs), names, full.name_out(),
                           GENERATED_SX_OPTIONS)
    passed = ca.Function(f"{name}_kept", [*inputs, kept], [*value.call(inputs), kept], names, full.name_out(),
                         GENERATED_SX_OPTIONS)
    return ca.Function.conditional(name, [passed], computed)


def renewing_item_function(name: str, switch: ca.Function, distance: ca.Function, tolerance: float) -> ca.Function:
    """``name(rule, *inputs, J, point) → (*values, J, point)``: :func:`kept_jacobian_switch`'s ``switch``, renewing
    the item where ``rule`` is non-zero or where it moved: ``distance(*inputs, point) → (far, here)`` is how far
    the item is from the ``point`` its kept Jacobians were computed at, in trust-region units, and where it is
    now; it reads the item's first inputs (as many as it has before ``point``). Renewed, the item returns ``here``
    as its point; kept, the given one."""
    count, reads = switch.n_in() - 2, distance.n_in() - 1
    rule = ca.MX.sym("rule")
    inputs = [ca.MX.sym(switch.name_in(i + 1), switch.sparsity_in(i + 1)) for i in range(count)]
    kept, point = ca.MX.sym("J", switch.sparsity_in(count + 1)), ca.MX.sym("point", distance.sparsity_in(reads))
    far, here = distance(*inputs[:reads], point)
    renew = ca.logic_or(rule, far > tolerance)
    return ca.Function(name, [rule, *inputs, kept, point],
                       [*switch(renew, *inputs, kept), ca.if_else(renew, here, point)])


def stage_distance_function(layout: StateLayout, m: int, limits: np.ndarray, control_range: np.ndarray
                            ) -> ca.Function:
    """``distance(x̄, ū, point) → (far, here)`` of a stage (:func:`renewing_item_function`): its node ``x̄`` in the
    chart of the kept point's state over the trust region (``limits``: :func:`step_limits`), or its control's
    change over ``control_range``, whichever is larger; ``here = (x̄, ū)``."""
    ns = layout.state_dim
    x_bar, u_bar, point = ca.SX.sym("x_bar", ns), ca.SX.sym("u_bar", m), ca.SX.sym("point", ns + m)
    state_far = ca.mmax(ca.fabs(layout.local(point[:ns], x_bar, CA)) / ca.DM(limits))
    control_far = ca.mmax(ca.fabs(u_bar - point[ns:]) / ca.DM(control_range))
    return ca.Function("rti_stage_distance", [x_bar, u_bar, point],
                       [ca.fmax(state_far, control_far), ca.vertcat(x_bar, u_bar)], GENERATED_SX_OPTIONS)


def node_distance_function() -> ca.Function:
    """``distance(q̄, point) → (far, here)`` of a node of the implicit dynamics, whose terms depend on its rotation
    alone: the rotation from the kept point's in its chart over :data:`STEP_LIMIT_ANGLE`; ``here = q̄``."""
    q_bar, point = ca.SX.sym("q_bar", 4), ca.SX.sym("point", 4)
    return ca.Function("rti_node_distance", [q_bar, point],
                       [ca.mmax(ca.fabs(ca.vertcat(*chart_local(ca.vertsplit(point), ca.vertsplit(q_bar)))))
                        / STEP_LIMIT_ANGLE, q_bar], GENERATED_SX_OPTIONS)


def relinearized(items: int, every: int, head: int) -> np.ndarray:
    """Which of a linearization's ``items`` (stages, or nodes of the implicit dynamics) get new Jacobians when
    the previous linearization's are at hand (``1.0``; ``0.0`` keeps the previous one's): the first ``head``,
    every ``every``-th and the last. The plan shifts one item a period, so each kept Jacobian is renewed
    when its node passes a multiple of ``every``: none is older than ``every − 1`` periods, and each
    linearization renews the same number. ``every = 1``: all."""
    index = np.arange(items)
    return ((index < head) | (index % every == 0) | (index == items - 1)).astype(float)


def shifted_items(jacobians: np.ndarray, items: int) -> np.ndarray:
    """A linearization's Jacobians (``items`` equal column blocks) moved one item earlier, as the plan moves
    at the shift; the last block repeated (:func:`relinearized` always renews it)."""
    width = jacobians.shape[1] // items
    return np.concatenate([jacobians[:, width:], jacobians[:, -width:]], axis=1)
