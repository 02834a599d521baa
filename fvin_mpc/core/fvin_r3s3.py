"""Translation and rotation together: the R³ × S³ step (paper §3.3, eqs. 3.20–3.24), written once.

State (13 numbers): ``(x, q, v, ω)`` — position ``x ∈ R³`` and velocity ``v`` in the world frame,
``q = (w, x, y, z)`` a unit quaternion (body → world, ``R(q)`` of eq. 3.10), ``ω`` the body-frame
angular velocity (rad/s). Momenta: ``p = M v`` (``M`` constant SPD 3×3) and ``π = 2 J ω``
(DESIGN.md). Control ``u ∈ R^m``.

Given ``(x_k, q_k, v_k, ω_k, u_k)``, a step ``h`` and :class:`CombinedTerms` (``M``, ``J(q)``,
``U(x, q)`` with ``∇ₓU`` (3) and the Euclidean ``∇_qU`` (4), the world-frame force ``F_x(x, q, u)``
and the rotational gain ``g(x, q)`` (3×m, left-trivialized: twice the body torque per unit ``u``):

0. Forces as eq. 3.6: ``f^{x−} = (h/2) F_x(x_k, q_k, u_k)``, ``f^{q±} = (h/2) g(x_k, q_k) u_k``;
   ``f^{x+} = f^{x−}`` (``force_rule="hold"``, eq. 3.6 as written) or
   ``f^{x+} = (h/2) F_x(x_{k+1}, q_{k+1}, u_k)`` (``force_rule="trapezoid"``, see below).
1. ``x_{k+1} = x_k + h M⁻¹ p_k − (h²/2) M⁻¹ ∇ₓU(x_k, q_k) + h M⁻¹ f^{x−}`` (explicit; computed as
   ``x_k + h (v_k + M⁻¹(f^{x−} − (h/2) ∇ₓU))`` so that ``M⁻¹ M v`` never round-trips).
2. The rotational solve of DESIGN.md steps 1–4 with ``∇_qU(x_k, q_k)`` and ``f^{q−}``
   (:func:`fvin_mpc.core.fvin.implicit_problem` / :func:`~fvin_mpc.core.fvin.solve_implicit`
   on the rotational terms frozen at ``x_k``): ``q_{k+1} = q_k ⊗ exp(ξ)``.
3. ``p_{k+1} = p_k − (h/2)(∇ₓU(x_k, q_k) + ∇ₓU(x_{k+1}, q_{k+1})) + f^{x+} + f^{x−}``,
   ``v_{k+1} = M⁻¹ p_{k+1}``; ``π_{k+1}`` by DESIGN.md step 5 with ``∇_qU(x_{k+1}, q_{k+1})``
   (:func:`~fvin_mpc.core.fvin.finish_step` on the terms frozen at ``x_{k+1}``), ``ω_{k+1} = ½ J⁻¹ π_{k+1}``.

The rotational math is :mod:`fvin_mpc.core.fvin`'s, unchanged: this module only supplies it a
:class:`~fvin_mpc.core.fvin.RigidBodyTerms` view of the combined terms at a fixed position.

Force rule. Eq. 3.6 holds ``F_x`` at ``(x_k, q_k)`` over the whole step. When ``F_x`` depends on
the orientation — a rotor's thrust ``R(q) e_z Σuᵢ`` on a tumbling body — the velocity then gains
an ``O(h²)`` error per step: the translational part is first order (measured in
``tests/test_r3s3.py``). ``"trapezoid"`` evaluates ``f^{x+}`` at the end of the step, as
``docs/design.md`` does for damping; it costs one more ``F_x`` evaluation and no solve (``x_{k+1}``
and ``q_{k+1}`` are known before ``p_{k+1}``), and the step is second order. With ``F_x`` not
depending on ``(x, q)`` the two rules are the same step.

Velocity-Verlet: with ``F_x = 0`` and ``U`` independent of ``q`` the translational part is the
Velocity-Verlet step, exact for constant gravity.

Where it breaks down: as the rotational step (``h|ω| ≲ 1`` for ``J = jI``); the residual
(:attr:`R3S3StepResult.residual`, rad/s) is how a caller notices. The translation never fails.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

from fvin_mpc.core import fvin, s3
from fvin_mpc.core.backend import Ops

FORCE_RULES = ("hold", "trapezoid")


class CombinedTerms(Protocol):
    """The (learned or closed-form) parts of a free rigid body in R³ × S³, on components.

    ``x`` is a 3-tuple, ``q`` a 4-tuple, ``u`` an ``m``-tuple of components.
    ``mass_matrix`` is the constant SPD ``M`` (3×3 rows); ``inertia`` the SPD ``J(q)`` (body);
    ``potential_gradient_x`` is ``∇ₓU`` (3), ``potential_gradient_q`` the Euclidean ``∇_qU`` in R⁴
    (4); ``translational_force`` ``F_x`` in the world frame (3); ``control_gain`` ``g`` (3 rows of
    ``m``), twice the body torque per unit control (DESIGN.md, factor of two).
    """

    control_dim: int
    constant_inertia: bool

    def mass_matrix(self) -> s3.Mat3: ...
    def inertia(self, q: s3.Quat) -> s3.Mat3: ...
    def potential(self, x: s3.Vec3, q: s3.Quat) -> Any: ...
    def potential_gradient_x(self, x: s3.Vec3, q: s3.Quat) -> s3.Vec3: ...
    def potential_gradient_q(self, x: s3.Vec3, q: s3.Quat) -> s3.Quat: ...
    def translational_force(self, x: s3.Vec3, q: s3.Quat, u: tuple[Any, ...]) -> s3.Vec3: ...
    def control_gain(self, x: s3.Vec3, q: s3.Quat) -> tuple[tuple[Any, ...], ...]: ...


class RotationAt:
    """:class:`~fvin_mpc.core.fvin.RigidBodyTerms` of ``terms`` with the position frozen at ``x``."""

    def __init__(self, terms: CombinedTerms, x: s3.Vec3) -> None:
        self.terms, self.x = terms, x
        self.control_dim = terms.control_dim
        self.constant_inertia = terms.constant_inertia

    def inertia(self, q: s3.Quat) -> s3.Mat3:
        return self.terms.inertia(q)

    def potential(self, q: s3.Quat) -> Any:
        return self.terms.potential(self.x, q)

    def potential_gradient(self, q: s3.Quat) -> s3.Quat:
        return self.terms.potential_gradient_q(self.x, q)

    def control_gain(self, q: s3.Quat) -> tuple[tuple[Any, ...], ...]:
        return self.terms.control_gain(self.x, q)

    def dissipation(self, q: s3.Quat) -> None:
        return None


@dataclass(frozen=True)
class R3S3StepResult:
    """One R³ × S³ step: ``x``, ``q``, ``v`` (world), ``ω`` (body) as backend components;
    ``residual`` the rotational solve's (rad/s, :class:`fvin_mpc.core.fvin.StepResult`) or ``None``."""

    x: s3.Vec3
    q: s3.Quat
    v: s3.Vec3
    omega: s3.Vec3
    residual: Any | None


