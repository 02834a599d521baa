"""Nonlinear MPC over an exported step of any configuration space, solved to convergence by IPOPT.

``controller = MPC(model, settings, goal, torque_low, torque_high, rest)`` (or
:func:`fvin_mpc.control.scene.scene_mpc` for a scene), then ``u, info = controller(x)`` once
per control period, ``x`` the measured state (``(q, ω)`` on a pivot, ``(x, q, v, ω)`` for a free body).

The problem is :mod:`fvin_mpc.control.problem`'s, the one :class:`~fvin_mpc.control.rti.RealTimeMPC`
solves by real-time iterations (multiple shooting, ``N = settings.horizon`` steps of the model's ``h``):

* **decision variables** — states ``x_0 … x_N`` and controls ``u_0 … u_{N−1}``; ``x_0`` is fixed to
  the measured state through its bounds.
* **objective** — the sum of squares of the problem's stage and terminal residuals: the state against
  the reference (a goal orientation at rest, a hover point, or a time-varying reference:
  :meth:`set_reference`) with the sign-invariant orientation residual (``orientation_residual``:
  the projector, whose square ``1 − ⟨q, g⟩² = sin²(angle/2)`` is a convex quadratic, or the rotation
  vector, sound upside down), ``u − u_s`` with ``u_s = u_goal − d̂`` the torque that holds the goal in
  the model, and on a pivoted body the terminal energy deficit
  ``e(x) = (E(x) − E(q_goal, 0)) / |E(q_goal, 0) − E(q_rest, 0)|`` (the model's own energy, so the
  learned scale λ cancels): a horizon shorter than a swing-up cannot see the goal from near hanging,
  and without ``W_E`` the plan that defers pumping is as cheap as the one that pumps. Off in a bare
  :class:`MPCSettings` (``W_E = 0``); on in the settings a scene derives
  (:func:`fvin_mpc.control.scene.scene_mpc_settings`) unless its preset says otherwise.
* **dynamics** — ``x_{k+1} = F(x_k, u_k + d̂)``, ``F`` mapped over the horizon (one copy of the step's
  code however long the horizon), ``d̂`` the input-disturbance estimate (offset-free:
  :class:`~fvin_mpc.control.problem.DisturbanceEstimate`, on by default).
* **bounds** — ``u`` within the actuators' range (the torque reserve tightens the controls after the
  first); every ``ω`` component of ``x_1 … x_N`` within ``omega_bound_fraction / h``, inside the
  step's solvability limit ``h|ω| ≈ 1`` (``DESIGN.md``).

Speed comes from three choices, measured in ``docs/bench/solver.md``: the Gauss–Newton
Lagrangian Hessian (``2JᵀJ`` of the residuals; no second derivatives of the networks),
the NLP's functions compiled to C once and cached on disk
(:func:`fvin_mpc.control.model_export.compile_functions`), and a primal–dual warm start from the
previous plan shifted by one step.

The NLP solver is IPOPT by default; ``solver="sqpmethod"`` (CasADi's SQP with the qrqp
active-set QP solver) and ``solver="fatrop"`` (structure-exploiting interior point; exact
Hessian, stage-wise variable order, functions expanded and evaluated in CasADi's virtual
machine) solve the same problem, for the comparison in ``docs/bench/solver.md``.

Hanging at rest is a stationary point of the swing-up problem (mirror symmetry), so the
first guess is the model rolled out under a constant torque (``initial_torque_fraction``
of the upper bound). A non-finite solve never reaches the actuator. An unconverged one (its
iteration limit) is flown only when its last iterate is a model trajectory cheaper than the
previous plan shifted (``IpoptOptions.last_iterate_max_defect``); otherwise the controller
returns the previous plan shifted by one step, else zero, clipped to the bounds; ``info`` says which.
"""

from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import casadi as ca
import numpy as np

from fvin_mpc.control.model_export import CompileReport, ExportedModel, compile_functions
from fvin_mpc.control.problem import (
    ControlProblem,
    Plan,
    control_bounds,
    predict_function,
    residual_functions,
)
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.goals import GoalSet

NP = get_ops("numpy")

#: IPOPT return statuses accepted as a solution.
SUCCESS_STATUSES = frozenset({"Solve_Succeeded", "Solved_To_Acceptable_Level"})

#: First guesses a cold solve can start from: the model rolled out under ``+f·u_max`` or
#: ``−f·u_max`` (``f`` = ``initial_torque_fraction``), or ``"goal"``: the orientation slerped from
#: the measured one to the goal over the first third of the horizon, at rest, no torque (not a
#: model trajectory — the solver closes the gaps — but in the basin of "catch it").
COLD_STARTS: tuple[str, ...] = ("rollout+", "rollout-", "goal")


@dataclass(frozen=True)
class IpoptOptions:
    """How the solvers to convergence (``solver`` ``"ipopt"``, ``"sqpmethod"``, ``"fatrop"``; :class:`MPC`)
    solve the problem — not what the problem is (:class:`MPCSettings`).

    Attributes:
        hessian: ``"gauss-newton"`` (constant cost Hessian, default), ``"exact"`` (with the
            dynamics' second derivatives) or ``"limited-memory"`` (IPOPT's L-BFGS).
        warm_start: ``"primal-dual"`` (shifted plan and multipliers), ``"primal"`` (shifted
            plan only) or ``"none"`` (every solve from the rolled-out first guess).
        max_iter: iteration limit per warm-started solve (primal–dual warm start).
        cold_max_iter: limit for solves without multipliers — the first call, the call after
            a failure, and every call with ``warm_start`` ``"primal"``/``"none"``. A cold swing-up
            from rest may need over 100 iterations; with too tight a limit it fails, the zero
            fallback keeps the body at rest, and the next cold solve fails the same way.
        tol: convergence tolerance.
        warm_mu_init: IPOPT's initial barrier parameter on warm-started solves.
        extra: further IPOPT options as ``(name, value)`` pairs.
        last_iterate_max_defect: when a solve stops unconverged (its iteration limit), its last iterate is
            used (``info["fallback"] = "last-iterate"``) if its largest dynamics defect is at most this
            (state units; IPOPT's own ``constr_viol_tol`` by default) and its cost is below that of the
            previous plan shifted — the plan the controller would otherwise fly (acados returns the iterate
            at its limit with a status; the RTI always keeps its best plan). ``None``: never.
        exact_retry: with ``hessian="gauss-newton"`` and IPOPT, a solve that ends unconverged is solved again
            from the same guess (and multipliers) with the exact Hessian before any fallback
            (``info["hessian"]`` says which Hessian the returned solve used, ``iterations`` counts both). The
            Gauss–Newton Hessian leaves out the dynamics' curvature weighted by the multipliers; on a learned
            model whose potential curves several times more sharply than the body's, that term outweighs
            the cost's Hessian and Gauss–Newton's iterates cycle to the iteration limit (docs/training.md).
            The exact Hessian is compiled only when a retry first needs it. Once a retry converges, the
            controller solves with the exact Hessian from then on (:attr:`MPC.exact_hessian`): the model's
            curvature does not change, and each further Gauss–Newton attempt would spend its iteration limit
            first.
    """

    hessian: Literal["gauss-newton", "exact", "limited-memory"] = "gauss-newton"
    warm_start: Literal["primal-dual", "primal", "none"] = "primal-dual"
    max_iter: int = 100
    cold_max_iter: int = 500
    tol: float = 1e-6
    warm_mu_init: float = 1e-4
    extra: tuple[tuple[str, Any], ...] = field(default_factory=tuple)
    last_iterate_max_defect: float | None = 1e-4
    exact_retry: bool = True

    def __post_init__(self) -> None:
        if self.hessian not in ("gauss-newton", "exact", "limited-memory"):
            raise ValueError(f"unknown hessian {self.hessian!r}")
        if self.warm_start not in ("primal-dual", "primal", "none"):
            raise ValueError(f"unknown warm_start {self.warm_start!r}")
        if self.max_iter < 1 or self.cold_max_iter < 1:
            raise ValueError(f"max_iter and cold_max_iter must be >= 1, got {self.max_iter}, {self.cold_max_iter}")
        if self.last_iterate_max_defect is not None and not self.last_iterate_max_defect >= 0.0:
            raise ValueError(f"last_iterate_max_defect must be >= 0 or None, got {self.last_iterate_max_defect}")


