"""The forced variational step of a mechanism — a tree of joints, its state a product of blocks — written once.

A mechanism's configuration ``q`` is its joints' ``qpos`` and its rates ``ν`` their ``qvel``
(:class:`~fvin_mpc.core.blocks.StateLayout`; ``../shared/DESIGN.md``, "Mechanisms: trees of joints"). Its terms
come through :class:`MechanismTerms` — ``M(q)`` (SPD), ``U(q)``, ``D(q)`` (PSD, or none) and the input map
``B(q)`` (``nv × m``: the generalized force per unit of control) — so that the closed form
(:class:`ClosedFormMechanism`, the tree read off the MJCF) and learned terms step through the same code.

**The chart of a step.** The unknown is the step's mean rate ``w`` (``nv`` entries, ``qvel``'s units), and the next
configuration is ``q_{k+1} = q_k ⊞ h w``, block by block (:func:`advance`); the discrete Lagrangian sees the rates
``ν(q_k, q_{k+1})`` (:func:`mean_rates`):

=========================  ==========================  ======================================
block                      ``q ⊞ δ``                   ``ν(q₀, q₁)``
=========================  ==========================  ======================================
slide, hinge               ``s + δ``                   ``(s₁ − s₀)/h``
ball (body-frame ``ω``)    ``q ⊗ exp(δ/2)``            ``(2/h) Im(q₀* ⊗ q₁)``
free joint                 both: ``p + δ_v``, ``q ⊗ exp(δ_ω/2)``  ``(p₁ − p₀)/h``, ``(2/h) Im(q₀* ⊗ q₁)``
=========================  ==========================  ======================================

(``exp`` of :mod:`fvin_mpc.core.s3`, no half angle: the double cover's factor of two sits in the retraction.) A
ball's ``ν`` is quadratic in the kinetic energy, so the Lagrangian is the same for ``±q₁``; it is the S³ step's
(:mod:`fvin_mpc.core.fvin`) kinetic term, so a single ball joint steps exactly as today's S³ step. A hinge's
``ν`` is the plain difference of angles — the Störmer–Verlet kinetic term for a constant ``M`` — not the S³ hinge
step's ``sin Δθ`` form; ``docs/mechanisms.md`` measures why.

**The discrete Lagrangian** (trapezoid, symmetric in its two ends, hence second order):
``L_d(q₀, q₁) = (h/2)[T(q₀, ν) + T(q₁, ν)] − (h/2)[U(q₀) + U(q₁)]`` with ``T(q, ν) = ½ νᵀ M(q) ν``.

**The step** (Lagrange–d'Alembert in position–momentum form; ``D₁``, ``D₂`` the exact derivatives of ``L_d``
along ``q ⊞ ε`` at either end, ``ε`` in ``qvel``'s units, from the backend's
:meth:`~fvin_mpc.core.backend.Ops.jacobian`):

1. ``f⁻ = (h/2)(B(q_k)u − D(q_k)ν_k)``; solve ``R(w) := M(q_k)ν_k + f⁻ + D₁L_d(q_k, q_k ⊞ h w) = 0``.
2. At ``w = 0`` the Jacobian is exactly ``−M(q_k)`` (the kinetic terms are quadratic in ``ν``), so the first
   Newton iterate is ``w₁ = M(q_k)⁻¹ R(0) = ν_k + M(q_k)⁻¹(f⁻ − (h/2)∇U(q_k))``; ``K − 1`` iterations with the exact
   ``∂R/∂w`` follow (unrolled: the step is one expression).
3. ``q_{k+1} = q_k ⊞ h w_K``; with ``f⁺ = (h/2)(B(q_{k+1})u − D(q_{k+1})ν_{k+1})`` the end's momentum
   ``M(q_{k+1})ν_{k+1} = D₂L_d(q_k, q_{k+1}) + f⁺`` is linear in ``ν_{k+1}``: one SPD solve
   ``(M + (h/2)D)(q_{k+1}) ν_{k+1} = D₂L_d + (h/2)B(q_{k+1})u``.

Both forces are taken at their own end of the step (trapezoid), the input map included — a site transmission's
``B(q)`` turns with the mechanism, and holding it at ``q_k`` would make the forced step first order
(DESIGN, "Translation and rotation together"). Unforced and undamped, the step is a variational integrator: its
energy error stays bounded instead of drifting.

**The residual** is ``|M(q_k)⁻¹ R(w_K)|``: the Newton correction still to be made, in the rates' units (rad/s,
m/s); it is how a caller notices a state past the region where ``K`` iterations converge (fast rates, a folded
chain's ill-conditioned ``M``). The derivatives make this module run on the backends that differentiate: CasADi
(symbolic: the export; NumPy numbers by evaluating its ``Function``) and torch (autograd, differentiable itself).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Protocol, Sequence

import mujoco

from fvin_mpc.core import s3
from fvin_mpc.core.backend import Ops
from fvin_mpc.core.blocks import Block, StateLayout
from fvin_mpc.core.errors import UsageError
from fvin_mpc.core.tree_dynamics import KinematicTree

Components = Sequence[Any]
Matrix = tuple[tuple[Any, ...], ...]


class MechanismTerms(Protocol):
    """A mechanism's terms on components (any backend), ``qpos`` a tuple of ``nq`` components.

    ``mass`` is ``M(q)`` (``nv`` rows of ``nv``, symmetric positive definite); ``potential`` the scalar ``U(q)``;
    ``dissipation`` ``D(q)`` (``nv × nv``, positive semidefinite) or ``None`` for none; ``input_map`` ``B(q)`` as
    ``nv`` rows of ``control_dim`` entries, the generalized force (``qfrc``'s units) per unit of control.
    """

    control_dim: int

    def mass(self, qpos: Components, ops: Ops) -> Matrix: ...
    def potential(self, qpos: Components, ops: Ops) -> Any: ...
    def dissipation(self, qpos: Components, ops: Ops) -> Matrix | None: ...
    def input_map(self, qpos: Components, ops: Ops) -> Matrix: ...


@dataclass(frozen=True)
class ClosedFormMechanism:
    """The closed form's terms (:class:`~fvin_mpc.core.tree_dynamics.KinematicTree`) as :class:`MechanismTerms`:
    ``M`` with armature, ``U`` gravity's and the springs' potential (so springs are conservative in the step),
    ``D`` the joints' damping, ``B = actuator_momentᵀ`` with each actuator's gain.

    Attributes:
        tree: the MJCF's tree.
        damped: whether the joints' damping acts (``False``: the same mechanism without it, for energy checks).
    """

    tree: KinematicTree
    damped: bool = True

    @classmethod
    def from_mujoco(cls, model: mujoco.MjModel, damped: bool = True) -> "ClosedFormMechanism":
        """The terms of a compiled model (refused in one line where the closed form cannot model it)."""
        return cls(KinematicTree.from_mujoco(model), damped)

    @property
    def control_dim(self) -> int:
        return self.tree.nu

    def mass(self, qpos, ops):
        return self.tree.mass_matrix(qpos, ops)

    def potential(self, qpos, ops):
        return self.tree.potential_energy(qpos, ops)

    def dissipation(self, qpos, ops):
        damping = self.tree.damping
        if not self.damped or not any(damping):
            return None
        return tuple(tuple(damping[i] if i == j else 0.0 for j in range(self.tree.nv)) for i in range(self.tree.nv))

    def input_map(self, qpos, ops):
        moment, gains = self.tree.actuator_moment(qpos, ops), self.tree.gains()
        return tuple(tuple(gains[a] * moment[a][k] for a in range(self.tree.nu)) for k in range(self.tree.nv))


# ----------------------------------------------------------------------------- the chart of a step, per block kind
def _add(position: Components, delta: Components, ops: Ops) -> tuple[Any, ...]:
    return tuple(p + d for p, d in zip(position, delta))


def _difference(start: Components, end: Components, step_size: float, ops: Ops) -> tuple[Any, ...]:
    return tuple((e - s) / step_size for s, e in zip(start, end))


def _turn(quaternion: Components, delta: Components, ops: Ops) -> tuple[Any, ...]:
    return s3.multiply(tuple(quaternion), s3.exp(s3.scale(0.5, delta), ops))


def _body_rate(start: Components, end: Components, step_size: float, ops: Ops) -> tuple[Any, ...]:
    return s3.scale(2.0 / step_size, s3.imaginary(s3.multiply(s3.conjugate(tuple(start)), tuple(end))))


def _free_advance(position: Components, delta: Components, ops: Ops) -> tuple[Any, ...]:
    return (*_add(position[:3], delta[:3], ops), *_turn(position[3:], delta[3:], ops))


def _free_rates(start: Components, end: Components, step_size: float, ops: Ops) -> tuple[Any, ...]:
    return (*_difference(start[:3], end[:3], step_size, ops), *_body_rate(start[3:], end[3:], step_size, ops))


#: Per block kind: ``(q ⊞ δ, ν(q₀, q₁))`` (module docstring). A new block kind adds its entry here.
STEP_CHARTS: dict[str, tuple[Callable[..., tuple[Any, ...]], Callable[..., tuple[Any, ...]]]] = {
    "slide": (_add, _difference), "hinge": (_add, _difference),
    "ball": (_turn, _body_rate), "free": (_free_advance, _free_rates),
}


def _chart(block: Block) -> tuple[Callable[..., tuple[Any, ...]], Callable[..., tuple[Any, ...]]]:
    if block.kind not in STEP_CHARTS:
        raise UsageError(f"the mechanism step has no chart for a {block.kind!r} block; known: {sorted(STEP_CHARTS)}")
    return STEP_CHARTS[block.kind]


def advance(layout: StateLayout, qpos: Components, delta: Components, ops: Ops) -> tuple[Any, ...]:
    """``q ⊞ δ``: every block's position moved by its part of ``δ`` (``nv`` entries in ``qvel``'s units)."""
    moved: list[Any] = []
    for slot in layout.slots:
        start, stop = slot.position.start, slot.position.stop
        chart_start = slot.rate.start - layout.rates.start
        moved += _chart(slot.block)[0](qpos[start:stop], delta[chart_start:chart_start + slot.block.tangent_size], ops)
    return tuple(moved)


def mean_rates(layout: StateLayout, start: Components, end: Components, step_size: float, ops: Ops) -> tuple[Any, ...]:
    """``ν(q₀, q₁)``: the rates the discrete Lagrangian sees between two configurations a step apart."""
    rates: list[Any] = []
    for slot in layout.slots:
        part = slot.position
        rates += _chart(slot.block)[1](start[part], end[part], step_size, ops)
    return tuple(rates)


# ----------------------------------------------------------------------------- linear algebra on components
def _is_zero(entry: Any) -> bool:
    return isinstance(entry, (int, float)) and entry == 0.0


def solve_linear(matrix: Matrix, rhs: Components) -> tuple[Any, ...]:
    """``matrix⁻¹ rhs`` by Gaussian elimination without pivoting, on components (any backend): for the step's
    matrices, ``M`` SPD and Newton Jacobians near ``−M``, whose diagonal dominates; structural zeros skipped."""
    n = len(rhs)
    rows, values = [list(row) for row in matrix], list(rhs)
    for column in range(n):
        for row in range(column + 1, n):
            if _is_zero(rows[row][column]):
                continue
            factor = rows[row][column] / rows[column][column]
            rows[row] = [rows[row][j] - factor * rows[column][j] for j in range(n)]
            values[row] = values[row] - factor * values[column]
    solution: list[Any] = [0.0] * n
    for row in range(n - 1, -1, -1):
        total = values[row]
        for j in range(row + 1, n):
            if not _is_zero(rows[row][j]):
                total = total - rows[row][j] * solution[j]
        solution[row] = total / rows[row][row]
    return tuple(solution)


def _quadratic(matrix: Matrix, vector: Components) -> Any:
    return s3.dot(vector, s3.matvec(matrix, vector))


def _safe_norm(vector: Components, ops: Ops) -> Any:
    """``|v|`` with derivatives that stay finite (zero) where ``v = 0``, a converged solve's residual."""
    squared = s3.dot(vector, vector)
    nonzero = squared > 0.0
    return ops.where(nonzero, ops.sqrt(ops.where(nonzero, squared, 1.0 + 0.0 * squared)), 0.0 * squared)