def r3s3_step(x: s3.Vec3, q: s3.Quat, v: s3.Vec3, omega: s3.Vec3, u: tuple[Any, ...], terms: CombinedTerms,
              h: float, K: int, ops: Ops, with_residual: bool = False,
              force_rule: str = "trapezoid") -> R3S3StepResult:
    """One step ``(x_k, q_k, v_k, ω_k, u_k) → (x_{k+1}, q_{k+1}, v_{k+1}, ω_{k+1})``; see the module
    docstring. ``K`` Newton iterations for the rotation; ``force_rule`` ``"trapezoid"`` (default:
    second order) or ``"hold"`` (eq. 3.6 as written: first order in ``x``, ``v`` when ``F_x`` turns
    with the body)."""
    if force_rule not in FORCE_RULES:
        raise ValueError(f"force_rule must be one of {FORCE_RULES}, got {force_rule!r}")
    mass = terms.mass_matrix()
    # Step 1: explicit position update.
    force_minus = s3.scale(h / 2.0, terms.translational_force(x, q, u))
    grad_x = terms.potential_gradient_x(x, q)
    kick = s3.solve3(mass, s3.sub(force_minus, s3.scale(h / 2.0, grad_x)))
    x_next = s3.add(x, s3.scale(h, s3.add(v, kick)))
    # Step 2: the rotational solve with ∇_qU(x_k, q_k) and f^{q−} = (h/2) g(x_k, q_k) u_k.
    problem = fvin.implicit_problem(q, omega, u, RotationAt(terms, x), h)
    xi = fvin.solve_implicit(problem.rhs, problem.inertia, K, ops)
    rotation = fvin.finish_step(q, xi, problem, RotationAt(terms, x_next), h, ops, with_residual)
    q_next = rotation.q
    # Step 3: p_{k+1} by the trapezoid of ∇ₓU (π_{k+1} was step 5 inside finish_step).
    force_plus = (
        force_minus if force_rule == "hold" else s3.scale(h / 2.0, terms.translational_force(x_next, q_next, u))
    )
    grad_x_next = terms.potential_gradient_x(x_next, q_next)
    impulse = s3.sub(s3.add(force_minus, force_plus), s3.scale(h / 2.0, s3.add(grad_x, grad_x_next)))
    v_next = s3.add(v, s3.solve3(mass, impulse))
    return R3S3StepResult(x=x_next, q=q_next, v=v_next, omega=rotation.omega, residual=rotation.residual)  # type: ignore[arg-type]


def total_energy(x: s3.Vec3, q: s3.Quat, v: s3.Vec3, omega: s3.Vec3, terms: CombinedTerms) -> Any:
    """``E = ½ vᵀ M v + ½ ωᵀ J(q) ω + U(x, q)`` in the model's own scale."""
    translational = 0.5 * s3.dot(v, s3.matvec(terms.mass_matrix(), v))
    rotational = 0.5 * s3.dot(omega, s3.matvec(terms.inertia(q), omega))
    return translational + rotational + terms.potential(x, q)


#: Entries of the state ``(x, q, v, ω)``.
FREE_STATE_DIM = 13


def split_free_state(state: Any, ops: Ops) -> tuple[s3.Vec3, s3.Quat, s3.Vec3, s3.Vec3]:
    """``(x, q, v, ω)`` components of a stacked state (NumPy/torch ``(..., 13)``, CasADi ``(13, 1)``)."""
    c = ops.unstack(state)
    if len(c) != FREE_STATE_DIM:
        raise ValueError(f"a free-body state has {FREE_STATE_DIM} entries (x, q, v, ω), got {len(c)}")
    return c[0:3], c[3:7], c[7:10], c[10:13]  # type: ignore[return-value]


def step_state(state: Any, u: Any, terms: CombinedTerms, h: float, K: int, ops: Ops,
               force_rule: str = "trapezoid") -> tuple[Any, Any]:
    """:func:`r3s3_step` on stacked arrays: ``state (..., 13)``, ``u (..., m)`` → ``(state_next, residual)``
    (CasADi: columns). The one place the 13-number layout ``(x, q, v, ω)`` is packed and unpacked."""
    x, q, v, omega = split_free_state(state, ops)
    out = r3s3_step(x, q, v, omega, ops.unstack(u), terms, h, K, ops, with_residual=True, force_rule=force_rule)
    return ops.stack((*out.x, *out.q, *out.v, *out.omega)), out.residual