@dataclass(frozen=True)
class RTIOptions:
    """How the real-time iteration (``solver="rti"``, :class:`fvin_mpc.control.rti.RealTimeMPC`) solves the
    problem.

    Attributes:
        max_iter: Gauss–Newton SQP iterations per warm call at most; the first always runs, each further
            one only while the call's time so far plus the last iteration's fits in ``budget_s``.
        budget_s: wall-clock budget of one warm call (s) for iterations after the first.
        tol: no further iteration once the last step is this small (largest ``|Δu|`` over the
            torque range, or state step over the trust region).
        cold_iter: iterations per cold-start guess on a cold call (after ``reset()``) …
        cold_budget_s: … within this wall-clock budget (s) over all guesses; when it runs out the
            best plan so far is used (``info["status"] = "budget"``).
        cold_solver: how a cold call gets its first plan: ``"rti"`` (budgeted Gauss–Newton iterations from
            the first guesses: the call stays within ``cold_budget_s``) or ``"ipopt"`` (the IPOPT MPC, with
            the settings' :class:`IpoptOptions`, solved to convergence once, multi-start as ``cold_starts``:
            a better first plan, but the first call takes as long as IPOPT needs — deadline misses at the
            start in latency-aware runs).
        regularization: Levenberg–Marquardt term added to the Gauss–Newton Hessian of the QP.
        omega_penalty: weight on the squared excess of each ``|ω_i|`` over its bound (the real-time
            iteration's soft form of the ``ω`` bound).
        qp_solver: ``"riccati"`` (a fixed number of interior-point iterations, each a Riccati recursion,
            generated and compiled with the linearization and the update on S³: one C call per iteration),
            ``"hpipm"`` (HPIPM through ``casadi.conic`` on the stage-wise sparse QP), ``"qrqp"`` or
            ``"osqp"`` (CasADi's, same QP).
        qp_iterations: interior-point iterations of ``qp_solver="riccati"``.
        qp_method: the interior-point method of ``qp_solver="riccati"``: ``"path"`` (path-following, a fixed
            centering of 0.1; one Riccati factorization and solve per iteration) or ``"mehrotra"`` (Mehrotra's
            predictor–corrector: one factorization and two solves per iteration, about 1.4× an iteration's
            time, and far more accurate per iteration: ``python -m benchmarks.qp_accuracy --methods path
            mehrotra``).
        riccati_stage: the backward stage of ``qp_method="path"``: ``"generated"`` (CasADi's straight-line
            code), ``"kernel"`` (hand-written C on the vector units, :mod:`fvin_mpc.control.riccati_kernel`; needs
            ``compile="cached"``) or ``"auto"`` (the kernel for free bodies, where it is 1.7–2.7× faster a
            stage, the generated stage for pivoted ones, where that is faster; the generated stage wherever the
            kernel cannot run: ``python -m benchmarks.riccati_stage``).
        stage_lanes: how a linearization maps its stages (the dynamics' gaps and Jacobians, the cost's
            Gauss–Newton model): ``"on"`` four stages at a time on the vector units (CasADi's C translated into
            vector code, :mod:`fvin_mpc.control.lane_kernel`; needs ``compile="cached"``, ``dynamics="unrolled"``
            and ``relinearize_every=1``), ``"off"`` CasADi's generated map, a stage at a time, or ``"auto"`` (lanes
            wherever they can run; the generated map otherwise, with a warning where a stage's code has an
            operation without a vector version).
        dynamics: the dynamics constraint: ``"unrolled"`` (the exported step ``x_{k+1} = F(x_k, u_k)``, K
            Newton iterations, linearized per stage) or ``"implicit"`` (the step's own equations between
            consecutive plan nodes, the learned terms evaluated once per node; pivoted bodies only;
            :mod:`fvin_mpc.control.implicit_dynamics`).
        feedback: what a warm call computes: ``"qp"`` (the QP at the measured state, ``max_iter``
            iterations) or ``"prepared"`` (the preparation solves the QP at the predicted state and the call
            applies its Riccati gains to the measured one: a forward pass; ``max_iter`` 1 and the Riccati QP;
            docs/c-controller.md).
        model_parameters: the model's run-time parameters (:mod:`fvin_mpc.core.model_parameters`: gain
            scales, physical values) are an input of the compiled functions, changed by
            :meth:`~fvin_mpc.control.rti.RealTimeMPC.set_parameters` without recompiling; ``False`` bakes
            them in as constants (what the parameters cost: docs/c-controller.md).
        restart_speed: a warm call whose measured ``ω`` differs from the plan's prediction of it by more
            than this (rad/s, in any component) starts cold instead — the multi-start guesses within
            ``cold_budget_s`` — and says so (``info["restarted"]``); ``inf`` never. A plan made before a
            knock kept the warm start after the body fell: on the damped pendulum the learned MPC then
            stayed at the bottom with its torque chattering in half the knocked episodes
            (docs/robustness.md). The scenes' defaults set it from their speed scale
            (:data:`~fvin_mpc.control.scene.RESTART_SPEED_FRACTION`).
        relinearize_every: a warm linearization computes the dynamics' derivatives (the most expensive part
            of a learned model's period) only for the first ``relinearize_head`` stages, every
            ``relinearize_every``-th, the last, and those whose node moved more than ``relinearize_tol`` since
            their derivatives were computed; it keeps the previous linearization's for the others, shifted with
            the plan (:func:`~fvin_mpc.control.linearization.relinearized`): none is older than
            ``relinearize_every − 1`` periods. The gaps, costs and their derivatives are new every time, so the
            iterations still close the gaps; what the kept derivatives cost is optimality, measured in
            docs/c-controller.md. The
            implicit dynamics keep their nodes' term slopes the same way. Cold calls and new model parameters
            renew all. ``1`` (default): every stage every time.
        relinearize_head: the leading stages renewed every time (see ``relinearize_every``).
        relinearize_tol: how far a node may move before its kept derivatives are renewed, as a fraction of the
            iteration's trust region (:func:`~fvin_mpc.control.linearization.step_limits`: a chart step of 0.5, about a
            radian of rotation; half the ``ω`` bound; …) or of the control range, whichever is reached first.
    """

    max_iter: int = 1
    budget_s: float = 0.0
    tol: float = 1e-3
    cold_iter: int = 10
    cold_budget_s: float = 0.02
    cold_solver: Literal["rti", "ipopt"] = "rti"
    regularization: float = 1e-6
    omega_penalty: float = 100.0
    qp_solver: Literal["riccati", "hpipm", "qrqp", "osqp"] = "riccati"
    qp_iterations: int = 10
    qp_method: Literal["path", "mehrotra"] = "path"
    riccati_stage: Literal["auto", "generated", "kernel"] = "auto"
    stage_lanes: Literal["auto", "on", "off"] = "auto"
    dynamics: Literal["unrolled", "implicit"] = "unrolled"
    model_parameters: bool = True
    feedback: Literal["qp", "prepared"] = "qp"
    restart_speed: float = math.inf
    relinearize_every: int = 1
    relinearize_head: int = 4
    relinearize_tol: float = 0.02

    def __post_init__(self) -> None:
        if not self.restart_speed > 0.0:
            raise ValueError(f"restart_speed must be > 0 (inf: never restart), got {self.restart_speed}")
        if self.max_iter < 1 or self.cold_iter < 1:
            raise ValueError(f"max_iter and cold_iter must be >= 1, got {self.max_iter}, {self.cold_iter}")
        if not (self.budget_s >= 0.0 and self.cold_budget_s >= 0.0 and self.regularization >= 0.0
                and self.omega_penalty >= 0.0):
            raise ValueError("budget_s, cold_budget_s, regularization and omega_penalty must be >= 0")
        if self.cold_solver not in ("rti", "ipopt"):
            raise ValueError(f"unknown cold_solver {self.cold_solver!r}")
        if self.qp_iterations < 1:
            raise ValueError(f"qp_iterations must be >= 1, got {self.qp_iterations}")
        if self.relinearize_every < 1 or self.relinearize_head < 0 or not self.relinearize_tol >= 0.0:
            raise ValueError(f"relinearize_every must be >= 1, relinearize_head and relinearize_tol >= 0, got "
                             f"{self.relinearize_every}, {self.relinearize_head}, {self.relinearize_tol}")
        if self.qp_solver not in ("riccati", "hpipm", "qrqp", "osqp"):
            raise ValueError(f"unknown qp_solver {self.qp_solver!r}")
        if self.qp_method not in ("path", "mehrotra"):
            raise ValueError(f"unknown qp_method {self.qp_method!r}; expected 'path' or 'mehrotra'")
        if self.riccati_stage not in ("auto", "generated", "kernel"):
            raise ValueError(f"unknown riccati_stage {self.riccati_stage!r}; expected 'auto', 'generated' or 'kernel'")
        if self.stage_lanes not in ("auto", "on", "off"):
            raise ValueError(f"unknown stage_lanes {self.stage_lanes!r}; expected 'auto', 'on' or 'off'")
        if self.dynamics not in ("unrolled", "implicit"):
            raise ValueError(f"unknown dynamics {self.dynamics!r}")
        if self.feedback not in ("qp", "prepared"):
            raise ValueError(f"unknown feedback {self.feedback!r}; expected 'qp' or 'prepared'")
        if self.feedback == "prepared" and (self.max_iter != 1 or self.qp_solver != "riccati"):
            raise ValueError("feedback='prepared' applies one prepared Riccati solve: it needs max_iter=1 and "
                             f"qp_solver='riccati', got max_iter={self.max_iter}, qp_solver={self.qp_solver!r}")


