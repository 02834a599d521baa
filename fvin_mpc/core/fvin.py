"""The forced S³ variational integrator step (paper eqs. 3.23–3.25), written once.

Given ``(q_k, ω_k, u_k)``, a step size ``h`` and the rigid-body terms ``J(q)`` (SPD),
``U(q)``, ``g(q)`` (3×m) and optionally a dissipation ``D(q)`` (PSD):

1. ``π_k = 2 J(q_k) ω_k``; discrete forces ``f⁻ = (h/2)(g(q_k) u_k − D(q_k) ω_k)`` and
   ``f⁺ = (h/2)(g(q_k) u_k − D(q_{k+1}) ω_{k+1})``.
2. ``C = −(h/4) (π_k + f⁻ − (h/2) H(q_k) ∇U(q_k))``.
3. Solve ``Φ(ξ) := G(exp(−ξ)) J Im(exp(−ξ)) = C`` by Newton from ``ξ = 0``.
   The first iterate is exact and nearly free: ``∂Φ/∂ξ(0) = −J`` so ``ξ₁ = −J⁻¹C``.
4. ``q_{k+1} = q_k ⊗ exp(ξ)``.
5. ``π_{k+1} = (4/h) G(exp ξ) J Im(exp ξ) − (h/2) H(q_{k+1}) ∇U(q_{k+1}) + f⁺`` with
   ``π_{k+1} = 2 J(q_{k+1}) ω_{k+1}``. ``f⁺`` is linear in ``ω_{k+1}``, so this is the 3×3
   linear system ``(2 J(q_{k+1}) + (h/2) D(q_{k+1})) ω_{k+1} = P`` with
   ``P = (4/h) G(exp ξ) J Im(exp ξ) − (h/2) H(q_{k+1}) ∇U(q_{k+1}) + (h/2) g(q_k) u_k``
   (SPD: ``J`` SPD, ``D`` PSD). Without ``D``: ``ω_{k+1} = ½ J(q_{k+1})⁻¹ P``, as before.

Damping: taking ``−Dω`` at the start of the step in ``f⁻`` and at its end in ``f⁺`` (the
trapezoidal rule for the virtual work of the force) keeps the step symmetric — for constant
``J``, ``g`` and ``u`` held over the step, the step from ``(q_k, ω_k)`` with ``h`` and the one
from ``(q_{k+1}, ω_{k+1})`` with ``−h`` are each other's inverse — so it is second order, and
the end-of-step damping costs no implicit solve because it is linear in ``ω_{k+1}`` (the
implicit-damping trick of simulators). Holding ``−D ω_k`` in both halves, as an earlier
version did, made any damped step first order. The control force ``g u`` stays at ``q_k`` in
both halves (zero-order hold, unchanged), so a configuration-dependent learned ``g`` under a
nonzero control is still integrated at first order in its ``q`` dependence; with ``D`` absent
the step is exactly (bit for bit) the undamped one.

``J`` in steps 3 and 5 is the discrete Lagrangian's inertia, evaluated at ``q_k``; the
Legendre map at ``q_{k+1}`` uses ``J(q_{k+1})``. For a constant ``J`` the two agree.

On a hinge (terms with a ``hinge_axis`` ``a``, unit, in the body frame): the body can only turn
about ``a``, so the increment is ``ξ = φ a`` and the hinge's reaction — a force perpendicular to
``a`` in both equations — drops out of their components along ``a`` (Lagrange–d'Alembert with the
holonomic constraint). Step 3 becomes ``aᵀΦ(φ a) = −½ sin(2φ) aᵀJa = aᵀC``, solved exactly,
``φ = ½ asin(−2 aᵀC / aᵀJa)`` (no Newton iterations: the ``K`` of the step is not used), and step 5
``ω_{k+1} = a (aᵀP) / (aᵀ(2J + (h/2)D)a)``. Only ``aᵀJa``, ``aᵀD a``, ``aᵀg`` and the torque of
``U`` about ``a`` enter, so a learned 3-D body trained on a hinge's motion cannot plan across the
hinge with terms its data never saw (:func:`hinge_step`). The same solvability limit: ``h|θ̇| ≲ 1``.

Where it breaks down: for ``J = jI``, ``|Φ| ≤ j/2`` so a solution exists only while
``h|ω| ≲ 1``, and ``∂Φ/∂ξ`` is singular at ``|ξ| = π/4``. Unrolled Newton still returns
numbers past that — always finite: iterates are kept within ``|ξ| ≤ 3π/8`` and the Newton
determinant is floored (:data:`MAX_INCREMENT`, :data:`SINGULAR_JACOBIAN`; both inactive in the
solvable region) — and :attr:`StepResult.residual` (``|Φ(ξ_K) − C| / |C|``-style, see
:func:`fvin_step`) is how a caller notices.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

from fvin_mpc.core import s3
from fvin_mpc.core.backend import Ops


class RigidBodyTerms(Protocol):
    """The learned (or closed-form) parts of a rigid body, evaluated on components.

    All methods take a quaternion ``q`` (4-tuple of components) and return tuples of
    components: ``inertia`` a symmetric 3×3 ``Mat3``; ``potential_gradient`` the
    Euclidean gradient of ``U`` in R⁴ (4-tuple); ``control_gain`` 3 rows of ``m``
    entries; ``dissipation`` a PSD ``Mat3`` or ``None`` when the model has none. Terms may also
    carry a ``hinge_axis`` (a unit 3-tuple of floats in the body frame): the body then turns about
    it only (:func:`hinge_axis_of`, :func:`hinge_step`).
    """

    control_dim: int
    constant_inertia: bool

    def inertia(self, q: s3.Quat) -> s3.Mat3: ...
    def potential(self, q: s3.Quat) -> Any: ...
    def potential_gradient(self, q: s3.Quat) -> s3.Quat: ...
    def control_gain(self, q: s3.Quat) -> tuple[tuple[Any, ...], ...]: ...
    def dissipation(self, q: s3.Quat) -> s3.Mat3 | None: ...


@dataclass(frozen=True)
class StepResult:
    """One FVIN step. Components follow the backend (see :mod:`fvin_mpc.backend`).

    ``residual`` is ``|Φ(ξ_K) − C|`` scaled by ``2/(h·|J|)`` so that it reads as an
    angular-velocity error in rad/s; ``None`` when not requested.
    """

    q: s3.Quat
    omega: s3.Vec3
    residual: Any | None


def implicit_lhs(xi: s3.Vec3, inertia: s3.Mat3, ops: Ops) -> s3.Vec3:
    """``Φ(ξ) = G(exp(−ξ)) J Im(exp(−ξ))`` (left-hand side of eq. 3.25)."""
    p = s3.exp(s3.scale(-1.0, xi), ops)
    return s3.G_apply(p, s3.matvec(inertia, s3.imaginary(p)))


def implicit_lhs_jacobian(xi: s3.Vec3, inertia: s3.Mat3, ops: Ops) -> tuple[s3.Vec3, s3.Mat3]:
    """``Φ(ξ)`` and its analytic Jacobian ``∂Φ/∂ξ`` (3×3, rows).

    With ``t = |ξ|²``, ``c = cos√t``, ``s = sin√t/√t``, ``s' = ds/dt``:
    ``exp(−ξ) = (c, v)`` with ``v = −s ξ`` and ``Φ = c Jv − v × Jv``. From
    ``∂c/∂ξ = −s ξᵀ`` and ``∂v/∂ξ = −s I − 2 s' ξ ξᵀ``:
    ``∂Φ/∂ξ = −s A + (−2 s' A ξ − s Jv) ξᵀ`` with ``A = c J − [v]× J + [Jv]×``.
    """
    t = s3.dot(xi, xi)
    c, s, ds = s3.trig_of_sqrt(t, ops, with_derivative=True)
    v = s3.scale(-s, xi)
    jv = s3.matvec(inertia, v)
    phi = s3.sub(s3.scale(c, jv), s3.cross(v, jv))
    # Columns of [v]× J are v × (columns of J); J is symmetric so its columns are its rows.
    v_cross_j = [s3.cross(v, inertia[k]) for k in range(3)]
    a = tuple(
        tuple(c * inertia[i][j] - v_cross_j[j][i] for j in range(3)) for i in range(3)
    )
    a = (
        (a[0][0], a[0][1] - jv[2], a[0][2] + jv[1]),
        (a[1][0] + jv[2], a[1][1], a[1][2] - jv[0]),
        (a[2][0] - jv[1], a[2][1] + jv[0], a[2][2]),
    )
    a_xi = s3.matvec(a, xi)
    w = tuple(-2.0 * ds * a_xi[i] - s * jv[i] for i in range(3))
    jacobian = tuple(tuple(w[i] * xi[j] - s * a[i][j] for j in range(3)) for i in range(3))
    return phi, jacobian  # type: ignore[return-value]


def solve_implicit(rhs: s3.Vec3, inertia: s3.Mat3, newton_iters: int, ops: Ops) -> s3.Vec3:
    """``K = newton_iters`` Newton iterations on ``Φ(ξ) = C`` from ``ξ = 0``."""
    if newton_iters < 1:
        raise ValueError(f"newton_iters must be >= 1, got {newton_iters}")
    xi = clamp_increment(s3.scale(-1.0, s3.solve3(inertia, rhs)), ops)  # exact first iterate: ∂Φ/∂ξ(0) = −J
    det_floor = SINGULAR_JACOBIAN * s3.determinant(inertia)
    for _ in range(newton_iters - 1):
        phi, jacobian = implicit_lhs_jacobian(xi, inertia, ops)
        xi = clamp_increment(s3.sub(xi, guarded_solve3(jacobian, s3.sub(phi, rhs), det_floor, ops)), ops)
    return xi


#: ``|det ∂Φ/∂ξ|`` is kept above this fraction of ``det J`` (its value at ``ξ = 0``). Past the
#: solvability limit an iterate can land exactly on a singular point (e.g. ``|ξ| = π/4`` for
#: ``J = jI``, reached in one step from ``h|ω| = π/2``), where Cramer's rule divides by 0.
SINGULAR_JACOBIAN = 1e-12


def guarded_solve3(m: s3.Mat3, r: s3.Vec3, det_floor: Any, ops: Ops) -> s3.Vec3:
    """``m⁻¹ r`` by Cramer's rule with ``|det m|`` floored at ``det_floor`` (inactive when regular)."""
    c0, c1, c2 = s3.cross(m[1], m[2]), s3.cross(m[2], m[0]), s3.cross(m[0], m[1])
    det = s3.dot(m[0], c0)
    det = ops.where(det >= 0.0, ops.where(det > det_floor, det, det_floor + 0.0 * det),
                    ops.where(det < -det_floor, det, -det_floor + 0.0 * det))
    return tuple((c0[i] * r[0] + c1[i] * r[1] + c2[i] * r[2]) / det for i in range(3))  # type: ignore[return-value]


#: Newton iterates are kept within ``|ξ| ≤ 3π/8`` (135° per step). The solution of interest lies
#: well inside (``|ξ| < π/4`` for ``J = jI``). Past the solvability limit unclamped iterates grow
#: without bound until the Jacobian's determinant underflows to 0 and the step returns NaN; the
#: radius avoids ``π/4`` and ``π/2``, where ``∂Φ/∂ξ`` of an isotropic ``J`` is singular on the
#: whole sphere (radially, resp. transversally).
MAX_INCREMENT = 3.0 * math.pi / 8.0


def clamp_increment(xi: s3.Vec3, ops: Ops) -> s3.Vec3:
    """``ξ`` scaled back onto ``|ξ| = 3π/8`` when longer; the identity (value and derivatives) inside."""
    t = s3.dot(xi, xi)
    outside = t > MAX_INCREMENT * MAX_INCREMENT
    safe_t = ops.where(outside, t, MAX_INCREMENT * MAX_INCREMENT + 0.0 * t)
    factor = ops.where(outside, MAX_INCREMENT / ops.sqrt(safe_t), 1.0 + 0.0 * t)
    return s3.scale(factor, xi)


def generalized_force(q: s3.Quat, omega: s3.Vec3, u: tuple[Any, ...], terms: RigidBodyTerms) -> s3.Vec3:
    """``g(q) u − D(q) ω`` — the continuous left-trivialized force on S³ (twice the SO(3) torque)."""
    return _force_from_control(q, omega, s3.matvec(terms.control_gain(q), u), terms)


def _force_from_control(q: s3.Quat, omega: s3.Vec3, control_force: s3.Vec3, terms: RigidBodyTerms) -> s3.Vec3:
    """``control_force − D(q) ω`` (``control_force`` itself when the model has no ``D``)."""
    damping = terms.dissipation(q)
    if damping is None:
        return control_force
    return s3.sub(control_force, s3.matvec(damping, omega))  # type: ignore[return-value]


@dataclass(frozen=True)
class ImplicitProblem:
    """Steps 1–2 of a step: the implicit equation ``Φ(ξ) = rhs`` and what finishing needs.

    Attributes:
        inertia: ``J(q_k)`` (rows).
        rhs: ``C`` of DESIGN.md step 2.
        control_force: ``(h/2) g(q_k) u_k`` — the part of ``f⁺`` known before the solve; the
            damping part ``−(h/2) D(q_{k+1}) ω_{k+1}`` is solved for in :func:`finish_step`.
    """

    inertia: s3.Mat3
    rhs: s3.Vec3
    control_force: s3.Vec3


def implicit_problem(q: s3.Quat, omega: s3.Vec3, u: tuple[Any, ...], terms: RigidBodyTerms,
                     step_size: float) -> ImplicitProblem:
    """Steps 1–2: momentum, ``f⁻`` and the right-hand side ``C``."""
    h = step_size
    inertia = terms.inertia(q)
    momentum = s3.scale(2.0, s3.matvec(inertia, omega))
    control = s3.matvec(terms.control_gain(q), u)
    force_minus = s3.scale(h / 2.0, _force_from_control(q, omega, control, terms))
    gravity = s3.H_apply(q, terms.potential_gradient(q))
    rhs = s3.scale(-h / 4.0, s3.sub(s3.add(momentum, force_minus), s3.scale(h / 2.0, gravity)))
    return ImplicitProblem(inertia=inertia, rhs=rhs, control_force=s3.scale(h / 2.0, control))


def finish_step(q: s3.Quat, xi: s3.Vec3, problem: ImplicitProblem, terms: RigidBodyTerms, step_size: float,
                ops: Ops, with_residual: bool = False) -> StepResult:
    """Steps 4–5 from a solution ``ξ`` of ``problem`` (however it was solved), and its residual."""
    h, inertia = step_size, problem.inertia
    increment = s3.exp(xi, ops)
    q_next = s3.multiply(q, increment)
    momentum_next = _end_momentum(q_next, increment, problem, terms, h)
    inertia_next, damping_next = _end_inertia_and_damping(q_next, problem, terms)
    if damping_next is None:
        omega_next = s3.scale(0.5, s3.solve3(inertia_next, momentum_next))
    else:  # (2 J + (h/2) D) ω_{k+1} = π_{k+1} + (h/2) D ω_{k+1}  — SPD, so always solvable.
        omega_next = s3.solve3(_end_momentum_map(inertia_next, damping_next, h), momentum_next)

    residual = None
    if with_residual:
        mismatch = s3.sub(implicit_lhs(xi, inertia, ops), problem.rhs)
        # Φ ≈ −Jξ and ξ ≈ hω/2: dividing by h·j/2 turns the mismatch into rad/s.
        inertia_scale = (inertia[0][0] + inertia[1][1] + inertia[2][2]) / 3.0
        squared = s3.dot(mismatch, mismatch)
        # A converged solve has mismatch exactly 0, where √ has no derivative; the safe
        # argument keeps the residual's derivatives finite (0 there) in every backend.
        nonzero = squared > 0.0
        norm = ops.where(nonzero, ops.sqrt(ops.where(nonzero, squared, 1.0 + 0.0 * squared)), 0.0 * squared)
        residual = norm * (2.0 / h) / inertia_scale
    return StepResult(q=q_next, omega=omega_next, residual=residual)  # type: ignore[arg-type]


def _end_momentum(q_next: s3.Quat, increment: s3.Quat, problem: ImplicitProblem, terms: RigidBodyTerms,
                  step_size: float) -> s3.Vec3:
    """``π_{k+1} + (h/2) D(q_{k+1}) ω_{k+1}``: everything in step 5 but the end-of-step damping."""
    h = step_size
    gravity_next = s3.H_apply(q_next, terms.potential_gradient(q_next))
    kinetic = s3.G_apply(increment, s3.matvec(problem.inertia, s3.imaginary(increment)))
    return s3.add(s3.sub(s3.scale(4.0 / h, kinetic), s3.scale(h / 2.0, gravity_next)), problem.control_force)


def _end_inertia_and_damping(q_next: s3.Quat, problem: ImplicitProblem,
                             terms: RigidBodyTerms) -> tuple[s3.Mat3, s3.Mat3 | None]:
    """``J(q_{k+1})`` of the Legendre map (``J(q_k)`` again when constant) and ``D(q_{k+1})`` or ``None``."""
    inertia_next = problem.inertia if terms.constant_inertia else terms.inertia(q_next)
    return inertia_next, terms.dissipation(q_next)


def _end_momentum_map(inertia_next: s3.Mat3, damping_next: s3.Mat3 | None, step_size: float) -> s3.Mat3:
    """``2 J + (h/2) D``: what :func:`_end_momentum` is of ``ω_{k+1}`` (SPD)."""
    if damping_next is None:
        return tuple(tuple(2.0 * inertia_next[i][j] for j in range(3)) for i in range(3))  # type: ignore[return-value]
    return tuple(tuple(2.0 * inertia_next[i][j] + (step_size / 2.0) * damping_next[i][j] for j in range(3))
                 for i in range(3))  # type: ignore[return-value]


def hinge_axis_of(terms: RigidBodyTerms) -> tuple[float, float, float] | None:
    """The hinge axis ``terms`` constrain the body to (their ``hinge_axis``), or ``None``."""
    return getattr(terms, "hinge_axis", None)


def hinge_basis(axis: tuple[float, float, float]) -> tuple[s3.Vec3, s3.Vec3]:
    """Two unit vectors completing the unit ``axis`` to a right-handed orthonormal basis (floats)."""
    # Start from the coordinate axis least aligned with the hinge: the cross product is then well
    # conditioned for any axis.
    least = min(range(3), key=lambda i: abs(axis[i]))
    start = tuple(1.0 if i == least else 0.0 for i in range(3))
    first = s3.cross(axis, start)
    norm = math.sqrt(s3.dot(first, first))
    first = s3.scale(1.0 / norm, first)
    return first, s3.cross(axis, first)  # type: ignore[return-value]


def _quadratic_form(matrix: s3.Mat3, axis: s3.Vec3) -> Any:
    return s3.dot(axis, s3.matvec(matrix, axis))


def hinge_step(q: s3.Quat, omega: s3.Vec3, u: tuple[Any, ...], terms: RigidBodyTerms, step_size: float,
               axis: tuple[float, float, float], ops: Ops, with_residual: bool = False) -> StepResult:
    """One step constrained to the hinge ``axis`` (module docstring, "On a hinge"): the same steps
    1–2 and 5 as :func:`fvin_step`, projected on ``a``, and step 3 solved exactly.

    ``φ`` exists while ``|2 aᵀC| ≤ aᵀJa`` (``h|θ̇| ≲ 1``); past it the step takes ``|φ| = π/4``
    with zero derivative, and the residual (the mismatch of ``aᵀΦ = aᵀC`` in rad/s) says so.
    """
    h = step_size
    problem = implicit_problem(q, omega, u, terms, h)
    inertia_along = _quadratic_form(problem.inertia, axis)
    sine = -2.0 * s3.dot(axis, problem.rhs) / inertia_along  # sin 2φ
    inside = sine * sine < 1.0
    cosine = ops.sqrt(ops.where(inside, 1.0 - sine * sine, 1.0 + 0.0 * sine))
    # Both branches as arrays of sine's type: torch.where of two Python floats would be float32.
    limit = 0.25 * math.pi * ops.where(sine >= 0.0, 1.0 + 0.0 * sine, -1.0 + 0.0 * sine)
    angle = ops.where(inside, 0.5 * ops.atan2(sine, cosine), limit)  # φ: the increment is exp(φ a)
    increment = (ops.cos(angle), *s3.scale(ops.sin(angle), axis))
    q_next = s3.multiply(q, increment)
    momentum_next = _end_momentum(q_next, increment, problem, terms, h)
    momentum_map = _end_momentum_map(*_end_inertia_and_damping(q_next, problem, terms), h)
    rate = s3.dot(axis, momentum_next) / _quadratic_form(momentum_map, axis)
    omega_next = s3.scale(rate, axis)

    residual = None
    if with_residual:
        mismatch = -0.5 * ops.sin(2.0 * angle) * inertia_along - s3.dot(axis, problem.rhs)
        nonzero = mismatch * mismatch > 0.0
        magnitude = ops.sqrt(ops.where(nonzero, mismatch * mismatch, 1.0 + 0.0 * mismatch))
        residual = ops.where(nonzero, magnitude, 0.0 * mismatch) * (2.0 / h) / inertia_along
    return StepResult(q=q_next, omega=omega_next, residual=residual)  # type: ignore[arg-type]


def step_residual(q: s3.Quat, omega: s3.Vec3, u: tuple[Any, ...], q_next: s3.Quat, omega_next: s3.Vec3,
                  terms: RigidBodyTerms, step_size: float, ops: Ops,
                  terms_next: RigidBodyTerms | None = None) -> tuple[Any, ...]:
    """The step's equations as a residual of both of its ends: 0 exactly when ``(q_next, ω_next)``
    is the converged step from ``(q, ω, u)`` (K → ∞ in :func:`fvin_step`); for sign-invariant terms
    the same for ``±q_next`` (other terms are read at ``q_next``'s own sign).

    Six components: ``Φ(ξ) − C`` (step 3, in the units of ``C``) with ``ξ = log(q* ⊗ q_next)``
    of the sign-aligned relative rotation, then step 5 as ``π_{k+1} + (h/2) D ω_{k+1}`` minus
    ``(2 J + (h/2) D) ω_{k+1}`` at ``q_next`` (momentum units). No Newton solve: this is the form
    an optimizer that treats both ends as unknowns enforces (the discrete Euler–Lagrange equations
    as constraints, as in discrete mechanics and optimal control). ``terms_next`` evaluates the
    terms at ``q_next`` (default: ``terms``) — a caller may give each end its own evaluation.
    """
    terms_next = terms if terms_next is None else terms_next
    problem = implicit_problem(q, omega, u, terms, step_size)
    relative = s3.multiply(s3.conjugate(q), q_next)
    increment = s3.scale(ops.where(relative[0] >= 0.0, 1.0, -1.0), relative)  # = exp(ξ), |ξ| ≤ π/2
    xi = s3.log(increment, ops)
    kinematic = s3.sub(implicit_lhs(xi, problem.inertia, ops), problem.rhs)
    momentum = _end_momentum(q_next, increment, problem, terms_next, step_size)
    momentum_map = _end_momentum_map(*_end_inertia_and_damping(q_next, problem, terms_next), step_size)
    dynamic = s3.sub(momentum, s3.matvec(momentum_map, omega_next))
    axis = hinge_axis_of(terms)
    if axis is None:
        return (*kinematic, *dynamic)
    # On a hinge: both equations along a (the reaction drops out), and the constraint itself — ξ and
    # ω_{k+1} along a — in the same units (scaled by aᵀJa, resp. aᵀ(2J + (h/2)D)a).
    across = hinge_basis(axis)
    inertia_along, map_along = _quadratic_form(problem.inertia, axis), _quadratic_form(momentum_map, axis)
    return (s3.dot(axis, kinematic), *(inertia_along * s3.dot(b, xi) for b in across),
            s3.dot(axis, dynamic), *(map_along * s3.dot(b, omega_next) for b in across))


def fvin_step(
    q: s3.Quat,
    omega: s3.Vec3,
    u: tuple[Any, ...],
    terms: RigidBodyTerms,
    step_size: float,
    newton_iters: int,
    ops: Ops,
    with_residual: bool = False,
) -> StepResult:
    """One forced S3FVIN step ``(q_k, ω_k, u_k) → (q_{k+1}, ω_{k+1})``; see the module docstring.
    Terms with a hinge axis take :func:`hinge_step` (``newton_iters`` is then not used)."""
    axis = hinge_axis_of(terms)
    if axis is not None:
        return hinge_step(q, omega, u, terms, step_size, axis, ops, with_residual)
    problem = implicit_problem(q, omega, u, terms, step_size)
    xi = solve_implicit(problem.rhs, problem.inertia, newton_iters, ops)
    return finish_step(q, xi, problem, terms, step_size, ops, with_residual)


def kinetic_energy(q: s3.Quat, omega: s3.Vec3, terms: RigidBodyTerms) -> Any:
    """``½ ωᵀ J(q) ω``."""
    return 0.5 * s3.dot(omega, s3.matvec(terms.inertia(q), omega))


def total_energy(q: s3.Quat, omega: s3.Vec3, terms: RigidBodyTerms) -> Any:
    """``E = ½ ωᵀ J ω + U(q)`` in the model's own (learned) scale."""
    return kinetic_energy(q, omega, terms) + terms.potential(q)
