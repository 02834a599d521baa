"""Real-time iteration MPC: one Gauss–Newton SQP step per control period, bounded compute — the controller.
Its linearization is :mod:`fvin_mpc.control.linearization`, its QP solver :mod:`fvin_mpc.control.riccati_qp`.

``controller = RealTimeMPC(model, settings, goal, torque_low, torque_high, rest)`` — or
:func:`fvin_mpc.control.scene.scene_mpc` with ``MPCSettings(solver="rti")`` — then
``u, info = controller(x)`` once per period and, after the torque is sent, ``controller.prepare()``
(:func:`fvin_mpc.control.closed_loop.run_episode` does both; a call finds the preparation done or
does it itself). The problem of :class:`fvin_mpc.control.mpc.MPC` (same model, cost weights,
torque bounds, terminal energy term), with two differences: the ``ω`` bound is a stiff penalty, and
the control cost is measured from the torque that holds the goal in the model (``u_s`` below; 0 for
an unbiased model). Solved differently (Diehl's real-time iteration, as in acados' SQP-RTI):

* **local coordinates** — each stage's state is a linearization point ``x̄_k`` plus local coordinates ``δ_k``
  in the blocks' chart (:class:`~fvin_mpc.core.blocks.StateLayout`): for a pivoted body ``x̄_k = (q̄_k, ω̄_k)``
  and ``δ_k = (θ_k, ν_k)``, ``q = q̄ ⊗ (1, θ)/√(1 + |θ|²)``, ``ω = ω̄ + ν`` (the Gibbs/Cayley retraction: to
  first order ``q̄ ⊗ exp(θ)``, rational, and its inverse ``θ = Im(p)/Re(p)`` of ``p = q̄* ⊗ q`` is the same
  for ``q`` and ``−q``). Iterates stay on S³ exactly; no norm constraint, no 7th direction.
* **QP per iteration** — the dynamics linearized per stage,
  ``δ_{k+1} = A_k δ_k + B_k Δu_k + c_k`` (``c_k`` the gap between ``F(x̄_k, ū_k + d)`` and
  ``x̄_{k+1}``, measured in ``x̄_{k+1}``'s chart; with ``rti.dynamics="implicit"`` the step's own
  equations between the nodes give ``A_k, B_k, c_k`` instead, the learned terms evaluated once per
  node: :mod:`fvin_mpc.control.implicit_dynamics`); the cost's Gauss–Newton model (every term of the
  MPC's cost is a sum of squares: ``c(q) = |q|² − ⟨q, g⟩² = |(I − ggᵀ)q|²``, the energy deficit,
  ``ω``, ``u − u_s``), so the Hessian needs first derivatives only; bounds on ``u`` as
  boxes, the bound on ``ω`` as a stiff penalty on its excess (``rti.omega_penalty``: a hard bound
  made the linearized QP infeasible from the spinning first guesses of the ball joint). ``δ_0`` is fixed
  to the measured state in ``x̄_0``'s chart. The QP is stage-wise sparse. By default
  (``rti.qp_solver="riccati"``) it is solved by a fixed number of primal–dual interior-point
  iterations on the input boxes, each a Riccati recursion (``O(N)``), generated together with the
  trust region and the update of the plan as one CasADi function
  (:func:`~fvin_mpc.control.riccati_qp.riccati_feedback_function`) and
  compiled with the linearization (:func:`fvin_mpc.control.model_export.compile_functions`): one C call
  per iteration, no Python between stages. The compiled functions are called through preallocated
  NumPy buffers (:class:`fvin_mpc.control.buffered.BufferedFunction`): CasADi's own call converts
  every argument and result, which cost more than the arithmetic here (docs/realtime.md).
  ``"hpipm"`` sends the same QP to HPIPM through ``casadi.conic`` (about 1 ms of interface
  overhead per call here, docs/realtime.md).
  ``A_k, B_k, c_k``, Hessian blocks and gradients come from one compiled function, which evaluates its
  stages four at a time on the vector units where it can (``rti.stage_lanes``,
  :mod:`fvin_mpc.control.lane_kernel`).
* **preparation / feedback** — after a torque is sent, :meth:`prepare` shifts the plan by one
  step (the last stage predicted by the model) and linearizes it; the next call only fixes
  ``δ_0`` and solves the QP (feedback), then iterates again only while ``rti.budget_s`` allows.
  With ``rti.feedback="prepared"`` the preparation also solves the QP at the predicted first state and
  keeps its Riccati gains; the call applies them to the measured ``δ_0`` (a forward pass).
* **model parameters** — the compiled functions take the model's run-time parameters as an input
  (:mod:`fvin_mpc.core.model_parameters`: gain scales, physical values); :meth:`RealTimeMPC.set_parameters`
  changes them without recompiling (``rti.model_parameters=False`` bakes them in).
* **trust region** — each stage's state step is clipped (:data:`STEP_LIMIT_ANGLE`,
  :data:`STEP_LIMIT_OMEGA`) and planned ``|ω|`` kept inside the step's solvability limit: a full
  Gauss–Newton step from a guess with large gaps otherwise leaps to where the model means nothing.
* **cold start** — after :meth:`reset`, ``cold_starts``' first guesses in :data:`RTI_COLD_ORDER`
  (``"goal"`` first: an orientation path to the goal, or the model rolled out under ``±f·u_max``;
  neither is the symmetric rest, so the first torque is non-zero), each improved by up to
  ``rti.cold_iter`` iterations while ``rti.cold_budget_s`` lasts; the best is kept. Guesses reached
  after the budget is spent are still scored, un-iterated (a rollout is a plan of the model with no
  gaps), so the clock never hands the call a half-iterated guess unchallenged. The budget is
  what bounds the first call (it is below the 50 ms period by default); the plan keeps improving by
  one iteration per period afterwards.
* **restart** — a warm call whose measured ``ω`` differs from the prepared plan's first state (the
  model's prediction of now) by more than ``rti.restart_speed`` in some component drops the plan and
  starts cold (``info["restarted"]``). A knock leaves the plan describing a body that is no longer
  there; warm-started from it after the fall, the learned damped pendulum's MPC stayed at the bottom
  in half the knocked episodes. The scenes' defaults set ``0.13·ω_s``; ``inf`` never restarts.
* **offset-free** (``disturbance_gain = α > 0``) — the model is ``x⁺ = F(x, u + d)`` with a
  constant input disturbance ``d``. After each step the prediction ``F(x_prev, u_prev + d̂)`` is
  compared with the measured ``ω``: ``d̂ ← d̂ + α·B⁺(ω − ω̂)`` (``B = ∂ω⁺/∂u``, least squares),
  within ``disturbance_region_rad`` of the reference attitude and below ``disturbance_region_speed``
  only, ``|d̂|`` at most half the torque range (:class:`fvin_mpc.control.problem.DisturbanceEstimate`,
  shared with the IPOPT MPC). The
  control cost is ``|u − u_s|²`` with ``u_s = u_goal − d̂`` the torque that holds the goal in the
  model (``F(goal, 0, u_goal) = (goal, 0)``): at the goal the MPC has no reason to move, and the
  plant's steady state is where the corrected model agrees with it — no steady error from a
  persistent model bias (Pannocchia & Rawlings 2003; Maeder & Morari 2009).
* **failure** — a failed or non-finite QP leaves the plan as it was (already shifted): its first
  control, clipped, is applied and ``info["fallback"] = "previous-plan"``.
"""

