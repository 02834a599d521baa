"""The control problem both solvers solve: its cost as least-squares residuals, written once.

:class:`~fvin_mpc.control.mpc.MPC` (IPOPT, sqpmethod or fatrop, to convergence) and
:class:`~fvin_mpc.control.rti.RealTimeMPC` (one Gauss–Newton iteration per period, as acados'
SQP-RTI) solve the same problem — acados' shape: one problem, the solver an option. Every cost
term is a sum of squares ``|r|²`` of a residual ``r``, so both use the Gauss–Newton Hessian ``2JᵀJ``:

* **stage** ``r(x, u, x_ref, u_s)`` — position and velocity against the reference (free bodies),
  the orientation against the reference's (``orientation_residual``: the projector ``(I − g gᵀ) q``,
  ``|·|² = sin²(angle/2)``, or half the rotation vector of the sign-aligned relative rotation,
  ``|·|² = (angle/2)²``; both the same for ``±q`` and ``±g``), ``ω`` against the reference's, and
  ``u − u_s``: the control is measured from the torque that holds the reference in the model
  corrected by the disturbance estimate (``u_s = u_goal − d̂``, :class:`DisturbanceEstimate`) and, with
  the model's parameters as run-time inputs, charged by its effect (``control_cost="effect"``, the
  default): ``effect ⊙ (u − u_s)``, each control's acceleration per unit against the exported model's
  (gain scale over mass ratio). A craft 1.5× as heavy then plans the unchanged craft's motion on 1.5× the
  thrust at the same cost — charged in newtons it pays 1.5² for the same motion and lags
  (docs/adaptation.md measures both);
* **terminal** ``r_N(x, x_ref)`` — the same tracking terms with the terminal weights and, on a pivoted
  body, the normalized energy deficit ``(E(x) − E(g, 0)) / |E(g, 0) − E(rest, 0)|`` (the model's own
  energy: the learned scale cancels);
* **the ω bound** ``|ω_i| ≤ omega_bound`` — IPOPT takes it as a hard bound on the plan's states; the
  real-time iteration as a stiff penalty on its excess, a residual appended to both (a hard bound made
  its linearized QP infeasible from spinning first guesses);
* **torque bounds** with the **torque reserve** (:func:`control_bounds`): the controls after the first
  are planned within the middle ``1 − r`` of the range (constraint tightening), the applied first keeps
  the whole range.

The dynamics ``x_{k+1} = F(x_k, u_k + d̂)`` carry the same input-disturbance estimate in both.

:class:`ControlProblem` is what the two controllers share of it (they are its subclasses, siblings): the goal,
the reference over the horizon, the bounds, the disturbance estimate, the control that holds the goal and the
first guesses.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Protocol

import casadi as ca
import numpy as np

from fvin_mpc.control.model_export import GENERATED_SX_OPTIONS
from fvin_mpc.core import s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.blocks import Ball, BlockSlots, FreeJoint, Hinge, Slide, single_attitude
from fvin_mpc.core.goals import UPRIGHT, GoalSet, default_goal_set
from fvin_mpc.core.space import StateLayout
from fvin_mpc.core.state import unit_quaternion

CA, NP = get_ops("casadi"), get_ops("numpy")


def orientation_error(q: Any, goal: Any, kind: str, free_axis: Any = None) -> Any:
    """The orientation residual of ``q`` against ``goal`` (CasADi columns of 4): ``"projector"``
    ``(I − g gᵀ) q`` or ``"rotation-vector"`` ``log(±g* ⊗ q)`` (the sign making the real part ≥ 0).

    Near the goal the two agree; far from it the projector's Gauss–Newton model has a false minimum
    at the upside-down orientation (its residual's Jacobian is orthogonal to the residual there), the
    rotation vector's does not.

    With ``free_axis`` (a body-frame unit ``n``, :attr:`MPCSettings.free_axis`) both are taken in
    the goal's body frame, ``g* ⊗ q``, and lose their component along ``n``: the projector's becomes
    ``(I − n nᵀ) vec(g* ⊗ q)`` (the same square, ``1 − (g·q)²``, less the turn about ``n``), the
    rotation vector's ``(I − n nᵀ) log(±g* ⊗ q)``; any turn about ``n`` from the goal costs nothing."""
    if free_axis is None and kind == "projector":
        return ca.mtimes(ca.SX.eye(4) - ca.mtimes(goal, goal.T), q)
    relative = s3.multiply(s3.conjugate(tuple(goal[i] for i in range(4))), tuple(q[i] for i in range(4)))
    if kind == "projector":
        error = ca.vertcat(*relative[1:])
    else:
        aligned = s3.scale(ca.if_else(relative[0] >= 0, 1.0, -1.0), relative)
        error = ca.vertcat(*s3.log(aligned, CA))
    if free_axis is None:
        return error
    return ca.mtimes(ca.DM(free_axis_projector(free_axis)), error)


def free_axis_projector(free_axis: Any) -> np.ndarray:
    """``I − n nᵀ`` for the unit ``n`` (:attr:`MPCSettings.free_axis`)."""
    n = np.asarray(free_axis, dtype=float).reshape(3)
    return np.eye(3) - np.outer(n, n)


def _position_errors(slot: BlockSlots, x: Any, reference: Any, settings: Any) -> list[tuple[str, Any]]:
    """A block's configuration residuals against the reference, each with its unit (which weight it takes): a
    slide's offset, a hinge's ``2 sin(Δθ/2)`` (wrap-free), an attitude's :func:`orientation_error`."""
    block, part, goal = slot.block, x[slot.position], reference[slot.position]
    if isinstance(block, Slide):
        return [("position", part - goal)]
    if isinstance(block, Hinge):
        return [("angle", 2.0 * ca.sin(0.5 * (part - goal)))]
    if isinstance(block, Ball):
        return [("angle", orientation_error(part, goal, settings.orientation_residual, settings.free_axis))]
    if isinstance(block, FreeJoint):
        return [("position", part[:3] - goal[:3]),
                ("angle", orientation_error(part[3:], goal[3:], settings.orientation_residual, settings.free_axis))]
    raise ValueError(f"the control problem has no cost for a {block.kind} block")


def _rate_errors(slot: BlockSlots, x: Any, reference: Any, free_axis: Any) -> list[tuple[str, Any]]:
    """A block's rate residuals against the reference, by unit; an attitude's spin about a free axis costs
    nothing (a body rate ``ω`` is in the body frame, as the axis is)."""
    units = ["angular rate" if angular else "velocity" for angular in slot.block.angular_rates]
    errors = []
    for start in range(len(units)):
        if start and units[start] == units[start - 1]:
            continue
        stop = next((i for i in range(start, len(units)) if units[i] != units[start]), len(units))
        rows = slice(slot.rate.start + start, slot.rate.start + stop)
        error = x[rows] - reference[rows]
        if free_axis is not None and slot.quaternion is not None and units[start] == "angular rate":
            error = ca.mtimes(ca.DM(free_axis_projector(free_axis)), error)
        errors.append((units[start], error))
    return errors


def residual_functions(layout: StateLayout, settings: Any, control_dim: int, omega_bound: float,
                       omega_penalty: float | None, energy: tuple[ca.Function, Any] | None, parameter_size: int = 0,
                       control_effect: Callable[[Any], Any] | None = None) -> tuple[ca.Function, ca.Function]:
    """``(stage, terminal)``: ``stage(x, u, x_ref, u_s) → r`` and ``terminal(x, x_ref) → r_N`` as SX
    functions (module docstring).

    Args:
        layout: the states' blocks (each block's residuals: :func:`_position_errors`, :func:`_rate_errors`).
        settings: the :class:`~fvin_mpc.control.mpc.MPCSettings` (weights, ``orientation_residual``).
        control_dim: ``m``.
        omega_bound: the bound on each ``|ω_i|``.
        omega_penalty: weight of the squared excess of ``|ω_i|`` over the bound, appended to both
            residuals; ``None`` leaves it out (a solver that bounds ``ω`` hard).
        energy: ``(E, E(rest, 0))`` for the terminal energy deficit (a pivoted body's ``E`` on its
            states); ``None`` leaves it out. With ``parameter_size``: ``(E(x, p), the rest state)``.
        parameter_size: ``> 0``: both residuals take the model parameters, ``stage(x, u, x_ref, u_s, p)`` and
            ``terminal(x, x_ref, p)``; the energies (the rest's too) are the parametrized model's.
        control_effect: with ``parameter_size`` and ``settings.control_cost == "effect"``, ``p ↦`` each
            control's effect relative to the exported model's
            (:meth:`~fvin_mpc.core.model_parameters.ModelParameters.control_effect`): the control residual
            becomes ``√w_u ⊙ effect ⊙ (u − u_s)``.
    """
    s = settings
    x, reference = ca.SX.sym("x", layout.state_dim), ca.SX.sym("x_ref", layout.state_dim)
    u, u_s = ca.SX.sym("u", control_dim), ca.SX.sym("u_s", control_dim)
    if s.free_axis is not None:
        layout.attitude(by="a free axis (MPCSettings.free_axis)")
    errors = [_position_errors(slot, x, reference, s) for slot in layout.slots]
    rate_errors = [_rate_errors(slot, x, reference, s.free_axis) for slot in layout.slots]
    rates = x[layout.angular_rates]
    excess = [] if omega_penalty is None else [
        np.sqrt(omega_penalty) * (rates - ca.fmin(ca.fmax(rates, -omega_bound), omega_bound))]

    def tracking(position_weight: float, orientation_weight: float, velocity_weight: float,
                 omega_weight: float) -> list[Any]:
        weights = {"position": position_weight, "angle": orientation_weight, "velocity": velocity_weight,
                   "angular rate": omega_weight}
        return [np.sqrt(weights[unit]) * error for block in (*errors, *rate_errors) for unit, error in block]

    p = ca.SX.sym("p", parameter_size)
    control_weights = np.broadcast_to(np.asarray(s.control_weight, dtype=float), (control_dim,))
    control_residual = ca.DM(np.sqrt(control_weights)) * (u - u_s)
    if parameter_size and control_effect is not None and getattr(s, "control_cost", "command") == "effect":
        control_residual = control_residual * control_effect(p)
    stage = ca.vertcat(*tracking(s.position_weight, s.orientation_weight, s.velocity_weight, s.omega_weight),
                       control_residual, *excess)
    terminal = [*tracking(s.terminal_position_weight, s.terminal_orientation_weight, s.terminal_velocity_weight,
                          s.terminal_omega_weight), *excess]
    if energy is not None:
        energy_function, rest_energy = energy
        if parameter_size:
            parametric_energy, rest_state = energy_function, ca.DM(rest_energy)

            def energy_function(state: Any) -> Any:
                return parametric_energy(state, p)

            rest_energy = energy_function(rest_state)
        at_rest = ca.vertcat(reference[layout.positions], ca.DM.zeros(layout.rates.stop - layout.rates.start))
        goal_energy = energy_function(at_rest)
        terminal.append(np.sqrt(s.terminal_energy_weight) * (energy_function(x) - goal_energy)
                        / ca.fabs(goal_energy - rest_energy))
    stage_inputs = [x, u, reference, u_s, p] if parameter_size else [x, u, reference, u_s]
    return (ca.Function("stage_residual", stage_inputs, [stage], ["x", "u", "x_ref", "u_s", "p"][:len(stage_inputs)],
                        ["r"]),
            ca.Function("terminal_residual", [x, reference, p] if parameter_size else [x, reference],
                        [ca.vertcat(*terminal)], ["x", "x_ref", "p"][:3 if parameter_size else 2], ["r"]))


def predict_function(model: Any, name: str = "predict", parameters: str = "none") -> ca.Function:
    """``(x, u) → (x⁺, B, residual, B⁺)``: one step of ``model``, the derivative ``B = ∂rates⁺/∂u`` of its
    rates (``ω``, or ``v`` and ``ω``) and its least-squares inverse — for the disturbance estimate and
    the control that holds the goal — and the step's Newton residual.

    ``parameters``: ``"none"`` (those inputs), ``"input"`` (a third input ``p``, the model parameters:
    :attr:`~fvin_mpc.control.model_export.ExportedModel.parametric_step`) or ``"constant"`` (the input
    ``p`` is there and unused: the constant step behind the same interface)."""
    layout = model.space.layout
    x, u = ca.SX.sym("x", layout.state_dim), ca.SX.sym("u", model.control_dim)
    inputs = [x, u]
    if parameters == "input":
        p = ca.SX.sym("p", model.model_parameters.size)
        stepped, residual = model.parametric_step(x, u, p)
        inputs.append(p)
    else:
        stepped, residual = model.step(x, u)
        if parameters == "constant":
            inputs.append(ca.SX.sym("p", model.model_parameters.size))
    b = ca.jacobian(stepped[layout.rates], u)
    # dense outputs (structural zeros as zeros): the C loop passes plain arrays
    return ca.Function(name, inputs, [stepped, ca.densify(b), residual, ca.densify(least_squares_inverse(b))],
                       GENERATED_SX_OPTIONS)


#: The ridge of :func:`least_squares_inverse`, relative to ``‖B‖_F²``. CasADi's symbolic solve does not
#: pivot: with ``1e-10`` an exactly rank-deficient ``B`` came back with entries wrong by 150× their size
#: (``1e-8``: 2 %). With ``1e-6`` a direction ``σ`` is inverted by ``σ / (σ² + λ)``: within 1 % of ``1/σ``
#: down to ``σ = 0.01 ‖B‖_F``, half of it at ``0.001 ‖B‖_F``, and damped below — the lateral force of
#: rotors tilted 0.5° (7013 of the flyer family: ``σ`` 2.4e-4 ``‖B‖_F``) counts as unactuated, not as a
#: newton of differential thrust for a millimetre per second of lateral drift.
LEAST_SQUARES_RIDGE = 1e-6


def least_squares_inverse(b: Any) -> Any:
    """``B⁺``, the damped least-squares, minimum-norm inverse of ``B`` ``(rates, m)``:
    ``(BᵀB + λI)⁻¹Bᵀ = Bᵀ(BBᵀ + λI)⁻¹`` (the smaller of the two systems), ``λ`` =
    :data:`LEAST_SQUARES_RIDGE` ``‖B‖_F²``.

    ``(BᵀB)⁻¹Bᵀ`` alone is singular for a craft with more actuators than rates (eight rotors: ``BᵀB`` is 8 × 8
    of rank 6) and for one whose actuators span fewer than its rates (six rotors that all push along the
    body z axis: no lateral force, rank 4); CasADi's solve then returned controls of 1e11–1e14 for the goal
    control of every such member of the free-flyer family."""
    rows, columns = b.shape
    ridge = LEAST_SQUARES_RIDGE * ca.sumsqr(b)
    if columns <= rows:
        return ca.solve(ca.mtimes(b.T, b) + ridge * ca.DM.eye(columns), b.T)
    return ca.solve(ca.mtimes(b, b.T) + ridge * ca.DM.eye(rows), b).T


def ordered_matvec(matrix: np.ndarray, vector: np.ndarray) -> np.ndarray:
    """``matrix @ vector`` summed term by term in column order, each product and sum rounded: what the C
    driver's loops compute (``c_template/fvin_controller.c``). NumPy's ``@`` goes to BLAS, whose fused
    multiply–adds and blocking round differently; the real-time loops compare to 1e-9 over episodes that
    amplify one ulp (docs/c-controller.md), so the small products they share are written this way."""
    matrix, vector = np.asarray(matrix, dtype=float), np.asarray(vector, dtype=float)
    result = np.zeros(matrix.shape[0])
    for k in range(matrix.shape[1]):
        result = result + matrix[:, k] * vector[k]
    return result


def control_bounds(low: np.ndarray, high: np.ndarray, horizon: int, reserve: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-stage control bounds ``(N, m)``: the whole range for the first control, the middle
    ``1 − reserve`` of it for the later ones (constraint tightening)."""
    lower, upper = np.tile(low, (horizon, 1)), np.tile(high, (horizon, 1))
    if reserve > 0.0:
        middle, half_range = 0.5 * (high + low), 0.5 * (high - low)
        lower[1:] = middle - (1.0 - reserve) * half_range
        upper[1:] = middle + (1.0 - reserve) * half_range
    return lower, upper


class DisturbanceEstimate:
    """The offset-free estimate ``d̂`` of a constant input disturbance (``x⁺ = F(x, u + d)``), shared
    by both solvers.

    After each step the prediction ``F(x_prev, u_prev + d̂)`` is compared with the measured rates
    (``ω``, or ``v`` and ``ω``): ``d̂ ← d̂ + α B⁺(rates − rates_pred)`` (``B = ∂rates⁺/∂u``, least
    squares), only within ``region_rad`` of the reference attitude and below ``region_speed``, and
    ``|d̂|`` at most half the torque range (Pannocchia & Rawlings 2003; Maeder & Morari 2009). With a
    ``free_axis`` (:attr:`~fvin_mpc.control.mpc.MPCSettings.free_axis`) "within" measures the angle
    between that axis's directions at the state and at the goal and the speed without the spin about
    it, as the cost does: a body held upright while turning about the axis is at its goal. During a
    swing-up the torque changes fast, and the delay between measurement and actuation (which the
    one-step prediction does not know) reads as a large, sign-changing "disturbance"; near the goal and
    slow the estimate is what it should be (docs/realtime.md).
    """

    def __init__(self, layout: StateLayout, gain: float, region_rad: float, region_speed: float,
                 low: np.ndarray, high: np.ndarray, free_axis: Any = None) -> None:
        self.layout, self.gain = layout, gain
        self.free_axis = None if free_axis is None else np.asarray(free_axis, dtype=float)
        self.region_rad, self.region_speed = region_rad, region_speed
        self.limit = 0.5 * (high - low)
        self.reset()

    def reset(self) -> None:
        self.value = np.zeros(self.limit.shape)
        self._last: tuple[np.ndarray, np.ndarray] | None = None  # (predicted rates, (∂rates/∂u)⁺)

    def forget_prediction(self) -> None:
        """The next measurement is not one step after the last torque (a deadline miss): skip it."""
        self._last = None

    def predicted(self, state: np.ndarray, rates_inverse: np.ndarray) -> None:
        """Remember the model's prediction of the next state (after the torque just sent)."""
        self._last = (np.asarray(state, dtype=float).ravel()[self.layout.rates], np.asarray(rates_inverse, dtype=float))

    def update(self, x0: np.ndarray, reference: np.ndarray) -> None:
        """``d̂ ← d̂ + α B⁺(rates − rates_pred)`` at the measured ``x0`` (class docstring), where ``x0`` is near the
        ``reference`` state: every attitude and hinge within ``region_rad`` of it, every angular rate within
        ``region_speed``."""
        if self.gain == 0.0 or self._last is None:
            return
        layout = self.layout
        angle, speeds = 0.0, x0.copy()
        for slot in layout.slots:
            if slot.quaternion is not None:
                q, goal = x0[slot.quaternion], reference[slot.quaternion]
                if self.free_axis is None:
                    angle = max(angle, float(s3.geodesic_angles(q, goal)))
                else:
                    angle = max(angle, s3.axis_angle(tuple(q), tuple(goal), tuple(self.free_axis)))
                    omega = layout.attitude(by="a free axis").omega
                    speeds[omega] = free_axis_projector(self.free_axis) @ x0[omega]
            elif isinstance(slot.block, Hinge):
                turn = float(x0[slot.position][0] - reference[slot.position][0])
                angle = max(angle, abs(math.atan2(math.sin(turn), math.cos(turn))))
        if angle > self.region_rad or np.max(np.abs(speeds[layout.angular_rates])) > self.region_speed:
            return
        predicted, inverse = self._last
        step = ordered_matvec(inverse, x0[layout.rates] - predicted)
        self.value = np.clip(self.value + self.gain * step, -self.limit, self.limit)


class Reference(Protocol):
    """What the MPC tracks: ``states, scales = reference(times)`` for times ``(T,)`` (s) — reference
    states ``(T, n)`` in the model's layout and control scales ``(T,)``: the stage's target control is
    ``scale × u_goal`` (``u_goal`` holds the goal at rest in the model; for a quadrotor the ratio of
    the thrust the reference needs to hover thrust). ``constant`` says the answer never changes
    with time (computed once)."""

    constant: bool

    def __call__(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


class ConstantReference:
    """The goal state at every time, control scale 1: swing up and hold, hover at a point."""

    constant = True

    def __init__(self, state: np.ndarray) -> None:
        self.state = np.asarray(state, dtype=float)

    def __call__(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.tile(self.state, (len(times), 1)), np.ones(len(times))


@dataclass(frozen=True)
class Plan:
    """A solution in array form: states ``(N+1, n)``, controls ``(N, m)`` and the multipliers."""

    states: np.ndarray
    controls: np.ndarray
    lam_g: np.ndarray | None
    lam_x: np.ndarray | None


class ControlProblem:
    """What the two controllers of the one problem share — :class:`~fvin_mpc.control.mpc.MPC` (solved to
    convergence) and :class:`~fvin_mpc.control.rti.RealTimeMPC` (real-time iterations) are its subclasses,
    siblings: the model, the goal (as the goal set reads it), the reference over the horizon, the control bounds,
    the disturbance estimate, the control that holds the goal and the first guesses. A subclass builds its solver
    in ``_build`` (called last by ``__init__``), and gives ``_predict`` and ``_rollout`` on its compiled model.

    Args:
        model: the discrete-time model (``from_checkpoint`` or ``from_rigid_body``).
        settings: the problem and its solvers' options (:class:`~fvin_mpc.control.mpc.MPCSettings`).
        goal: as ``goal_set`` reads it: a goal orientation ``(4,)`` (either sign) for an upright goal, a
            state for a hover point.
        torque_low, torque_high: control bounds ``(m,)``, e.g. the scene's ``ctrlrange``.
        rest: the orientation of the potential's minimum (hanging), which sets the energy
            scale of the terminal energy cost; needed only when ``terminal_energy_weight > 0``.
            :func:`fvin_mpc.control.scene.scene_mpc` passes the scene's.
        goal_set: what the goal is (:mod:`fvin_mpc.core.goals`; a scene declares it:
            :func:`fvin_mpc.control.scene.scene_mpc` passes the scene's); ``None``:
            :func:`~fvin_mpc.core.goals.default_goal_set` of the model's states.

    Attributes:
        build_s: seconds spent building (and compiling) the solver.
    """

    def __init__(self, model: Any, settings: Any, goal: Any, torque_low: Any, torque_high: Any,
                 rest: Any = None, goal_set: GoalSet | None = None) -> None:
        self.model = model
        self.settings = settings
        #: the blocks of the model's states (pivoted ``(q, ω)``, free ``(x, q, v, ω)``, a mechanism's joints)
        self.layout = model.space.layout
        #: what the goal is (the scene's declaration: an orientation at rest or a whole state)
        self.goal_set = default_goal_set(self.layout) if goal_set is None else goal_set
        goal_state = self.goal_set.goal_state(self.layout, goal)
        if not self.goal_set.attitude_at_rest and settings.terminal_energy_weight > 0:
            raise ValueError(f"a {self.goal_set.description} takes no terminal energy term (the energy deficit "
                             "to an orientation at rest is written for a pivot's upright goal)")
        #: the goal state; the reference is this state at rest unless :meth:`set_reference` says otherwise
        self.goal_state = goal_state
        attitude = single_attitude(self.layout)
        #: the goal orientation (the goal state's attitude), ``None`` for states of several attitudes or none
        self.goal = None if attitude is None else goal_state[attitude.quaternion].copy()
        self._reference: Reference = ConstantReference(goal_state)
        m = model.control_dim
        self.torque_low = np.broadcast_to(np.asarray(torque_low, dtype=float), (m,)).copy()
        self.torque_high = np.broadcast_to(np.asarray(torque_high, dtype=float), (m,)).copy()
        if not np.all(self.torque_low < self.torque_high):
            raise ValueError(f"need torque_low < torque_high, got {self.torque_low} and {self.torque_high}")
        self.omega_bound = settings.omega_bound_fraction / model.step_size
        self.estimate = DisturbanceEstimate(self.layout, settings.disturbance_gain, settings.disturbance_region_rad,
                                            settings.disturbance_region_speed, self.torque_low, self.torque_high,
                                            settings.free_axis)
        self.rest = None if rest is None else unit_quaternion(rest, "rest")
        #: the rest orientation at rest, as a state (``None`` without ``rest``)
        self.rest_state = None if rest is None else UPRIGHT.goal_state(self.layout, self.rest)
        if settings.terminal_energy_weight > 0:
            if self.rest is None:
                raise ValueError("terminal_energy_weight > 0 needs the rest orientation (the potential's minimum), "
                                 "which sets the energy scale: pass rest=... (a scene's task has it)")
            rest_energy = model.energy(self.rest_state)
            span = abs(model.energy(goal_state) - rest_energy)
            if not span > 1e-9 * (1.0 + abs(rest_energy)):
                raise ValueError("terminal_energy_weight > 0 needs different goal and rest energies; "
                                 f"the model gives {span:.3g} between {self.goal} and {self.rest}")
        start = time.perf_counter()
        self._build()
        self.build_s = time.perf_counter() - start
        self._u_goal = self._goal_control()
        self.reset()

    # ------------------------------------------------------------------ state of the controller
    def _goal_control(self) -> np.ndarray:
        """``u_goal``: the control that holds the goal at rest in the model — its rates (``ω``, or ``v``
        and ``ω``) stay zero (least squares, Newton). For a quadrotor: the hover thrusts."""
        x_goal = self.goal_state.copy()
        x_goal[self.layout.rates] = 0.0
        u = np.zeros(self.model.control_dim)
        for _ in range(5):
            stepped, _, _, inverse = self._predict(x_goal, u)
            u = u - ordered_matvec(inverse, np.asarray(stepped, dtype=float).ravel()[self.layout.rates])
        return u

    @property
    def disturbance(self) -> np.ndarray:
        """``d̂``, the input-disturbance estimate (control units; :class:`DisturbanceEstimate`)."""
        return self.estimate.value

    def reset(self) -> None:
        """Forget the plan and the disturbance estimate (the next call is a cold start); the clock
        restarts at 0."""
        self._previous: Plan | None = None
        self.estimate.reset()
        self._time = 0.0
        self._forget_preparation()

    def _forget_preparation(self) -> None:
        """Drop what was prepared for the next call (a solver that prepares says what)."""

    def set_reference(self, reference: Reference) -> None:
        """Track ``reference`` (a :class:`~fvin_mpc.control.problem.Reference`: states and control
        scales over time) from now on."""
        self._reference = reference
        self._reference_cache = None
        self._forget_preparation()

    def set_time(self, t: float) -> None:
        """The time of the next measurement (s, on the reference's clock). Without it the clock
        advances by one step per call; :func:`fvin_mpc.control.closed_loop.run_episode` tells it."""
        if abs(float(t) - self._time) > 1e-9:
            # Not one step after the last call (a deadline miss skipped observations): the last
            # one-step prediction says nothing about this measurement, and what was prepared was for
            # another time.
            self.estimate.forget_prediction()
            if not self._reference.constant:
                self._forget_preparation()
        self._time = float(t)

    def _sample_reference(self) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """``(time, states (N+1, n), scales (N,), states as the solvers' input (n, N+1))`` of the
        reference over the horizon from now (cached)."""
        cache = getattr(self, "_reference_cache", None)
        if cache is None or not (self._reference.constant or cache[0] == self._time):
            n = self.horizon
            states, scales = self._reference(self._time + self.model.step_size * np.arange(n + 1))
            states = np.asarray(states, dtype=float).reshape(n + 1, self.layout.state_dim)
            cache = (self._time, states, np.asarray(scales, dtype=float).reshape(n + 1)[:n], states.T)
            self._reference_cache = cache
        return cache

    def reference_window(self) -> tuple[np.ndarray, np.ndarray]:
        """The reference over the horizon from the current time: states ``(N+1, n)`` and target
        controls ``u_s,k = clip(s_k u_goal − d̂)`` ``(N, m)`` (``s_k`` the reference's control scale)."""
        _, states, scales, _ = self._sample_reference()
        return states, np.clip(scales[:, None] * self._u_goal - self.disturbance, self.torque_low, self.torque_high)

    @property
    def target_control(self) -> np.ndarray:
        """``u_s = u_goal − d̂`` (times the reference's control scale now), clipped to the bounds."""
        return self.reference_window()[1][0]

    def _update_estimate(self, x0: np.ndarray) -> None:
        """The disturbance estimate at the measured ``x0``, against the reference's attitude now."""
        self.estimate.update(x0, self._sample_reference()[1][0])

    def _predicted(self, x0: np.ndarray, u: np.ndarray) -> float:
        """Remember the model's prediction after ``u`` from ``x0`` (with ``d̂``) for the next estimate,
        advance the clock one step; returns the step's Newton residual (rad/s)."""
        predicted, _, residual, inverse = self._predict(x0, u + self.disturbance)
        self.estimate.predicted(predicted, inverse)
        self._time += self.model.step_size  # the next measurement's time unless set_time says otherwise
        return float(residual)

    # ------------------------------------------------------------------ layout
    @property
    def horizon(self) -> int:
        return self.settings.horizon

    # ------------------------------------------------------------------ what a solver gives
    def _build(self) -> None:
        """Build the solver (and the ``_predict`` it plans with)."""
        raise NotImplementedError(f"{type(self).__name__} builds no solver")

    def _predict(self, x: Any, u: Any) -> tuple[Any, ...]:
        """``(x⁺, B, residual, B⁺)`` of one step of the solver's model (:func:`predict_function`)."""
        raise NotImplementedError(f"{type(self).__name__} has no prediction")

    def _rollout(self, x0: np.ndarray, controls: np.ndarray) -> np.ndarray:
        """The model's states ``(N+1, n)`` from ``x0`` under ``controls`` (the solver's model: a solver
        with run-time model parameters rolls out with them)."""
        return self.model.rollout(x0, controls)

    # ------------------------------------------------------------------ guesses
    def _first_guess(self, x0: np.ndarray, start: str) -> Plan:
        """The plan a cold solve starts from (see :data:`COLD_STARTS`). A free body's ``"goal"``: the
        reference, the orientation turned from the measured one to the reference's along the geodesic
        over the first third of the horizon, the reference's target controls."""
        if start == "goal" and not self.goal_set.attitude_at_rest:
            n, attitude = self.horizon, self.layout.attitude(by="the goal first guess")
            references, targets = self.reference_window()
            states = references.copy()
            q0 = x0[attitude.quaternion]
            q_ref = references[:, attitude.quaternion]
            q_ref = q_ref * np.where(q_ref @ q0 >= 0, 1.0, -1.0)[:, None]  # each on q0's side of S³
            relative = s3.multiply(s3.conjugate(tuple(q0)), tuple(q_ref.T))
            turn = np.array(s3.log(relative, NP))  # (3, N+1): q_ref = q0 ⊗ exp(turn)
            weights = np.clip(np.arange(n + 1) / max(1, n // 3), 0.0, 1.0)
            states[:, attitude.quaternion] = np.array(s3.multiply(tuple(q0), s3.exp(tuple(weights * turn), NP))).T
            states[:, attitude.omega] = 0.0
            states[0] = x0
            return Plan(states, targets.copy(), None, None)
        if start == "goal":
            # Sums in order and libm's sin and acos (math, not NumPy's own SIMD versions): the C driver's
            # goal_guess computes the same, and a cold start from it converged to controls 2e-13 apart
            # that the ball joint's swing-up amplified past 1e-9 (tests/test_c_controller.py).
            n, attitude = self.horizon, self.layout.attitude(by="the goal first guess")
            q0 = [float(value) for value in x0[attitude.quaternion]]
            sign = 1.0 if float(ordered_matvec(np.array([q0]), self.goal)[0]) >= 0 else -1.0
            goal = [sign * float(value) for value in self.goal]
            angle = math.acos(min(max(float(ordered_matvec(np.array([q0]), goal)[0]), -1.0), 1.0))
            third = max(1, n // 3)
            quaternions = np.empty((n + 1, 4))
            for k in range(n + 1):
                weight = min(max(k / third, 0.0), 1.0)
                quaternions[k] = q0 if angle < 1e-9 else [  # slerp
                    (math.sin((1 - weight) * angle) * a + math.sin(weight * angle) * b) / math.sin(angle)
                    for a, b in zip(q0, goal)]
            states = np.zeros((n + 1, self.layout.state_dim))
            states[:, attitude.quaternion] = quaternions
            states[0] = x0
            return Plan(states, np.zeros((n, self.model.control_dim)), None, None)
        sign = 1.0 if start == "rollout+" else -1.0
        return self._rollout_guess(x0, sign * self.settings.initial_torque_fraction * self.torque_high)

    def _rollout_guess(self, x0: np.ndarray, torque: np.ndarray) -> Plan:
        """The model rolled out under the constant ``torque`` (clipped to the bounds), ω clipped to its bound."""
        controls = np.clip(np.tile(torque, (self.horizon, 1)), self.torque_low, self.torque_high)
        states = self._rollout(x0, controls)
        rates = self.layout.angular_rates
        states[1:, rates] = np.clip(states[1:, rates], -self.omega_bound, self.omega_bound)
        return Plan(states, controls, None, None)