@dataclass(frozen=True)
class MPCSettings:
    """The control problem (:mod:`fvin_mpc.control.problem`) and which solver solves it, with each solver's
    own options nested (:class:`IpoptOptions`, :class:`RTIOptions`).

    Attributes:
        horizon: ``N`` model steps (horizon ``N·h`` seconds).
        orientation_weight: ``w_q`` on ``c(q) = sin²(angle/2)`` (``4`` ≈ angle² near the goal).
        omega_weight: ``w_ω`` on ``|ω|²``.
        control_weight: ``w_u`` on ``|u|²``, or one weight per control (``Σ w_i u_i²``).
        control_cost: what the control weight charges when the model's parameters are run-time inputs
            (:mod:`fvin_mpc.control.problem`): ``"effect"`` (default) the control's effect, ``effect ⊙ (u −
            u_s)`` with the parameters' gain scale over the mass ratio — an adapted heavier body plans the
            same motion as before; ``"command"`` the command in the actuator's units, whatever the
            parameters say. Equal with the exported model's own parameters. The RTI only (IPOPT has no
            run-time parameters).
        terminal_orientation_weight: ``W_q`` on ``c(q_N)``.
        terminal_omega_weight: ``W_ω`` on ``|ω_N|²``.
        terminal_energy_weight: ``W_E`` on the squared normalized energy deficit ``e(x_N)²``
            (module docstring); ``0`` leaves it out of the problem.
        omega_bound_fraction: bound ``|ω_i| ≤ fraction / h`` on predicted states; the step has
            no solution past ``h|ω| ≈ 1``.
        torque_reserve: fraction ``r`` of the torque range held back in the plan: the controls after
            the first are bounded to the middle ``(1 − r)`` of ``[torque_low, torque_high]``, the
            first (the one applied) keeps the whole range. A swing-up that is torque-limited to the
            top rides the bound; when the model predicts the climb a little too easily, the body
            falls short and takes one more swing (on the pendulum: +50–120 % on such a start).
            With a reserve the re-planned first control has torque left to correct it
            (constraint tightening, as in tube MPC; docs/data-efficiency.md measures what it fixes
            and what it does not). ``0`` (default) plans on the whole range. Both solvers.
        initial_torque_fraction: the rollout first guesses apply this fraction of the upper torque
            bound; must be non-zero to leave the symmetric rest state.
        solver: ``"ipopt"`` (default), ``"sqpmethod"`` (CasADi's SQP with qrqp; all three
            Hessians; the warm start passes the plan and, with ``"primal-dual"``, the
            multipliers), ``"fatrop"`` (needs ``ipopt.hessian="exact"`` and ``compile="none"``:
            it forms its own exact Hessian from the expanded functions) — all three :class:`MPC`, with
            :attr:`ipopt` — or ``"rti"`` (:class:`fvin_mpc.control.rti.RealTimeMPC`, with :attr:`rti`).
        cold_starts: first guesses of a cold solve (the first call after ``reset()``, or after a
            zero fallback), from :data:`COLD_STARTS`; with several, each is solved and the
            successful plan of lowest cost is kept (multi-start: a swing-up NLP has local optima —
            swing left or right first, catch the body near upright or let it fall through a turn —
            and a local solver converges to the one nearest its guess). Warm calls are unchanged.
            With ``solver="rti"`` each guess gets ``rti.cold_iter`` iterations and the best is kept.
        disturbance_gain: gain ``α`` of the offset-free estimator of a constant input disturbance ``d``
            (``x⁺ = F(x, u + d)``; :class:`~fvin_mpc.control.problem.DisturbanceEstimate`), both solvers;
            ``0`` switches it off. Default 0.1 (0.5 until 2026-11-27; the quadrotor's flight settings keep
            0.5): the estimate must be slower than the loop it serves. A torque that reaches the plant a
            period late makes the estimate's update ``(1 − α) d̂ + α (d + u_{k−1} − u_k)``, so within its
            bandwidth it cancels ``α`` of each new command and the plan answers with ``1/(1 − α)`` of it —
            twice the loop gain at 0.5: on ``pendulum_damped`` a one-period delay held both MPCs in a limit
            cycle at the hold tolerance's edge (the learned one past it, 4 % success), with 0.1 (and with 0)
            they hold within 0.003 rad (docs/robustness.md). A constant torque is still found, in about ten
            periods instead of two.
        disturbance_region_rad: … updated only within this angle of the reference attitude (rad) …
        disturbance_region_speed: … and while every ``|ω_i|`` is below this (rad/s). The pendulums'
            defaults: during a swing-up the torque changes fast, and the delay between measurement and
            actuation (which the one-step prediction does not know) reads as a large, sign-changing
            "disturbance" that feeds back through the plan; near the goal and slow the torque is nearly
            constant and the estimate is what it should be (docs/realtime.md).
        position_weight: a free body (``(x, q, v, ω)`` states): ``w_x`` on ``|x − x_ref|²`` per stage …
        velocity_weight: … ``w_v`` on ``|v − v_ref|²`` per stage …
        terminal_position_weight: … ``W_x`` on the last stage's …
        terminal_velocity_weight: … and ``W_v``. Pivoted bodies have no ``x``, ``v``: unused there.
        orientation_residual: the least-squares residual whose square is the orientation cost (both
            solvers): ``"projector"`` ``(I − g gᵀ) q`` (``|·|² = sin²(angle/2)``, a convex quadratic
            in q) or ``"rotation-vector"`` ``log(±g* ⊗ q)`` (half the rotation vector,
            ``|·|² = (angle/2)²``, the sign making the real part ≥ 0). Near the goal the two agree;
            far from it the projector's Gauss–Newton model has a false minimum at the upside-down
            orientation (its residual's Jacobian is orthogonal to the residual there: the model sees
            every turn as uphill), the rotation vector's does not — the quadrotor's recovery needs it.
        free_axis: a body-frame unit axis about which the goal is a set, not a point (``None``: the
            goal is one orientation): the orientation residual's and ``ω``'s components along it cost
            nothing. A ball joint whose actuators span two directions cannot act on the spin about
            the centre of mass's direction upright, and gravity is the same at every turn about it:
            penalizing that turn or spin made the plan trade tilt for it, holding the body 0.3–0.8 rad
            off upright (the two-motor ball scenes of ``fvin_mpc.envs.families``). Set by the scene's defaults
            (:func:`~fvin_mpc.control.scene.goal_symmetry_axis`).
        compile: ``"cached"`` compiles the solver's functions to C once (cached on disk); ``"none"``
            evaluates them in CasADi's virtual machine. Every solver.
        ipopt: the solvers to convergence's options (also the RTI's cold solve with ``rti.cold_solver="ipopt"``).
        rti: the real-time iteration's options.
    """

    horizon: int = 30
    orientation_weight: float = 4.0
    omega_weight: float = 0.1
    control_weight: float | tuple[float, ...] = 0.01
    control_cost: Literal["effect", "command"] = "effect"
    terminal_orientation_weight: float = 40.0
    terminal_omega_weight: float = 1.0
    terminal_energy_weight: float = 0.0
    omega_bound_fraction: float = 0.6
    torque_reserve: float = 0.0
    initial_torque_fraction: float = 0.5
    solver: Literal["ipopt", "sqpmethod", "fatrop", "rti"] = "ipopt"
    cold_starts: tuple[str, ...] = ("rollout+",)
    disturbance_gain: float = 0.1
    disturbance_region_rad: float = 0.5
    disturbance_region_speed: float = 1.0
    position_weight: float = 0.0
    velocity_weight: float = 0.0
    terminal_position_weight: float = 0.0
    terminal_velocity_weight: float = 0.0
    orientation_residual: Literal["projector", "rotation-vector"] = "projector"
    free_axis: tuple[float, float, float] | None = None
    compile: Literal["cached", "none"] = "cached"
    ipopt: IpoptOptions = field(default_factory=IpoptOptions)
    rti: RTIOptions = field(default_factory=RTIOptions)

    def __post_init__(self) -> None:
        if self.horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {self.horizon}")
        if not 0.0 < self.omega_bound_fraction <= 1.0:
            raise ValueError(f"omega_bound_fraction must be in (0, 1], got {self.omega_bound_fraction}")
        for name in ("orientation_weight", "omega_weight", "control_weight", "terminal_orientation_weight",
                     "terminal_omega_weight", "terminal_energy_weight", "position_weight", "velocity_weight",
                     "terminal_position_weight", "terminal_velocity_weight"):
            if not np.all(np.asarray(getattr(self, name)) >= 0.0):
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not 0.0 <= self.torque_reserve < 1.0:
            raise ValueError(f"torque_reserve must be in [0, 1), got {self.torque_reserve}")
        if self.solver not in ("ipopt", "sqpmethod", "fatrop", "rti"):
            raise ValueError(f"unknown solver {self.solver!r}")
        if not isinstance(self.ipopt, IpoptOptions) or not isinstance(self.rti, RTIOptions):
            raise ValueError("ipopt must be an IpoptOptions and rti an RTIOptions, "
                             f"got {type(self.ipopt).__name__} and {type(self.rti).__name__}")
        if self.control_cost not in ("effect", "command"):
            raise ValueError(f"unknown control_cost {self.control_cost!r}: 'effect' or 'command'")
        if self.orientation_residual not in ("projector", "rotation-vector"):
            raise ValueError(f"unknown orientation_residual {self.orientation_residual!r}")
        if self.free_axis is not None and (
                np.shape(self.free_axis) != (3,) or abs(float(np.linalg.norm(self.free_axis)) - 1.0) > 1e-9):
            raise ValueError(f"free_axis must be a unit 3-vector or None, got {self.free_axis!r}")
        if self.compile not in ("cached", "none"):
            raise ValueError(f"unknown compile mode {self.compile!r}")
        if not 0.0 <= self.disturbance_gain <= 1.0:
            raise ValueError(f"disturbance_gain must be in [0, 1], got {self.disturbance_gain}")
        if self.solver == "fatrop" and (self.ipopt.hessian != "exact" or self.compile != "none"):
            raise ValueError("solver='fatrop' forms its own exact Hessian from expanded functions: "
                             "use ipopt=IpoptOptions(hessian='exact') and compile='none'")
        if not self.cold_starts or any(start not in COLD_STARTS for start in self.cold_starts):
            raise ValueError(f"cold_starts must be a non-empty tuple from {COLD_STARTS}, got {self.cold_starts!r}")
        if self.initial_torque_fraction == 0.0:
            raise ValueError("initial_torque_fraction must be non-zero: rest is a stationary point")

    def updated(self, **fields: Any) -> MPCSettings:
        """These settings with ``fields`` changed: problem fields by name, and ``ipopt`` / ``rti`` either as
        an options object (replacing) or as a mapping of its fields (changing those only)."""
        for name, kind in (("ipopt", IpoptOptions), ("rti", RTIOptions)):
            if name in fields and not isinstance(fields[name], kind):
                fields[name] = replace(getattr(self, name), **dict(fields[name]))
        return replace(self, **fields)