from __future__ import annotations

import math
import re
import time
from dataclasses import replace
from typing import Any

import casadi as ca
import numpy as np

from fvin_mpc.control import implicit_dynamics, lane_kernel, riccati_kernel
from fvin_mpc.control.buffered import BufferedFunction
from fvin_mpc.control.linearization import (
    STEP_LIMIT_OMEGA,
    kept_jacobian_switch,
    node_distance_function,
    relinearized,
    renewing_item_function,
    shifted_items,
    stage_distance_function,
    step_limits,
    unrolled_stage_function,
)
from fvin_mpc.control.model_export import (
    GENERATED_SX_OPTIONS,
    CKernel,
    ExportedModel,
    compile_functions,
    kernel_function,
)
from fvin_mpc.control.mpc import MPC, MPCSettings
from fvin_mpc.control.problem import ControlProblem, Plan, control_bounds, predict_function, residual_functions
from fvin_mpc.control.riccati_qp import riccati_feedback_function
from fvin_mpc.core.backend import get_ops

CA, NP = get_ops("casadi"), get_ops("numpy")

#: The order a cold call tries ``cold_starts`` in (within ``rti.cold_budget_s``): from the ``"goal"``
#: guess the iteration reached IPOPT's optimum on the ball joint in ~10 iterations, from the
#: rollouts (ω clipped to the bound: large gaps) it diverged (docs/realtime.md).
RTI_COLD_ORDER = ("goal", "rollout+", "rollout-")
#: The generated source of the loop's functions (``rti_linearize_blocks``, ``rti_predict``, ``rti_feedback``,
#: ``rti_apply``), by that name in both loops: the Python loop compiles it into its library, the C loop's folder
#: holds it as ``fvc_model.c`` (:mod:`fvin_mpc.control.c_controller`) — the same text, so the same machine code
#: (a different name alone moved a function's time by 4 %: it changes the code's layout).
LOOP_SOURCE = "fvc_model"
#: Planned ``|ω_i|`` are kept below this fraction of ``1/h`` (the step's solvability limit).
OMEGA_VALID_FRACTION = 0.9