# ----------------------------------------------------------------------------- the discrete Lagrangian
def discrete_lagrangian(terms: MechanismTerms, layout: StateLayout, start: Components, end: Components,
                        step_size: float, ops: Ops) -> Any:
    """``L_d(q₀, q₁) = (h/2)[T(q₀, ν) + T(q₁, ν)] − (h/2)[U(q₀) + U(q₁)]`` (module docstring)."""
    h = step_size
    rates = mean_rates(layout, start, end, h, ops)
    kinetic = 0.5 * (_quadratic(terms.mass(start, ops), rates) + _quadratic(terms.mass(end, ops), rates))
    return 0.5 * h * (kinetic - terms.potential(start, ops) - terms.potential(end, ops))


def lagrangian_slopes(terms: MechanismTerms, layout: StateLayout, start: Components, end: Components,
                      step_size: float, ops: Ops, at_end: bool) -> tuple[Any, ...]:
    """``D₁L_d(q₀, q₁)`` (``at_end`` false) or ``D₂L_d`` (true): the derivative along ``q ⊞ ε`` at that end,
    ``nv`` entries in ``qfrc``'s units times seconds (momentum)."""
    zeros = tuple(0.0 * start[0] for _ in range(layout.rates.stop - layout.rates.start))

    def moved(epsilon: Components) -> tuple[Any]:
        if at_end:
            return (discrete_lagrangian(terms, layout, start, advance(layout, end, epsilon, ops), step_size, ops),)
        return (discrete_lagrangian(terms, layout, advance(layout, start, epsilon, ops), end, step_size, ops),)

    return ops.jacobian(moved, zeros)[1][0]


