"""Real-time iteration MPC: one Gauss–Newton SQP step per control period, bounded compute — the controller.
Its linearization is :mod:`fvin_mpc.control.linearization`, its QP solver :mod:`fvin_mpc.control.riccati_qp`,
its loop the generated C library of :mod:`fvin_mpc.control.c_controller`: this class builds the problem's
functions, has them generated and compiled once (cached), and drives the library through ``ctypes`` — the
same library ``python -m fvin_mpc.export --controller`` writes for a robot.

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
  (:func:`~fvin_mpc.control.riccati_qp.riccati_feedback_function`) and generated into the library with the
  linearization: no Python between stages or iterations (docs/peers.md measures it beside HPIPM, DAQP,
  ProxQP and OSQP on the same QPs).
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
  ``rti.cold_iter`` iterations while ``rti.cold_budget_s`` lasts; the best is kept
  (``rti.cold_solver="ipopt"``: the IPOPT MPC's solution instead, handed to the library and improved by one
  iteration). Guesses reached
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
  only, ``|d̂|`` at most half the torque range (the library's; the IPOPT MPC's is
  :class:`fvin_mpc.control.problem.DisturbanceEstimate`). The
  control cost is ``|u − u_s|²`` with ``u_s = u_goal − d̂`` the torque that holds the goal in the
  model (``F(goal, 0, u_goal) = (goal, 0)``): at the goal the MPC has no reason to move, and the
  plant's steady state is where the corrected model agrees with it — no steady error from a
  persistent model bias (Pannocchia & Rawlings 2003; Maeder & Morari 2009).
* **failure** — a failed or non-finite QP leaves the plan as it was (already shifted): its first
  control, clipped, is applied and ``info["fallback"] = "previous-plan"``.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import replace
from typing import Any

import casadi as ca
import numpy as np

from fvin_mpc.control import implicit_dynamics, lane_kernel, riccati_kernel
from fvin_mpc.control.buffered import BufferedFunction
from fvin_mpc.control.c_controller import (
    COLD_GUESS_NAMES,
    LOOP_SOURCE,
    RTI_COLD_ORDER,
    STATUS_NAMES,
    ControllerLibrary,
    cached_library,
)
from fvin_mpc.control.linearization import (
    STEP_LIMIT_OMEGA,
    kept_jacobian_switch,
    node_distance_function,
    relinearized,
    renewing_item_function,
    stage_distance_function,
    step_limits,
    unrolled_stage_function,
)
from fvin_mpc.control.model_export import GENERATED_SX_OPTIONS, CKernel, CompileReport, ExportedModel, kernel_function
from fvin_mpc.control.mpc import MPC, MPCSettings
from fvin_mpc.control.problem import ControlProblem, Plan, control_bounds, predict_function, residual_functions
from fvin_mpc.control.riccati_qp import riccati_feedback_function
from fvin_mpc.core.backend import get_ops

CA, NP = get_ops("casadi"), get_ops("numpy")

__all__ = ["LOOP_SOURCE", "RTI_COLD_ORDER", "RealTimeMPC"]

#: Planned ``|ω_i|`` are kept below this fraction of ``1/h`` (the step's solvability limit).
OMEGA_VALID_FRACTION = 0.9


class RealTimeMPC(ControlProblem):
    """Real-time iteration MPC (module docstring); same constructor and ``controller(x)`` contract as
    :class:`~fvin_mpc.control.mpc.MPC`, plus :meth:`prepare` and :attr:`disturbance`.

    ``info`` keys: ``success``, ``fallback`` (``None`` or ``"previous-plan"``), ``iterations``,
    ``solve_time_s`` (the library's call), ``status`` (``"rti"``, ``"cold"``, ``"budget"`` — a wall-clock
    budget ended the iterations — or ``"qp-not-finite"``), ``cost`` (NaN: :meth:`plan_cost` computes it),
    ``step_residual`` (the model's Newton residual for the applied step), ``states``, ``controls``,
    ``disturbance`` (``d̂``, control units), ``qp_iterations``, ``restarted``, and on cold calls
    ``cold_start`` and ``cold_costs`` (with ``rti.cold_solver="ipopt"``: ``cold_solver`` and
    ``cold_ipopt_success``).

    ``compile="none"`` defers building the library to its first use (``python -m fvin_mpc.export`` writes the
    folder without it).
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
        if settings.rti.qp_solver != "riccati":
            raise ValueError(f"rti.qp_solver={settings.rti.qp_solver!r}: the real-time loop is generated C and its "
                             "QP is the generated Riccati interior-point solver ('riccati'); docs/peers.md "
                             "compares it with HPIPM, DAQP, ProxQP and OSQP on the same QPs")
        self._had_plan = False
        super().__init__(model, settings, goal, torque_low, torque_high, rest, goal_set=goal_set)
        self._cold_mpc = None
        if settings.rti.cold_solver == "ipopt":
            self._cold_mpc = MPC(model, replace(settings, solver="ipopt"), goal, torque_low,
                                 torque_high, rest, goal_set=goal_set)
        if settings.compile == "cached":
            self._load_library()

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
        self._control_bounds = control_bounds(self.torque_low, self.torque_high, n, s.torque_reserve)
        self._omega_valid = OMEGA_VALID_FRACTION / self.model.step_size
        sweep = None
        if riccati_kernel.uses_kernel(s.rti.riccati_stage, nd, s.compile == "cached", s.rti.qp_method):
            self.loop_kernels += (riccati_kernel.riccati_stage_kernel(nd, m, n),)
            sweep = kernel_function(self.loop_kernels[-1])
        #: the CasADi functions the loop calls (linearize, predict, feedback, apply), before generation: what
        #: :mod:`fvin_mpc.control.c_controller` generates as the library's C — their one source
        self.loop_functions = (linearize_blocks, predict, *riccati_feedback_function(
            layout, n, m, *self._control_bounds, self._step_limits, self._omega_valid, s.rti.qp_iterations,
            method=s.rti.qp_method, sweep=sweep))
        self.compile_report: CompileReport | None = None
        self._library: ControllerLibrary | None = None
        self._predict_function: Any = BufferedFunction(predict)  # CasADi's VM until the library is loaded

    # ------------------------------------------------------------------ the library
    def _load_library(self) -> ControllerLibrary:
        """The controller's generated C library, built once (cached by its sources' SHA-256) and loaded."""
        if self._library is None:
            start = time.perf_counter()
            path, cached = cached_library(self)
            library = ControllerLibrary(path, self)
            source = hashlib.sha256((path.parent / f"{LOOP_SOURCE}.c").read_bytes()).hexdigest()
            self.compile_report = CompileReport(library=path, cached=cached, codegen_s=0.0,
                                                compile_s=0.0 if cached else time.perf_counter() - start,
                                                source_sha256=source)
            self._predict_function = library.function("rti_predict")
            if self.settings.rti.model_parameters:
                library.set_parameters(self._parameters)
            self._library = library
            self._u_goal = library.goal_control()
            self._push_reference(new_reference=True)
            self.build_s += time.perf_counter() - start
        return self._library

    @property
    def library(self) -> ControllerLibrary:
        """The loaded library (built on first use where ``compile="none"`` deferred it)."""
        return self._load_library()

    def loop_function(self, name: str) -> BufferedFunction:
        """The library's compiled ``name`` (one of :data:`~fvin_mpc.control.c_controller.LOOP_FUNCTION_NAMES`),
        callable from Python through preallocated buffers: the machine code the loop runs."""
        return self.library.function(name)

    # ------------------------------------------------------------------ model parameters
    def _predict(self, x: Any, u: Any) -> tuple[Any, ...]:
        """One model step with the current model parameters (``predict_function``'s outputs)."""
        return self._predict_function(x, u, self._parameters)

    def _goal_control(self) -> np.ndarray:
        """``u_goal`` as the library computes it (its ``rti_predict``), where it is loaded."""
        if self._library is None:
            return super()._goal_control()
        return self._library.goal_control()

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
        parameters = self.model.model_parameters.values(self._parameters if values is None else values, **blocks)
        self.library.set_parameters(parameters)
        self._parameters = parameters
        self._u_goal = self._goal_control()

    # ------------------------------------------------------------------ the reference and the clock
    @property
    def disturbance(self) -> np.ndarray:
        """``d̂``, the library's input-disturbance estimate (control units)."""
        return self.library.disturbance() if self._library is not None else np.zeros(self.model.control_dim)

    def set_disturbance(self, value: Any) -> None:
        """Set ``d̂`` (control units), e.g. an estimate carried over from another controller of the same plant;
        the next preparation plans with it."""
        self.library.set_disturbance(np.broadcast_to(np.asarray(value, dtype=float), (self.model.control_dim,)))

    def set_reference(self, reference: Any) -> None:
        """Track ``reference`` from now on (sampled here, handed to the library over the horizon)."""
        super().set_reference(reference)
        self._push_reference(new_reference=True)

    def _push_reference(self, new_reference: bool = False) -> None:
        if self._library is None:
            return
        _, states, scales, _ = self._sample_reference()
        self._library.set_reference(states, scales, new_reference)

    def set_time(self, t: float) -> None:
        """The time of the next measurement (s, on the reference's clock); without it the clock advances by
        one step per call (:func:`fvin_mpc.control.closed_loop.run_episode` tells it)."""
        self._time = float(t)
        self.library.set_time(self._time, not self._reference.constant)

    def reset(self) -> None:
        """Forget the plan and the disturbance estimate (the next call is a cold start); the clock restarts
        at 0."""
        super().reset()
        self._had_plan = False
        if self._library is not None:
            self._library.reset()
            self._push_reference(new_reference=True)

    # ------------------------------------------------------------------ the loop
    def prepare(self) -> None:
        """Shift the plan by one step and linearize it for the next call (the preparation phase)."""
        if not self._reference.constant:
            self._time = self.library.time()
            self._push_reference()
        self.library.prepare()

    def feedback(self, x: Any) -> np.ndarray:
        """The control for the measured state ``x`` alone: one C call, no ``info`` (for timing loops)."""
        return self.library.feedback(x)

    def __call__(self, x: Any) -> tuple[np.ndarray, dict[str, Any]]:
        """The torque for the measured state ``x (n,)``; see the class docstring for ``info``."""
        start = time.perf_counter()
        x0 = self.layout.check(x)
        library = self.library
        if not self._reference.constant:
            self._time = library.time()
            self._push_reference()
        extra: dict[str, Any] = {}
        if self._cold_mpc is None:
            u = library.feedback(x0)
        elif library.measure(x0) == "cold":  # cold: IPOPT to convergence, then one iteration of the loop
            self._cold_mpc.reset()
            _, cold_info = self._cold_mpc(x0)
            u = library.solve_from(cold_info["states"], cold_info["controls"])
            extra = {"cold_start": cold_info.get("cold_start"), "cold_solver": "ipopt",
                     "cold_ipopt_success": cold_info["success"]}
        else:
            u = library.solve()
        solve_time = time.perf_counter() - start
        status = library.status()
        states, controls = library.plan()
        name = STATUS_NAMES[status.status]
        info = {"status": "qp-not-finite" if name == "previous-plan" else "budget" if status.budget else name,
                "success": name != "previous-plan", "fallback": "previous-plan" if name == "previous-plan" else None,
                "iterations": int(status.iterations), "solve_time_s": solve_time, "cost": float("nan"),
                "states": states, "controls": controls, "disturbance": library.disturbance(),
                "qp_iterations": self.settings.rti.qp_iterations, "restarted": bool(status.restarted), **extra}
        if name == "cold" and self._cold_mpc is None:
            info["cold_start"] = COLD_GUESS_NAMES[status.cold_guess]
            info["cold_costs"] = library.cold_costs()
        self._had_plan = True
        library.complete()  # the step's residual for info (the loop itself defers it to the preparation)
        info["step_residual"] = float(library.status().step_residual)
        return u, info

    def counters(self) -> dict[str, int]:
        """Calls, cold calls, fallbacks, preparations and refused states since the library's controller was made."""
        return self.library.counters()

    # ------------------------------------------------------------------ the plan, for studies and tests
    @property
    def plan(self) -> Plan | None:
        """The library's plan (after :meth:`prepare`: shifted and linearized for the next call); ``None`` before
        the first call."""
        if not self._had_plan:
            return None
        return Plan(*self.library.plan(), None, None)

    @property
    def qp_mu(self) -> float:
        """The last QP's final barrier parameter."""
        return float(self.library.status().qp_mu)

    def linearize(self, plan: Plan, kept: tuple[np.ndarray, np.ndarray] | None = None,
                  renewed: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        """The loop's linearization at ``plan`` (``rti_linearize_blocks`` of the library) with the reference,
        ``d̂`` and the model parameters in use: ``(H, H_N, g, g_N, AB, gaps, cost)``. ``kept``: Jacobians and
        their points to keep where ``renewed`` (per item, default: all renewed) is 0 and they did not move
        (``rti.relinearize_every``); what it ends with is left in ``last_jacobians``."""
        states = np.array(plan.states, dtype=float)
        if self._implicit:
            # Both ends of a stage on one sheet of S³, as the exported step continues q_k (the library's
            # linearization does the same before it calls the function).
            quaternions = states[:, self.layout.attitude(by="the implicit dynamics").quaternion]
            turns = np.einsum("ij,ij->i", quaternions[:-1], quaternions[1:])
            quaternions *= np.cumprod(np.concatenate([[1.0], np.where(turns < 0.0, -1.0, 1.0)]))[:, None]
            states[:, self.layout.attitude(by="the implicit dynamics").quaternion] = quaternions
        _, _, _, references = self._sample_reference()
        targets = self.reference_window()[1].T
        kept = self._nothing_kept if kept is None else kept
        renewed = self._all_fresh if renewed is None else renewed
        *linearization, jacobians, points = self.loop_function("rti_linearize_blocks")(
            states.T, np.asarray(plan.controls, dtype=float).T, references, self.disturbance, targets,
            self._parameters, *kept, renewed)
        self.last_jacobians = (np.array(jacobians, dtype=float), np.array(points, dtype=float))
        return tuple(np.array(out, dtype=float) for out in linearization)

    def plan_cost(self, plan: Plan | None = None) -> tuple[float, float]:
        """``(cost, largest gap)`` of ``plan`` (default: the library's current one) under the model — for tests
        and studies; the cost is the MPC's objective when the gaps are zero."""
        plan = self.plan if plan is None else plan
        if plan is None:
            raise ValueError("no plan yet: call the controller first")
        linearization = self.linearize(plan)
        return float(linearization[6]), float(np.max(np.abs(linearization[5])))

    def iterate(self, plan: Plan, x0: Any) -> Plan | None:
        """One SQP iteration from ``plan`` with ``δ_0`` fixed by the measured ``x0`` (the library's linearization
        and ``rti_feedback``): the updated plan, or ``None`` where the QP gave no finite step."""
        h, h_n, g, g_n, ab, gaps, _ = self.linearize(plan)
        states, controls, *_ = self.loop_function("rti_feedback")(
            np.asarray(plan.states, dtype=float).T, np.asarray(plan.controls, dtype=float).T,
            self.layout.check(x0), h, h_n, g, g_n, ab, gaps)
        states, controls = np.array(states, dtype=float).T, np.array(controls, dtype=float).T
        if not (np.all(np.isfinite(states)) and np.all(np.isfinite(controls))):
            return None
        return Plan(states, controls, None, None)