class MPC(ControlProblem):
    """Receding-horizon controller over an :class:`~fvin_mpc.control.model_export.ExportedModel`, the problem
    solved to convergence (IPOPT, sqpmethod or fatrop); :class:`~fvin_mpc.control.rti.RealTimeMPC` is its sibling
    over the same :class:`~fvin_mpc.control.problem.ControlProblem`.

    Args:
        model, settings, goal, torque_low, torque_high, rest, goal_set: as
            :class:`~fvin_mpc.control.problem.ControlProblem` (``settings``: :class:`MPCSettings`).
        terminal_cost: optional CasADi Function ``x_N (n,) -> scalar`` added to the objective at
            the last stage (e.g. a value function: the cost of what follows the horizon). ``None``
            (default) leaves the problem as it is. Its exact Hessian is added to the Gauss–Newton
            one (it depends on ``x_N`` only: a small block). IPOPT and sqpmethod solvers only.
        cold_start_score: optional ``(states (N+1, n), controls (N, m)) -> float``: how a multi-start
            cold call ranks its successful plans (lowest wins), e.g. by an estimate of the whole
            task's cost; ``None`` (default) ranks them by the NLP's own cost, as before.

    Attributes:
        compile_report: how the compiled functions were obtained (``None`` if not compiled).
        build_s: seconds spent building (and compiling) the solver.
        exact_retries: unconverged Gauss–Newton solves retried with the exact Hessian (``IpoptOptions.exact_retry``).
        exact_hessian: whether this controller now solves with the exact Hessian (a retry converged).
    """

    def __init__(self, model: ExportedModel, settings: MPCSettings, goal: Any, torque_low: Any, torque_high: Any,
                 rest: Any = None, terminal_cost: ca.Function | None = None,
                 cold_start_score: Any = None, goal_set: GoalSet | None = None) -> None:
        if terminal_cost is not None:
            if terminal_cost.n_in() != 1 or terminal_cost.size_in(0) != (model.state_dim, 1) \
                    or terminal_cost.n_out() != 1 or terminal_cost.size_out(0) != (1, 1):
                raise ValueError(f"terminal_cost must map the state ({model.state_dim},) to a scalar, "
                                 f"got {terminal_cost}")
            if settings.solver not in ("ipopt", "sqpmethod"):
                raise ValueError(f"terminal_cost needs solver 'ipopt' or 'sqpmethod', got {settings.solver!r}")
        if settings.solver == "rti":
            raise ValueError("solver='rti' is solved by fvin_mpc.control.rti.RealTimeMPC, not MPC "
                             "(fvin_mpc.control.scene.scene_mpc picks the class from the settings)")
        self.terminal_cost = terminal_cost
        self.cold_start_score = cold_start_score
        super().__init__(model, settings, goal, torque_low, torque_high, rest, goal_set)

    def _unpack(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n, m = self.horizon, self.model.control_dim
        nx = self.model.state_dim
        split = nx * (n + 1)
        # CasADi vectorizes column-major: column k of X (state k) is contiguous.
        return w[:split].reshape(n + 1, nx), w[split:].reshape(n, m)

    @staticmethod
    def _pack(states: np.ndarray, controls: np.ndarray) -> np.ndarray:
        return np.concatenate([states.ravel(), controls.ravel()])

    # ------------------------------------------------------------------ problem
    def _build(self) -> None:
        s, n, m, nx, layout = self.settings, self.horizon, self.model.control_dim, self.model.state_dim, self.layout
        # The exact-Hessian retry's state (IpoptOptions.exact_retry), for every solver and compile mode;
        # exact_hessian is set once a retry converged where Gauss–Newton did not: the model's curvature does not change.
        self._exact_source, self.exact_retries, self.exact_hessian = None, 0, False
        self._exact_solvers: dict[bool, Any] | None = None
        states = ca.MX.sym("X", nx, n + 1)
        controls = ca.MX.sym("U", m, n)
        # Parameters: the reference over the horizon, the target controls u_s = u_goal − d̂, and d̂.
        references, targets, disturbance = ca.MX.sym("R", nx, n + 1), ca.MX.sym("U_s", m, n), ca.MX.sym("d", m)
        parameters = ca.vertcat(ca.vec(references), ca.vec(targets), disturbance)
        x_sym, u_sym = ca.SX.sym("x", nx), ca.SX.sym("u", m)
        next_state = ca.Function("next_state", [x_sym, u_sym], [self.model.step(x_sym, u_sym)[0]])
        predict = predict_function(self.model, "mpc_predict")

        # --- objective: the problem's residuals (control/problem.py), the ω bound hard (below)
        energy = None
        if s.terminal_energy_weight > 0:
            energy = (self.model.energy_function, self.model.energy(self.rest_state))
        stage, terminal = residual_functions(layout, s, m, self.omega_bound, None, energy)
        residuals = ca.vertcat(ca.vec(stage.map(n)(states[:, :n], controls, references[:, :n], targets)),
                               terminal(states[:, n], references[:, n]))
        objective = ca.sumsqr(residuals)
        # An optional terminal cost (constructor argument); its exact Hessian joins the Gauss–Newton one.
        terminal_term = None if self.terminal_cost is None else self.terminal_cost(states[:, n])
        if terminal_term is not None:
            objective = objective + terminal_term
        # --- dynamics, with the disturbance estimate on the input
        defects = next_state.map(n)(states[:, :n], controls + ca.repmat(disturbance, 1, n)) - states[:, 1:]
        decision = ca.vertcat(ca.vec(states), ca.vec(controls))
        nlp = {"x": decision, "p": parameters, "f": objective, "g": ca.vec(defects)}
        self._num_constraints = nx * n
        self._num_parameters = parameters.shape[0]

        # --- bounds (x_0 is fixed per call)
        lower = np.full(decision.shape[0], -np.inf)
        upper = np.full(decision.shape[0], np.inf)
        state_lower, control_lower = self._unpack(lower)
        state_upper, control_upper = self._unpack(upper)
        rates = layout.angular_rates
        state_lower[1:, rates], state_upper[1:, rates] = -self.omega_bound, self.omega_bound
        control_lower[:], control_upper[:] = control_bounds(self.torque_low, self.torque_high, n, s.torque_reserve)
        self._lower, self._upper = lower, upper

        self.compile_report: CompileReport | None = None
        self._order = None
        self._exact_source = None
        if s.solver == "fatrop":
            self._predict = predict
            self._build_fatrop(states, controls, parameters, objective, defects)
            return
        options: dict[str, Any] = {}
        if s.ipopt.hessian == "gauss-newton":
            lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", self._num_constraints)
            residual_jacobian = ca.jacobian(residuals, decision)
            cost_hessian = 2.0 * ca.mtimes(residual_jacobian.T, residual_jacobian)
            if terminal_term is not None:
                cost_hessian = cost_hessian + ca.hessian(terminal_term, decision)[0]
            # IPOPT reads the upper triangle, sqpmethod the whole symmetric matrix.
            hessian, label = (ca.triu(lam_f * cost_hessian), "triu_hess_gamma_x_x") if s.solver == "ipopt" \
                else (lam_f * cost_hessian, "hess_gamma_x_x")
            options["hess_lag"] = ca.Function("nlp_hess_l", [decision, parameters, lam_f, lam_g], [hessian],
                                              ["x", "p", "lam_f", "lam_g"], [label])
        symbolic = ca.nlpsol("mpc_symbolic", s.solver, nlp, {**options, **self._ipopt_options(warm=False)})
        if s.compile == "none":
            self._nlp = nlp
            self._oracle_options = options
            self._predict = predict
        else:
            names = ["nlp_f", "nlp_g", "nlp_grad_f", "nlp_jac_g"] if s.solver == "ipopt" else ["nlp_fg", "nlp_jac_fg"]
            if s.ipopt.hessian != "limited-memory":
                names.append("nlp_hess_l")
            oracles = [symbolic.get_function(name) for name in names]
            if s.ipopt.hessian == "gauss-newton":
                oracles[-1] = options["hess_lag"]
            oracles.append(predict)
            # IPOPT's interface insists on being able to differentiate f and g (for lam_p, which
            # calc_lam_p=False never computes); finite differences satisfy it and are never run.
            compiled, self.compile_report = compile_functions(
                oracles, prefix=re.sub(r"[^0-9A-Za-z_]", "_", f"mpc_{self.model.name}"),
                external_options={"enable_fd": True})
            self._predict = compiled["mpc_predict"]
            x, p = ca.MX.sym("x", decision.shape[0]), ca.MX.sym("p", self._num_parameters)
            if s.solver == "ipopt":
                f, g = compiled["nlp_f"](x, p), compiled["nlp_g"](x, p)
            else:
                f, g = compiled["nlp_fg"](x, p)
            self._nlp = {"x": x, "p": p, "f": f, "g": g}
            self._oracle_options = {"grad_f": compiled["nlp_grad_f"], "jac_g": compiled["nlp_jac_g"]} \
                if s.solver == "ipopt" else {"jac_fg": compiled["nlp_jac_fg"]}
            if "nlp_hess_l" in compiled:
                self._oracle_options["hess_lag"] = compiled["nlp_hess_l"]
        self._cold = ca.nlpsol("mpc_cold", s.solver, self._nlp,
                               {**self._oracle_options, **self._ipopt_options(warm=False)})
        self._cost_and_defects = self._cost_and_defects_function()
        warm = s.ipopt.warm_start == "primal-dual" and s.solver == "ipopt"
        self._warm = self._cold if not warm else ca.nlpsol(
            "mpc_warm", s.solver, self._nlp, {**self._oracle_options, **self._ipopt_options(warm=warm)})
        # The exact-Hessian solvers an unconverged Gauss–Newton solve retries with, built on first need.
        self._exact_source = nlp if s.solver == "ipopt" and s.ipopt.hessian == "gauss-newton" and s.ipopt.exact_retry \
            else None

    def _exact_solver(self, warm: bool) -> Any:
        """The IPOPT solver with the exact Lagrangian Hessian (the dynamics' second derivatives weighted by
        the multipliers, which the Gauss–Newton Hessian leaves out), ``warm`` or cold; its Hessian is
        generated and compiled the first time a retry needs it, so a model that never needs one never
        pays for it."""
        if self._exact_solvers is None:
            s = self.settings
            oracles = {key: value for key, value in self._oracle_options.items() if key != "hess_lag"}
            if s.compile != "none":
                symbolic = ca.nlpsol("mpc_exact_symbolic", "ipopt", self._exact_source, self._ipopt_options(warm=False))
                compiled, _ = compile_functions(
                    [symbolic.get_function("nlp_hess_l")],
                    prefix=re.sub(r"[^0-9A-Za-z_]", "_", f"mpc_{self.model.name}_exact_hessian"),
                    external_options={"enable_fd": True})
                oracles["hess_lag"] = compiled["nlp_hess_l"]
            self._exact_solvers = {
                kind: ca.nlpsol(f"mpc_exact_{'warm' if kind else 'cold'}", "ipopt", self._nlp,
                                {**oracles, **self._ipopt_options(warm=kind)}) for kind in (False, True)}
        return self._exact_solvers[warm]

    def _build_fatrop(self, states: ca.MX, controls: ca.MX, parameters: ca.MX, objective: ca.MX,
                      defects: ca.MX) -> None:
        """The same NLP for fatrop: variables stage by stage ``(x_0, u_0, x_1, …, x_N)`` and the
        dynamics as gap-closing constraints ``x_{k+1} − F(x_k, u_k) = 0``, the form its structure
        detection requires. ``self._order`` maps the stage-wise vector to the default layout."""
        n, m, nx = self.horizon, self.model.control_dim, self.model.state_dim
        problem = ca.Function("mpc_problem", [states, controls, parameters], [objective, -ca.vec(defects)])
        index = np.arange(nx * (n + 1) + m * n)
        state_index, control_index = self._unpack(index)
        order = np.concatenate([np.concatenate([state_index[k], control_index[k]]) if k < n else state_index[k]
                                for k in range(n + 1)])
        self._order = order  # stage-wise vector v = w[order]
        v, p = ca.MX.sym("v", order.size), ca.MX.sym("p", self._num_parameters)
        w = v[np.argsort(order).tolist()]  # default layout from the stage-wise one
        w_states, w_controls = ca.reshape(w[: nx * (n + 1)], nx, n + 1), ca.reshape(w[nx * (n + 1):], m, n)
        f, g = problem(w_states, w_controls, p)
        self._nlp = {"x": v, "p": p, "f": f, "g": g}
        self._oracle_options = {}
        options = {"structure_detection": "auto", "equality": [True] * self._num_constraints, "expand": True,
                   "fatrop": {"print_level": 0, "max_iter": self.settings.ipopt.max_iter,
                              "tol": self.settings.ipopt.tol},
                   "print_time": False, "error_on_fail": False}
        self._cold = self._warm = ca.nlpsol("mpc_fatrop", "fatrop", self._nlp, options)
        self._cost_and_defects = self._cost_and_defects_function()

    def _cost_and_defects_function(self) -> ca.Function:
        """The objective and the dynamics defects in the solver's own variable order: what an unconverged
        last iterate is judged by against the shifted previous plan."""
        return ca.Function("mpc_cost_defects", [self._nlp["x"], self._nlp["p"]], [self._nlp["f"], self._nlp["g"]])

    def _ipopt_options(self, warm: bool) -> dict[str, Any]:
        o = self.settings.ipopt
        if self.settings.solver == "sqpmethod":
            quiet = {"print_iter": False, "print_header": False, "error_on_fail": False}
            return {"qpsol": "qrqp", "qpsol_options": quiet,
                    "hessian_approximation": "limited-memory" if o.hessian == "limited-memory" else "exact",
                    "max_iter": o.max_iter, "tol_pr": o.tol, "tol_du": o.tol, "print_header": False,
                    "print_iteration": False, "print_status": False, "print_time": False, "error_on_fail": False,
                    "calc_lam_p": False}
        ipopt: dict[str, Any] = {"print_level": 0, "sb": "yes", "max_iter": o.max_iter if warm else o.cold_max_iter,
                                 "tol": o.tol, "linear_solver": "mumps"}
        if o.hessian == "limited-memory":
            ipopt["hessian_approximation"] = "limited-memory"
        if warm:
            ipopt.update({"warm_start_init_point": "yes", "mu_init": o.warm_mu_init,
                          "warm_start_bound_push": 1e-8, "warm_start_mult_bound_push": 1e-8,
                          "warm_start_slack_bound_push": 1e-8})
        ipopt.update(dict(o.extra))
        # lam_p is never used; computing it would need derivatives of the compiled functions.
        return {"ipopt": ipopt, "print_time": False, "error_on_fail": False, "calc_lam_p": False}

    def _shifted(self, plan: Plan, x0: np.ndarray) -> Plan:
        """``plan`` advanced one step: drop the first stage, repeat the last."""
        states = np.vstack([plan.states[1:], plan.states[-1:]])
        states[0] = x0
        controls = np.vstack([plan.controls[1:], plan.controls[-1:]])
        lam_g = lam_x = None
        if plan.lam_g is not None and plan.lam_x is not None:
            m = self.model.control_dim
            defects = plan.lam_g.reshape(self.horizon, self.model.state_dim)
            lam_g = np.vstack([defects[1:], defects[-1:]]).ravel()
            state_mult, control_mult = self._unpack(plan.lam_x)
            lam_x = self._pack(np.vstack([state_mult[1:], state_mult[-1:]]),
                               np.vstack([control_mult[1:], control_mult[-1:]]).reshape(-1, m))
        return Plan(states, controls, lam_g, lam_x)

    # ------------------------------------------------------------------ control
    def __call__(self, x: Any) -> tuple[np.ndarray, dict[str, Any]]:
        """Plan from the measured state ``x (n,)`` (``(q, ω)`` on a pivot); returns ``(u (m,), info)``.

        ``info``: ``status`` (the solver's), ``success``, ``iterations``, ``solve_time_s`` (summed
        over the cold starts of a multi-start call), ``fallback`` (``None``, ``"last-iterate"``
        (unconverged, its last iterate flown: ``last_iterate_max_defect``), ``"previous-plan"`` or
        ``"zero"``), ``cost``, ``step_residual`` (the model's Newton residual for the applied first
        step, rad/s), ``disturbance`` (``d̂``), ``states`` ``(N+1, n)`` and ``controls`` ``(N, m)`` of the
        plan; on cold calls also ``cold_start`` (the first guess that won) and ``cold_costs`` (guess →
        cost, ``nan`` if that solve failed).

        Raises:
            ValueError: non-finite or wrongly shaped state, or ``q`` not of unit norm.
        """
        x0 = self.layout.check(x)
        self._update_estimate(x0)
        u, info = self._plan_and_control(x0)
        info["step_residual"] = self._predicted(x0, u)
        info["disturbance"] = self.disturbance.copy()
        return u, info

    def _plan_and_control(self, x0: np.ndarray) -> tuple[np.ndarray, dict[str, Any]]:
        """A warm solve from the shifted previous plan, or the multi-start cold solves."""
        if self._previous is not None and self.settings.ipopt.warm_start != "none":
            return self._solve(x0, self._shifted(self._previous, x0), warm=True)
        best: tuple[np.ndarray, dict[str, Any], Plan | None] | None = None
        costs: dict[str, float] = {}
        total_time = 0.0
        earlier_plan = self._previous  # what a failed solve falls back to (kept with warm_start="none")
        score = self.cold_start_score
        best_rank: tuple[bool, float] = (True, np.inf)
        for start in self.settings.cold_starts:
            self._previous = earlier_plan
            u, info = self._solve(x0, self._first_guess(x0, start), warm=False)
            total_time += info["solve_time_s"]
            usable = info["success"] or info["fallback"] == "last-iterate"
            costs[start] = info["cost"] if usable else float("nan")
            if usable:  # a converged plan beats any last iterate
                rank = (not info["success"],
                        info["cost"] if score is None else float(score(info["states"], info["controls"])))
                if best is None or rank < best_rank:
                    best, best_rank = (u, {**info, "cold_start": start}, self._previous), rank
        if best is None:  # every cold start failed: the last one's fallback stands
            return u, {**info, "solve_time_s": total_time, "cold_start": None, "cold_costs": costs}
        u, info, self._previous = best
        return u, {**info, "solve_time_s": total_time, "cold_costs": costs}

    def _solve(self, x0: np.ndarray, guess: Plan, warm: bool) -> tuple[np.ndarray, dict[str, Any]]:
        """One NLP solve from ``guess``; keeps the plan (or falls back) and returns the control."""
        lower, upper = self._lower.copy(), self._upper.copy()
        lower[:x0.size] = upper[:x0.size] = x0
        references, targets = self.reference_window()
        parameters = np.concatenate([references.ravel(), targets.ravel(), self.disturbance])
        arguments: dict[str, Any] = {"x0": self._pack(guess.states, guess.controls), "p": parameters,
                                     "lbx": lower, "ubx": upper, "lbg": 0.0, "ubg": 0.0}
        use_duals = warm and self.settings.ipopt.warm_start == "primal-dual" and guess.lam_g is not None
        if use_duals:
            arguments.update(lam_g0=guess.lam_g, lam_x0=guess.lam_x)
        solver = self._warm if use_duals else self._cold
        if self._order is not None:  # fatrop: stage-wise order, negated constraints
            arguments = {**arguments, **{key: arguments[key][self._order] for key in ("x0", "lbx", "ubx", "lam_x0")
                                         if key in arguments}}
            if "lam_g0" in arguments:
                arguments["lam_g0"] = -arguments["lam_g0"]
        start = time.perf_counter()
        hessian = self.settings.ipopt.hessian
        if self.exact_hessian:
            solver, hessian = self._exact_solver(use_duals), "exact"
        solution = solver(**arguments)
        stats = solver.stats()
        iterations = int(stats.get("iter_count", -1))
        if self._exact_source is not None and not self.exact_hessian \
                and str(stats.get("return_status")) not in SUCCESS_STATUSES:
            # Where the dynamics curve sharply (a learned potential whose U'' is several times the body's) the
            # multiplier-weighted curvature that Gauss–Newton leaves out outweighs the cost's Hessian and its
            # iterates cycle; Newton's method with the exact Lagrangian Hessian converges from the same guess.
            solver = self._exact_solver(use_duals)
            solution = solver(**arguments)
            stats = solver.stats()
            iterations += int(stats.get("iter_count", -1))
            hessian = "exact"
            self.exact_retries += 1
            self.exact_hessian = str(stats.get("return_status")) in SUCCESS_STATUSES
        solve_time = time.perf_counter() - start
        solver_x = np.asarray(solution["x"], dtype=float).ravel()  # in the solver's order, for _last_iterate_wins
        if self._order is not None:
            solution = dict(solution)
            for key in ("x", "lam_x"):
                stage_wise = np.asarray(solution[key], dtype=float).ravel()
                solution[key] = np.empty_like(stage_wise)
                solution[key][self._order] = stage_wise
            solution["lam_g"] = -np.asarray(solution["lam_g"], dtype=float)
        status = str(stats.get("return_status", "unknown"))
        w = np.asarray(solution["x"], dtype=float).ravel()
        finite = bool(np.all(np.isfinite(w)))
        converged = status in SUCCESS_STATUSES if self.settings.solver == "ipopt" else bool(stats.get("success", False))
        success = converged and finite
        fallback = None
        last_iterate = not success and finite and self._last_iterate_wins(solver_x, arguments["p"], x0)
        if success or last_iterate:
            states, controls = self._unpack(w)
            self._previous = Plan(states, controls, np.asarray(solution["lam_g"], float).ravel(),
                                   np.asarray(solution["lam_x"], float).ravel())
            u = controls[0].copy()
            fallback = "last-iterate" if last_iterate else None
        elif self._previous is not None and np.all(np.isfinite(self._previous.controls)):
            # The plan made one period ago, advanced by one step: its second control is for now.
            self._previous = self._shifted(self._previous, x0)
            states, controls = self._previous.states, self._previous.controls
            u, fallback = controls[0].copy(), "previous-plan"
        else:
            self._previous = None
            states, controls = guess.states, guess.controls
            u, fallback = np.zeros(self.model.control_dim), "zero"
        u = np.clip(u, self.torque_low, self.torque_high)
        info = {
            "status": status, "success": success, "iterations": iterations, "hessian": hessian,
            "solve_time_s": solve_time, "fallback": fallback,
            "cost": float(solution["f"]) if success or last_iterate else float("nan"),
            "states": states, "controls": controls,
        }
        return u, info

    def _last_iterate_wins(self, iterate: np.ndarray, parameters: np.ndarray, x0: np.ndarray) -> bool:
        """Whether an unconverged solve's last ``iterate`` (solver order) is flown: its dynamics defects
        within ``last_iterate_max_defect`` and its cost below the shifted previous plan's (any cost when
        there is none: the alternative is the zero torque)."""
        tolerance = self.settings.ipopt.last_iterate_max_defect
        if tolerance is None:
            return False
        cost, defects = (np.asarray(value, dtype=float).ravel()
                         for value in self._cost_and_defects(iterate, parameters))
        if not (np.all(np.isfinite(defects)) and np.max(np.abs(defects), initial=0.0) <= tolerance):
            return False
        if self._previous is None or not np.all(np.isfinite(self._previous.controls)):
            return True
        shifted = self._shifted(self._previous, x0)
        packed = self._pack(shifted.states, shifted.controls)
        if self._order is not None:
            packed = packed[self._order]
        shifted_cost = float(np.asarray(self._cost_and_defects(packed, parameters)[0]).ravel()[0])
        return bool(cost[0] <= shifted_cost)