# ----------------------------------------------------------------------------- the step
@dataclass(frozen=True)
class MechanismStepResult:
    """One step: the next state (stacked as the input: NumPy/torch ``(…, n)``, CasADi a column) and the
    residual ``|M(q_k)⁻¹ R(w_K)|`` in the rates' units."""

    x: Any
    residual: Any


def _check(layout: StateLayout, terms: MechanismTerms, step_size: float, newton_iters: int) -> None:
    if not isinstance(layout, StateLayout):
        raise UsageError(f"the mechanism step needs a StateLayout, got {type(layout).__name__}")
    for block in layout.blocks:
        _chart(block)
    if not (isinstance(step_size, (int, float)) and math.isfinite(step_size) and step_size > 0.0):
        raise UsageError(f"step_size must be a positive number of seconds, got {step_size!r}")
    if isinstance(newton_iters, bool) or not isinstance(newton_iters, int) or newton_iters < 1:
        raise UsageError(f"newton_iters must be an integer >= 1, got {newton_iters!r}")
    if not isinstance(getattr(terms, "control_dim", None), int):
        raise UsageError(f"the mechanism's terms need an integer control_dim, got {type(terms).__name__}")


def _generalized_force(terms: MechanismTerms, qpos: Components, rates: Components | None, control: Components,
                       nv: int, ops: Ops) -> tuple[Any, ...]:
    """``B(q)u − D(q)ν`` (``ν`` ``None``: the control's part alone)."""
    force = s3.matvec(terms.input_map(qpos, ops), control) if len(control) else (0.0,) * nv
    damping = terms.dissipation(qpos, ops) if rates is not None else None
    return force if damping is None else s3.sub(force, s3.matvec(damping, rates))