class RealTimeMPC(ControlProblem):
    """Real-time iteration MPC (module docstring); same constructor and ``controller(x)`` contract as
    :class:`~fvin_mpc.control.mpc.MPC`, plus :meth:`prepare` and :attr:`disturbance`.

    ``info`` keys: ``success``, ``fallback`` (``None`` or ``"previous-plan"``), ``iterations``,
    ``solve_time_s`` (the whole call), ``status`` (``"rti"``, ``"cold"``, ``"budget"`` or the QP
    solver's failure), ``cost`` (the model cost of the plan's linearization point), ``step_residual``,
    ``states``, ``controls``, ``disturbance`` (``d̂``, control units), ``gap`` (largest dynamics gap
    of the plan, in the charts), and on cold calls ``cold_start`` and ``cold_costs``.
    """

    def __init__(self, model: ExportedModel, settings: MPCSettings, goal: Any, torque_low: Any, torque_high: Any,
                 rest: Any = None, terminal_cost: Any = None, cold_start_score: Any = None,
                 goal_set: Any = None) -> None:
        # Features of the problem the real-time iteration cannot honour are refused, never ignored.
        if terminal_cost is not None:
            raise ValueError("the real-time iteration takes no terminal_cost hook (its QP is the Gauss–Newton "
                             "model of the problem's residuals); use solver='ipopt' or 'sqpmethod'")
        if cold_start_score is not None:
            raise ValueError("the real-time iteration ranks its cold guesses by model cost and dynamics gaps; "
                             "cold_start_score needs solver='ipopt', 'sqpmethod' or 'fatrop'")
        if settings.solver != "rti":
            raise ValueError(f"RealTimeMPC solves settings with solver='rti', got {settings.solver!r} "
                             "(fvin_mpc.control.scene.scene_mpc picks the class from the settings)")
        super().__init__(model, settings, goal, torque_low, torque_high, rest, goal_set=goal_set)
        self._cold_mpc = None
        if settings.rti.cold_solver == "ipopt":
            self._cold_mpc = MPC(model, replace(settings, solver="ipopt"), goal, torque_low,
                                 torque_high, rest, goal_set=goal_set)

    # ------------------------------------------------------------------ problem
    def _build(self) -> None:
        s, n, m, layout = self.settings, self.horizon, self.model.control_dim, self.layout
        ns, nd = layout.state_dim, layout.tangent_dim
        stage_size = nd + m

        x_bar = ca.SX.sym("x_bar", ns)
        u_bar, u_s = ca.SX.sym("u_bar", m), ca.SX.sym("u_s", m)
        reference = ca.SX.sym("reference", ns)  # the stage's reference state
        delta, du = ca.SX.sym("delta", nd), ca.SX.sym("du", m)
        x = layout.retract(x_bar, delta, CA)
        u = u_bar + du
        zero = [ca.DM.zeros(nd), ca.DM.zeros(m)]

        def at_zero(expressions: list[Any]) -> list[Any]:
            return ca.substitute(expressions, [delta, du], zero)

        # --- the model parameters: an input p of every function that evaluates the model (read by it
        # with rti.model_parameters, else unused: the constants baked in behind the same interface)
        parametric = s.rti.model_parameters
        parameter_count = self.model.model_parameters.size
        #: the model parameters the next preparation uses (:meth:`set_parameters`)
        self._parameters = self.model.model_parameters.defaults
        p_mx = ca.MX.sym("p", parameter_count)
        p_stages = [ca.repmat(p_mx, 1, n)] if parametric else []

        # --- dynamics: e(δ, Δu) = F(x, u + d) in x̄_{k+1}'s chart
        implicit = s.rti.dynamics == "implicit"
        if implicit:
            if not self.model.space.has_step_residual or self.model.casadi_terms is None:
                raise ValueError(f"rti.dynamics='implicit' needs the step's own equations, which the "
                                 f"{self.model.space.description} space does not provide, and rigid-body terms "
                                 f"(model {self.model.name!r}); use rti.dynamics='unrolled'")
            parametrized = self.model if parametric else None
            node_terms, term_layout = implicit_dynamics.node_terms_function(self.model.casadi_terms,
                                                                            parametrized)
            implicit_stage = implicit_dynamics.implicit_stage_function(self.model.casadi_terms, term_layout,
                                                                       self.model.step_size, parametrized)
        else:
            step = self.model.parametric_step if parametric else self.model.step
            stage_dynamics = unrolled_stage_function(step, layout, m, model=self.model)
        # --- the Jacobians a linearization may keep from the previous one (rti.relinearize_every): each item
        # (a stage; a node of the implicit dynamics, whose derivatives are its terms' slopes) computes its values
        # always and its derivatives where `fresh` says or where it moved more than rti.relinearize_tol from
        # where its kept ones were computed (its `point`), else passes the given ones through
        self._step_limits = step_limits(layout, STEP_LIMIT_OMEGA * self.omega_bound)
        tolerance = s.rti.relinearize_tol
        if implicit:
            node_values, _ = implicit_dynamics.node_terms_function(self.model.casadi_terms, parametrized,
                                                                   derivatives=False)
            item_function = renewing_item_function(
                "rti_node_terms_renewing", kept_jacobian_switch("rti_node_terms_select", node_terms, node_values),
                node_distance_function(), tolerance)
            items, kept_rows, kept_width, point_size = n + 1, term_layout.size, 3, 4
        else:
            item_function = renewing_item_function(
                "rti_dynamics_renewing",
                kept_jacobian_switch("rti_dynamics_select", stage_dynamics,
                                     unrolled_stage_function(step, layout, m, jacobian=False)),
                stage_distance_function(layout, m, self._step_limits, self.torque_high - self.torque_low),
                tolerance)
            items, kept_rows, kept_width, point_size = n, nd, stage_size, ns + m
        # --- the stages mapped four at a time on the vector units where they can be (rti.stage_lanes): every
        # item renewed each time (relinearize_every = 1), so the per-item switch is the full stage always
        lanes = lane_kernel.uses_lanes(s.rti.stage_lanes, s.compile == "cached", s.rti.relinearize_every, not implicit)
        #: the hand-written or translated C functions the generated code calls (:mod:`~fvin_mpc.control.lane_kernel`,
        #: :mod:`~fvin_mpc.control.riccati_kernel`)
        self.loop_kernels: tuple[CKernel, ...] = ()

        def in_lanes(function: ca.Function) -> ca.Function | None:
            """``function.map(n)`` as a lane kernel (its outputs dense), or ``None`` where ``lanes`` says no or
            its code has no vector translation (``auto`` warns)."""
            if not lanes:
                return None
            inputs = function.sx_in()
            dense = ca.Function(function.name(), inputs, [ca.densify(o) for o in function.call(inputs)],
                                function.name_in(), function.name_out(), GENERATED_SX_OPTIONS)
            kernel = lane_kernel.lane_map_or_none(s.rti.stage_lanes, dense, n)
            if kernel is None:
                return None
            self.loop_kernels += (kernel,)
            return kernel_function(kernel)

        kept_mx, fresh_mx = ca.MX.sym("J", kept_rows, kept_width * items), ca.MX.sym("fresh", 1, items)
        points_mx = ca.MX.sym("points", point_size, items)

        # --- cost: the problem's residuals (control/problem.py), the ω bound as a stiff penalty on its
        # excess (zero inside the bound): the linearized QP then has only the torque boxes and is always
        # feasible. Gauss–Newton.
        energy = None
        rest_state = None if self.rest is None else np.concatenate([self.rest, np.zeros(3)])
        if s.terminal_energy_weight > 0:
            energy = ((self.model.parametric_energy, rest_state) if parametric
                      else (self.model.energy_function, self.model.energy(rest_state)))
        stage_function, terminal_function = residual_functions(
            layout, s, m, self.omega_bound, s.rti.omega_penalty, energy, parameter_count if parametric else 0,
            self.model.model_parameters.control_effect)
        p_sx = ca.SX.sym("p", parameter_count)
        cost_parameters = [p_sx] if parametric else []
        stage_residual = stage_function(x, u, reference, u_s, *cost_parameters)
        terminal_residual = terminal_function(x, reference, *cost_parameters)
        regularization = s.rti.regularization

        def gauss_newton(residual: Any, variables: Any, size: int) -> list[Any]:
            jacobian = ca.jacobian(residual, variables)
            hessian = 2.0 * ca.mtimes(jacobian.T, jacobian) + regularization * ca.SX.eye(size)
            return at_zero([ca.densify(hessian), 2.0 * ca.mtimes(jacobian.T, residual), ca.sumsqr(residual)])

        stage_cost = ca.Function("rti_stage_cost", [x_bar, u_bar, reference, u_s, *cost_parameters],
                                 gauss_newton(stage_residual, ca.vertcat(delta, du), stage_size),
                                 GENERATED_SX_OPTIONS)
        terminal_cost = ca.Function("rti_terminal_cost", [x_bar, reference, *cost_parameters],
                                    gauss_newton(terminal_residual, delta, nd), GENERATED_SX_OPTIONS)

        # --- the whole QP over the horizon, stage-wise, δ_0 eliminated (it is fixed by the measurement):
        # z = (Δu_0, δ_1, Δu_1, …, δ_N); the feedback adds A_0 δ_0 to the first gap and S_0 δ_0 to the
        # gradient of Δu_0.
        states, controls = ca.MX.sym("X", ns, n + 1), ca.MX.sym("U", m, n)
        references, d_mx, u_s_mx = ca.MX.sym("R", ns, n + 1), ca.MX.sym("d", m), ca.MX.sym("u_s", m, n)
        if implicit:  # the terms once per node, each stage reads its two nodes'
            node_parameters = [ca.repmat(p_mx, 1, n + 1)] if parametric else []
            qs = layout.attitude(by="the implicit dynamics").quaternion
            values, slopes, points_out = item_function.map(n + 1)(fresh_mx, states[qs, :], *node_parameters, kept_mx,
                                                                  points_mx)
            gaps, jacobians = implicit_stage.map(n)(states[:, :n], controls, states[:, 1:], ca.repmat(d_mx, 1, n),
                                                    values[:, :n], slopes[:, :3 * n], values[:, 1:], slopes[:, 3:],
                                                    *p_stages)
            kept_out = slopes
        elif (dynamics_lanes := in_lanes(stage_dynamics)) is not None:
            gaps, jacobians = dynamics_lanes(states[:, :n], controls, states[:, 1:], ca.repmat(d_mx, 1, n), *p_stages)
            kept_out, points_out = jacobians, ca.vertcat(states[:, :n], controls)  # every stage renewed, here
        else:
            gaps, jacobians, points_out = item_function.map(n)(fresh_mx, states[:, :n], controls, states[:, 1:],
                                                               ca.repmat(d_mx, 1, n), *p_stages, kept_mx, points_mx)
            kept_out = jacobians
        stage_costs = in_lanes(stage_cost)
        stage_costs = stage_cost.map(n) if stage_costs is None else stage_costs
        hessians, gradients, costs = stage_costs(states[:, :n], controls, references[:, :n], u_s_mx, *p_stages)
        terminal_hessian, terminal_gradient, terminal_value = terminal_cost(states[:, n], references[:, n],
                                                                            *([p_mx] if parametric else []))
        size = stage_size * n
        blocks = [hessians[:, k * stage_size:(k + 1) * stage_size] for k in range(n)]
        hessian = ca.diagcat(blocks[0][nd:, nd:], *blocks[1:], terminal_hessian)
        rows = [ca.horzcat(jacobians[:, nd:stage_size], -ca.MX.eye(nd), ca.MX(nd, size - m - nd))]
        for k in range(1, n):
            column = m + (k - 1) * stage_size
            rows.append(ca.horzcat(ca.MX(nd, column), jacobians[:, k * stage_size:(k + 1) * stage_size],
                                   -ca.MX.eye(nd), ca.MX(nd, size - column - stage_size - nd)))
        constraints = ca.vertcat(*rows)
        gradient = ca.vertcat(gradients[nd:, 0], ca.vec(gradients[:, 1:]), terminal_gradient)
        linearize = ca.Function("rti_linearize",
                                [states, controls, references, d_mx, u_s_mx, p_mx, kept_mx, points_mx, fresh_mx],
                                [hessian, gradient, constraints, ca.vec(gaps), ca.sum2(costs) + terminal_value,
                                 jacobians[:, :nd], blocks[0][nd:, :nd], kept_out, points_out],
                                ["X", "U", "R", "d", "u_s", "p", "J_kept", "points_kept", "fresh"],
                                ["H", "g", "A", "gaps", "cost", "A0", "S0", "J", "points"])
        linearize_blocks = ca.Function("rti_linearize_blocks",
                                       [states, controls, references, d_mx, u_s_mx, p_mx, kept_mx, points_mx, fresh_mx],
                                       # dense where the Jacobians have structural zeros: the C driver passes
                                       # plain arrays, and a dense wrapper around it copied every output
                                       [hessians, terminal_hessian, gradients, terminal_gradient, ca.densify(jacobians),
                                        gaps, ca.sum2(costs) + terminal_value, ca.densify(kept_out), points_out],
                                       ["X", "U", "R", "d", "u_s", "p", "J_kept", "points_kept", "fresh"],
                                       ["H", "HN", "g", "gN", "AB", "gaps", "cost", "J", "points"])
        predict = predict_function(self.model, "rti_predict", "input" if parametric else "constant")

        self._implicit = implicit
        #: the Jacobians a linearization may keep (rti.relinearize_every): how many items, which it renews when
        #: it has the previous ones, all of them when not, and the previous ones on the plan's lineage
        self._kept_items = items
        self._relinearized = relinearized(items, s.rti.relinearize_every, s.rti.relinearize_head)
        self._all_fresh = np.ones(items)
        # a period's further iterations renew only what moved — unless every item is renewed every time
        self._renewed_further = np.ones(items) if s.rti.relinearize_every == 1 else np.zeros(items)
        no_points = np.zeros((items, point_size))
        # unit quaternions where the points hold them: a distance from them is finite
        for first in [0] if implicit else [quaternion.start for quaternion in layout.quaternions]:
            no_points[:, first] = 1.0
        self._nothing_kept = (np.zeros((kept_rows, kept_width * items)), no_points.T.copy())
        self._plan_jacobians: tuple[np.ndarray, np.ndarray] | None = None
        self._control_bounds = control_bounds(self.torque_low, self.torque_high, n, s.torque_reserve)
        self._omega_valid = OMEGA_VALID_FRACTION / self.model.step_size
        riccati = s.rti.qp_solver == "riccati"
        if riccati:
            linearize = linearize_blocks
            sweep = None
            if riccati_kernel.uses_kernel(s.rti.riccati_stage, nd, s.compile == "cached", s.rti.qp_method):
                self.loop_kernels += (riccati_kernel.riccati_stage_kernel(nd, m, n),)
                sweep = kernel_function(self.loop_kernels[-1])
            functions = [linearize, predict, *riccati_feedback_function(
                layout, n, m, *self._control_bounds, self._step_limits, self._omega_valid, s.rti.qp_iterations,
                method=s.rti.qp_method, sweep=sweep)]
        else:
            functions = [linearize, predict]
        #: the CasADi functions the loop calls (linearize, predict, feedback), before compilation: what
        #: :mod:`fvin_mpc.control.c_controller` generates as C — one source for both loops
        self.loop_functions = tuple(functions)
        self.compile_report = None
        if s.compile == "cached":
            compiled, self.compile_report = compile_functions(
                functions, prefix=re.sub(r"[^0-9A-Za-z_]", "_", f"rti_{self.model.name}"), kernels=self.loop_kernels,
                source_name=LOOP_SOURCE if riccati else None)
            functions = [compiled[function.name()] for function in functions]
        if riccati:  # every argument of the Riccati path is dense: call through buffers, not DMs
            functions = [BufferedFunction(function) for function in functions]
        self._linearize, self._predict_with_parameters = functions[:2]
        self._feedback = functions[2] if riccati else None
        self._apply = functions[3] if riccati else None
        self._qp = None if riccati else self._make_qp(hessian.sparsity(), constraints.sparsity())
        self._size = size
        self._stage_size = stage_size

    def _make_qp(self, h: ca.Sparsity, a: ca.Sparsity) -> ca.Function:
        s, n, m = self.settings, self.horizon, self.model.control_dim
        if s.rti.qp_solver == "hpipm":
            options = {"N": n, "nx": [0] + [self.layout.tangent_dim] * n, "nu": [m] * n + [0], "ng": [0] * (n + 1),
                       "hpipm": {"iter_max": 50, "warm_start": 0, "mode": "speed_abs"},
                       "error_on_fail": False}
        elif s.rti.qp_solver == "qrqp":
            options = {"print_iter": False, "print_header": False, "error_on_fail": False}
        else:
            options = {"osqp": {"verbose": False, "eps_abs": 1e-8, "eps_rel": 1e-8, "max_iter": 4000},
                       "error_on_fail": False}
        return ca.conic("rti_qp", s.rti.qp_solver, {"h": h, "a": a}, options)

    def _linearize_at(self, plan: Plan, kept: tuple[np.ndarray, np.ndarray] | None = None,
                      by_rule: bool = True) -> tuple[Any, ...]:
        """The linearization at ``plan``. ``kept``: the previous linearization's Jacobians on this plan's
        lineage and the points they were computed at (shifted as the plan was), of which it keeps those that
        :func:`relinearized` does not renew (``by_rule``; else, in a period's further iteration, it renews only
        what moved — all when ``rti.relinearize_every`` is 1) and that moved less than ``rti.relinearize_tol``;
        ``None`` renews all. The Jacobians and points it ends with are left in ``_last_jacobians``."""
        if self._implicit:
            # Both ends of a stage on one sheet of S³, as the exported step continues q_k: a model
            # whose terms are not sign-invariant reads them at each node's own sign (the measured
            # state's sign can differ from the plan's). The same rotations, the same charts.
            quaternions = plan.states[:, self.layout.attitude(by="the implicit dynamics").quaternion]
            turns = np.einsum("ij,ij->i", quaternions[:-1], quaternions[1:])
            if turns.min() < 0.0:  # rare (the measured state's sign): flip every node after a sign change
                quaternions *= np.cumprod(np.concatenate([[1.0], np.where(turns < 0.0, -1.0, 1.0)]))[:, None]
        time_, _, _, references = self._sample_reference()
        key = (time_, self.disturbance.tobytes())
        cached = getattr(self, "_targets_cache", None)
        if cached is None or cached[0] != key:  # u_s changes only with the time and d̂: compute once
            cached = self._targets_cache = (key, self.reference_window()[1].T)
        *linearization, jacobians, points = self._linearize(
            plan.states.T, plan.controls.T, references, self.disturbance, cached[1], self._parameters,
            *(self._nothing_kept if kept is None else kept),
            self._all_fresh if kept is None else self._relinearized if by_rule else self._renewed_further)
        self._last_jacobians = (np.asarray(jacobians, dtype=float), np.asarray(points, dtype=float))
        return tuple(linearization)

    # ------------------------------------------------------------------ model parameters
    def _predict(self, x: Any, u: Any) -> tuple[Any, ...]:
        """One model step with the current model parameters (``predict_function``'s outputs)."""
        return self._predict_with_parameters(x, u, self._parameters)

    def _rollout(self, x0: np.ndarray, controls: np.ndarray) -> np.ndarray:
        """The rollout first guesses step with the loop's own compiled prediction (``rti_predict``, with the
        current model parameters), as the C driver does: the same machine code, so the two loops' cold plans
        agree to the bit even where the compiled code rounds apart from CasADi's interpreter (fused
        multiply–adds)."""
        states = [np.asarray(x0, dtype=float)]
        for u in controls:
            states.append(np.asarray(self._predict(states[-1], u)[0], dtype=float).ravel())
        return np.array(states)

    @property
    def kept_jacobians(self) -> tuple[int, int, int, np.ndarray, np.ndarray]:
        """``(items, Jacobian numbers per item, point numbers per item, renewed, renewed further)`` of the
        Jacobians a linearization may keep (``rti.relinearize_every``): stages, or nodes of the implicit dynamics;
        the items a preparation renews whether they moved or not (:func:`relinearized`), and those a period's
        further iteration renews (none, or all when ``relinearize_every`` is 1)."""
        jacobians, points = self._nothing_kept
        return (self._kept_items, jacobians.size // self._kept_items, points.size // self._kept_items,
                self._relinearized.copy(), self._renewed_further.copy())

    @property
    def nothing_kept(self) -> tuple[np.ndarray, np.ndarray]:
        """What a linearization that renews every item is given as kept Jacobians and points (zeros, unit
        quaternions), in its input shapes."""
        return self._nothing_kept[0].copy(), self._nothing_kept[1].copy()

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """The model parameters' names (:mod:`fvin_mpc.core.model_parameters`), in the vector's order."""
        return self.model.model_parameters.names

    @property
    def parameters(self) -> np.ndarray:
        """The model parameters in use (a copy)."""
        return self._parameters.copy()

    def set_parameters(self, values: Any = None, **blocks: Any) -> None:
        """New model parameters: ``values`` a whole vector (:attr:`parameter_names`' order) and/or blocks by
        name, e.g. ``set_parameters(gain_scale=[0.8])`` (the rest as they are). No recompilation: the
        compiled functions take them as an input. The plan prepared already keeps the values it was
        linearized with; the next preparation (and any further iteration of the next call) uses the new
        ones, and so do the control that holds the goal (``u_goal``) and the disturbance estimate's next
        prediction. ``ValueError`` for a controller built with ``rti.model_parameters=False`` or values
        of the wrong size or not finite."""
        if not self.settings.rti.model_parameters:
            raise ValueError("this controller has its model parameters baked in (rti.model_parameters=False); "
                             "build it with rti.model_parameters=True to change them at run time")
        parameters = self.model.model_parameters
        self._parameters = parameters.values(self._parameters if values is None else values, **blocks)
        self._u_goal = self._goal_control()
        self._targets_cache = None
        self._plan_jacobians = None  # computed with the old parameters: the next linearization renews them all

    # ------------------------------------------------------------------ one SQP iteration
    def _iterate(self, plan: Plan, linearization: tuple[Any, ...], x0: np.ndarray) -> tuple[Plan | None, str]:
        """Solve the QP at ``plan`` with ``δ_0`` fixed by the measured ``x0``; the updated plan (or
        ``None`` and the QP solver's status)."""
        if self._feedback is not None:
            return self._iterate_riccati(plan, linearization, x0)
        h, g, a, gaps, _, a0, s0 = linearization
        n, m, size, layout = self.horizon, self.model.control_dim, self._stage_size, self.layout
        nd = layout.tangent_dim
        delta0 = layout.local(plan.states[0], x0)
        gaps = -np.asarray(gaps, dtype=float).ravel()
        gaps[:nd] -= np.asarray(a0, dtype=float) @ delta0
        g = np.asarray(g, dtype=float).ravel()
        g[:m] += np.asarray(s0, dtype=float) @ delta0
        lower, upper = np.full(self._size, -np.inf), np.full(self._size, np.inf)
        control_lower = lower[:size * n].reshape(n, size)[:, :m]  # Δu_k sits first in each stage
        control_upper = upper[:size * n].reshape(n, size)[:, :m]
        stage_low, stage_high = self._control_bounds
        control_lower[:] = stage_low - plan.controls
        control_upper[:] = stage_high - plan.controls
        solution = self._qp(h=h, g=g, a=a, lba=gaps, uba=gaps, lbx=lower, ubx=upper)
        stats = self._qp.stats()
        self.qp_iterations = int(stats.get("iter_count", -1))
        z = np.asarray(solution["x"], dtype=float).ravel()
        if not (stats.get("success", False) and np.all(np.isfinite(z))):
            return None, str(stats.get("return_status", "qp-failed"))
        stages = z[:n * size].reshape(n, size)  # rows: (Δu_k, δ_{k+1})
        # A crude trust region: each stage's state step is clipped to `step_limits` (`STEP_LIMIT_ANGLE`,
        # a fraction of the ω bound, …: a Gauss–Newton step from a poor guess — with large gaps — can
        # otherwise leap past h|ω| ≈ 1, where the model means nothing). Clipping per stage, not
        # scaling the whole step, keeps the progress of the stages that are fine.
        steps = stages[:, m:]
        clipped = np.clip(steps, -self._step_limits, self._step_limits)
        deltas = np.vstack([delta0[None, :], clipped])
        states = layout.retract(plan.states, deltas)
        rates = layout.angular_rates
        states[:, rates] = np.clip(states[:, rates], -self._omega_valid, self._omega_valid)
        states[0] = x0
        controls = np.clip(plan.controls + stages[:, :m], stage_low, stage_high)
        self.step_scale = float(np.mean(clipped == steps))
        #: size of the last step: largest |Δu| over the torque range, or |δ| over the trust region
        self.last_step = max(float(np.max(np.abs(stages[:, :m]) / (self.torque_high - self.torque_low))),
                             float(np.max(np.abs(clipped) / self._step_limits)))
        return Plan(states, controls, None, None), "rti"

    def _iterate_riccati(self, plan: Plan, linearization: tuple[Any, ...],
                         x0: np.ndarray) -> tuple[Plan | None, str]:
        """:meth:`_iterate` in one compiled call (:func:`riccati_feedback_function`)."""
        h, h_n, g, g_n, ab, gaps, _ = linearization
        states, controls, step, mu, _, _ = self._feedback(plan.states.T, plan.controls.T, x0, h, h_n, g, g_n, ab, gaps)
        states, controls = np.asarray(states, dtype=float).T, np.asarray(controls, dtype=float).T
        self.qp_iterations = self.settings.rti.qp_iterations
        self.last_step, self.qp_mu = float(step), float(mu)
        if not (np.all(np.isfinite(states)) and np.all(np.isfinite(controls))):
            return None, "qp-not-finite"
        return Plan(states, controls, None, None), "rti"

    def _apply_prepared(self, x0: np.ndarray) -> tuple[Plan | None, int, str]:
        """The prepared feedback (``rti.feedback="prepared"``): the preparation's QP gains applied to the
        measured ``x0`` — one forward pass, no factorization in the call."""
        assert self._plan is not None and self._linearization is not None
        gains, feedforwards = self._gains
        _, _, _, _, ab, gaps, _ = self._linearization
        states, controls, step = self._apply(self._plan.states.T, self._plan.controls.T, x0, gains, feedforwards, ab,
                                             gaps)
        states, controls = np.asarray(states, dtype=float).T, np.asarray(controls, dtype=float).T
        self.last_step = float(step)
        if not (np.all(np.isfinite(states)) and np.all(np.isfinite(controls))):
            return None, 0, "qp-not-finite"
        return Plan(states, controls, None, None), 1, "rti"

    def _improve(self, plan: Plan, x0: np.ndarray, iterations: int, deadline: float,
                 linearization: tuple[Any, ...] | None = None,
                 keep_jacobians: bool = False) -> tuple[Plan | None, int, str, float]:
        """Up to ``iterations`` SQP iterations from ``plan``: the first always, each further one only
        while the last step was not negligible (``rti.tol``) and the last iteration's duration still
        fits before ``deadline`` (perf_counter). Returns the plan (``None`` if the first QP failed), the
        iterations done, the status (``"budget"`` if time, not convergence, stopped it) and the time of
        the last iteration. ``keep_jacobians``: ``plan`` is the controller's own (a warm call), and each
        further linearization keeps the last one's Jacobians where the plan's nodes did not move
        (``rti.relinearize_tol``): the period's first linearization renewed those the rule renews."""
        done, status, last = 0, "rti", 0.0
        current = plan
        while done < iterations:
            if done > 0:
                if self.last_step < self.settings.rti.tol:
                    break
                if time.perf_counter() + last > deadline:
                    status = "budget"
                    break
            start = time.perf_counter()
            if linearization is None:
                keeps = keep_jacobians and self.settings.rti.relinearize_every > 1
                linearization = self._linearize_at(current, self._plan_jacobians if keeps else None, by_rule=False)
                if keep_jacobians:
                    self._plan_jacobians = self._last_jacobians
            updated, qp_status = self._iterate(current, linearization, x0)
            linearization = None
            last = time.perf_counter() - start
            if updated is None:
                return (None if done == 0 else current), done, qp_status, last
            current, done = updated, done + 1
        return current, done, status, last

    # ------------------------------------------------------------------ control
    def prepare(self) -> None:
        """Shift the plan by one step and linearize it for the next call (the preparation phase)."""
        if self._plan is None or self._linearization is not None:
            return
        plan = self._plan
        last_state = self._predict(plan.states[-1], plan.controls[-1] + self.disturbance)[0]
        states = np.vstack([plan.states[1:], np.asarray(last_state, dtype=float).reshape(1, self.layout.state_dim)])
        rates = self.layout.angular_rates
        states[-1, rates] = np.clip(states[-1, rates], -self.omega_bound, self.omega_bound)
        controls = np.vstack([plan.controls[1:], plan.controls[-1:]])
        self._plan = Plan(states, controls, None, None)
        # relinearize_every = 1 renews every item: nothing kept to shift
        kept = None if self._plan_jacobians is None or self.settings.rti.relinearize_every == 1 else tuple(
            shifted_items(array, self._kept_items) for array in self._plan_jacobians)
        self._linearization = self._linearize_at(self._plan, kept)
        self._plan_jacobians = self._last_jacobians
        if self.settings.rti.feedback == "prepared":
            # The QP solved now, at the predicted first state; the call applies its gains to the measured one.
            h, h_n, g, g_n, ab, gaps, _ = self._linearization
            plan = self._plan
            *_, mu, gains, feedforwards = self._feedback(plan.states.T, plan.controls.T, plan.states[0], h, h_n, g,
                                                         g_n, ab, gaps)
            self._gains, self.qp_mu = (gains, feedforwards), float(mu)

    def reset(self) -> None:
        """Forget the plan and the disturbance estimate (the next call is a cold start); the clock
        restarts at 0."""
        super().reset()
        self._plan: Plan | None = None
        self._plan_jacobians = None

    def _forget_preparation(self) -> None:
        self._linearization: tuple[Any, ...] | None = None

    def __call__(self, x: Any) -> tuple[np.ndarray, dict[str, Any]]:
        """The torque for the measured state ``x (n,)``; see the class docstring for ``info``."""
        start = time.perf_counter()
        x0 = self.layout.check(x)
        s = self.settings
        extra: dict[str, Any] = {}
        self._update_estimate(x0)
        restarted = self._leaves_plan(x0)
        if restarted:
            self._plan, self._linearization = None, None
        if self._plan is None:  # a cold call's plan comes with no Jacobians of its own lineage
            self._plan_jacobians = None
        if self._plan is None and self._cold_mpc is not None:  # cold: IPOPT to convergence, once
            self._cold_mpc.reset()
            _, cold_info = self._cold_mpc(x0)
            self._plan = Plan(np.asarray(cold_info["states"], dtype=float).copy(),
                               np.asarray(cold_info["controls"], dtype=float).copy(), None, None)
            self._plan.states[0] = x0
            extra = {"cold_start": cold_info.get("cold_start"), "cold_solver": "ipopt",
                     "cold_ipopt_success": cold_info["success"]}
            plan, iterations, status, _ = self._improve(self._plan, x0, 1, start, None)
            fallback, success = None, plan is not None
            if plan is None:
                plan, fallback = self._plan, "previous-plan"
        elif self._plan is None:  # cold: each first guess, a few iterations, within the cold budget
            deadline = start + s.rti.cold_budget_s
            best: tuple[float, Plan, str] | None = None
            costs: dict[str, float] = {}
            iterations, status = 0, "cold"
            for number, guess_name in enumerate(sorted(s.cold_starts, key=RTI_COLD_ORDER.index)):
                guess = self._first_guess(x0, guess_name)
                guess = Plan(guess.states, guess.controls, None, None)
                # Past the budget a guess is still scored, un-iterated: the budget must not decide which
                # guess wins. On a loaded machine it ran out inside the first ("goal") guess, whose gaps
                # were still open, and the others were never looked at: from 7 of 20 starts near hanging
                # that half-iterated plan (off the hinge, where a learned model means nothing) was kept and
                # the torque chattered at the bottom. A rollout is a plan of the model from the start.
                over = number > 0 and time.perf_counter() > deadline
                plan, done, step_status, _ = (None, 0, "budget", None) if over else self._improve(
                    guess, x0, s.rti.cold_iter, deadline)
                iterations += done
                status = "budget" if step_status == "budget" else status
                plan = guess if plan is None else plan
                score = self._score(plan)
                costs[guess_name] = score
                if best is None or score < best[0]:
                    best = (score, plan, guess_name)
            assert best is not None
            plan, fallback, success = best[1], None, True
            extra = {"cold_start": best[2], "cold_costs": costs}
        else:
            if self._linearization is None:
                self.prepare()
            assert self._plan is not None
            if s.rti.feedback == "prepared":
                plan, iterations, status = self._apply_prepared(x0)
            else:
                plan, iterations, status, _ = self._improve(self._plan, x0, s.rti.max_iter, start + s.rti.budget_s,
                                                            self._linearization, keep_jacobians=True)
            fallback, success = None, plan is not None
            if plan is None:  # the shifted previous plan, clipped
                plan, fallback = self._plan, "previous-plan"
        self._plan, self._linearization = plan, None
        u = np.clip(plan.controls[0], self.torque_low, self.torque_high)
        residual = self._predicted(x0, u)
        info = {"status": status, "success": success, "fallback": fallback, "iterations": iterations,
                "solve_time_s": time.perf_counter() - start, "cost": float("nan"), "step_residual": residual,
                "states": plan.states, "controls": plan.controls, "disturbance": self.disturbance.copy(),
                "qp_iterations": getattr(self, "qp_iterations", -1), "restarted": restarted, **extra}
        return u, info

    def _leaves_plan(self, x0: np.ndarray) -> bool:
        """Whether the measured ``ω`` is more than ``rti.restart_speed`` from the prepared plan's first
        state (the model's prediction of now) in some component: the plan is stale, start cold."""
        limit = self.settings.rti.restart_speed
        if self._plan is None or not math.isfinite(limit):
            return False
        if self._linearization is None:
            self.prepare()
        rates = self.layout.angular_rates
        return bool(np.max(np.abs(x0[rates] - self._plan.states[0][rates])) > limit)

    def _score(self, plan: Plan) -> float:
        """A cold guess's merit: model cost plus a heavy penalty on its dynamics gaps."""
        gaps, cost = self._gaps_and_cost(plan)
        return float(cost) + 1e3 * float(np.sum(np.square(np.asarray(gaps, dtype=float))))

    def _gaps_and_cost(self, plan: Plan) -> tuple[Any, Any]:
        linearization = self._linearize_at(plan)
        return linearization[5:7] if self._feedback is not None else linearization[3:5]

    def plan_cost(self, plan: Plan | None = None) -> tuple[float, float]:
        """``(cost, largest gap)`` of ``plan`` (default: the current one) under the model — for tests
        and studies; the cost is the MPC's objective when the gaps are zero."""
        plan = self._plan if plan is None else plan
        if plan is None:
            raise ValueError("no plan yet: call the controller first")
        gaps, cost = self._gaps_and_cost(plan)
        return float(cost), float(np.max(np.abs(np.asarray(gaps, dtype=float))))