def mechanism_step(x: Any, u: Any, terms: MechanismTerms, layout: StateLayout, step_size: float,
                   newton_iters: int, ops: Ops) -> MechanismStepResult:
    """One forced variational step ``(q_k, ν_k, u_k) → (q_{k+1}, ν_{k+1})`` (module docstring).

    Args:
        x: the state, ``layout``'s ``(qpos, qvel)``: NumPy/torch ``(…, n)``, CasADi a column of ``n``.
        u: the control, ``(…, m)`` or a column of ``m`` (``m = terms.control_dim``; held over the step).
        terms: the mechanism's :class:`MechanismTerms`.
        layout: the state's blocks.
        step_size: ``h`` in seconds.
        newton_iters: ``K ≥ 1``; ``K = 1`` is the first iterate alone.
        ops: a backend that differentiates (CasADi or torch).

    Raises:
        UsageError: a bad size, step size, ``K``, or a block kind without a step chart, before any work.
    """
    _check(layout, terms, step_size, newton_iters)
    state, control = ops.unstack(x), ops.unstack(u)
    if len(state) != layout.state_dim:
        raise UsageError(f"the state has {len(state)} entries; {layout.name} has {layout.state_dim}")
    if len(control) != terms.control_dim:
        raise UsageError(f"the control has {len(control)} entries; the mechanism has {terms.control_dim}")
    h = step_size
    qpos, rates = state[layout.positions], state[layout.rates]
    mass = terms.mass(qpos, ops)
    if len(mass) != len(rates):
        raise UsageError(f"the terms' M is {len(mass)} × {len(mass)}; {layout.name} has {len(rates)} rates")
    start_force = s3.scale(h / 2.0, _generalized_force(terms, qpos, rates, control, len(rates), ops))
    momentum = s3.add(s3.matvec(mass, rates), start_force)

    def residual_of(mean_rate: Components) -> tuple[Any, ...]:
        end = advance(layout, qpos, s3.scale(h, mean_rate), ops)
        return s3.add(momentum, lagrangian_slopes(terms, layout, qpos, end, h, ops, at_end=False))

    mean_rate = solve_linear(mass, residual_of(tuple(0.0 * r for r in rates)))  # ∂R/∂w(0) = −M(q_k), exactly
    for _ in range(newton_iters - 1):
        value, jacobian = ops.jacobian(residual_of, mean_rate)
        mean_rate = s3.sub(mean_rate, solve_linear(jacobian, value))
    qpos_next = advance(layout, qpos, s3.scale(h, mean_rate), ops)
    end_momentum = s3.add(lagrangian_slopes(terms, layout, qpos, qpos_next, h, ops, at_end=True),
                          s3.scale(h / 2.0, _generalized_force(terms, qpos_next, None, control, len(rates), ops)))
    end_map = terms.mass(qpos_next, ops)
    damping_next = terms.dissipation(qpos_next, ops)
    if damping_next is not None:
        end_map = tuple(tuple(end_map[i][j] + (h / 2.0) * damping_next[i][j] for j in range(len(rates)))
                        for i in range(len(rates)))
    rates_next = solve_linear(end_map, end_momentum)
    residual = _safe_norm(solve_linear(mass, residual_of(mean_rate)), ops)
    return MechanismStepResult(ops.stack([*qpos_next, *rates_next]), residual)


def mechanism_energy(x: Any, terms: MechanismTerms, layout: StateLayout, ops: Ops) -> Any:
    """``½ νᵀ M(q) ν + U(q)`` of a state (any backend; NumPy too: no derivatives)."""
    state = ops.unstack(x)
    qpos, rates = state[layout.positions], state[layout.rates]
    return 0.5 * _quadratic(terms.mass(qpos, ops), rates) + terms.potential(qpos, ops)
