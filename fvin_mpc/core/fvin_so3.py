"""The forced LieFVIN step on SO(3) (paper eq. 3.9; Duruisseaux et al.'s SO3FVIN), written once.

The baseline the paper compares S3FVIN with: the same rigid body integrated on 3×3 rotation
matrices. Discrete Lagrangian (3.9) ``L_d = (1/h) tr((F_k − I) J̃) − (h/2)(U(R_k) + U(R_{k+1}))``,
``F_k = R_kᵀR_{k+1}``, ``J̃ = J − ½ tr(J) I``; discrete forces as eq. (3.6),
``f⁻ = (h/2)(τ(R_k) u_k − D ω_k)``, ``f⁺ = (h/2)(τ(R_k) u_k − D ω_{k+1})`` (body-frame torques).
Left-trivializing the forced discrete Euler–Lagrange equations with ``δR = R[η]×`` gives, with
``Π = Jω`` and the potential torque ``M`` (``d/dε U(R exp(ε[η]×)) = −ηᵀM``):

1. ``a = h (J(R_k) ω_k + (h/2) M(R_k) + f⁻)``.
2. Solve ``(F J_d − J_d Fᵀ)^∨ = a`` (``J_d = ½ tr(J) I − J``) for ``F = exp([f]×)``: in the
   rotation vector ``f`` this is ``Γ(f) := (sin|f|/|f|) J f + ((1 − cos|f|)/|f|²) f × J f = a``,
   solved by Newton from ``f = 0`` with the analytic Jacobian (:func:`implicit_lhs_jacobian`);
   ``∂Γ/∂f(0) = J``, so the first iterate is ``J⁻¹a``.
3. ``R_{k+1} = R_k F``.
4. ``Π_{k+1} = (1/h)(J_d F − Fᵀ J_d)^∨ + (h/2) M(R_{k+1}) + f⁺``, where
   ``(J_d F − Fᵀ J_d)^∨ = (sin|f|/|f|) J f − ((1 − cos|f|)/|f|²) f × J f``; then
   ``(J(R_{k+1}) + (h/2) D) ω_{k+1} = Π_{k+1} + (h/2) D ω_{k+1}`` (one 3×3 solve).

Relation to the S³ step (:mod:`fvin_mpc.core.fvin`): under the covering map the discrete
Lagrangians coincide — ``tr((F − I)J̃) = 2 sin²|ξ| nᵀJn`` for ``F = R(exp ξ)``, which is
eq. (3.14)'s kinetic term — and ``Γ(2ξ) = −2 Φ(ξ)`` exactly, so Newton's iterates correspond
(``f = 2ξ``) for every number of iterations ``K``. With the S³ gains twice the SO(3) torques
(``g = 2τ``, ``D_S³ = 2 D``; ``DESIGN.md``'s factor of two) the two steps are the same map up to
rounding; ``tests/test_so3fvin.py`` checks it. What differs in the learned models is only what
the networks read (:mod:`fvin_mpc.core.networks_so3`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

from fvin_mpc.core import s3, so3
from fvin_mpc.core.backend import Ops
from fvin_mpc.core.fvin import SINGULAR_JACOBIAN, clamp_increment, guarded_solve3


class RotationTerms(Protocol):
    """The learned (or closed-form) parts of a rigid body on SO(3), evaluated on components.

    All methods take a rotation matrix ``R`` (row tuples of components): ``inertia`` a symmetric
    3×3 ``J``; ``potential_torque`` the body torque ``M`` of the potential
    (``d/dε U(R exp(ε[η]×)) = −ηᵀM``); ``control_gain`` 3 rows of ``m`` entries, the body torque
    per unit control (half the S³ model's ``g``); ``dissipation`` a PSD ``D`` (torque ``−Dω``) or ``None``.
    """

    control_dim: int
    constant_inertia: bool

    def inertia(self, r: so3.Mat3) -> so3.Mat3: ...
    def potential(self, r: so3.Mat3) -> Any: ...
    def potential_torque(self, r: so3.Mat3) -> so3.Vec3: ...
    def control_gain(self, r: so3.Mat3) -> tuple[tuple[Any, ...], ...]: ...
    def dissipation(self, r: so3.Mat3) -> so3.Mat3 | None: ...


@dataclass(frozen=True)
class SO3StepResult:
    """One SO(3) step: ``rotation`` (row tuples), ``omega``, and ``residual`` (rad/s) or ``None``.

    ``residual`` is ``|Γ(f_K) − a| / (h · tr(J)/3)``, an angular-velocity error in rad/s — the same
    number as :attr:`fvin_mpc.core.fvin.StepResult.residual` for the same physics."""

    rotation: so3.Mat3
    omega: so3.Vec3
    residual: Any | None


def torque_from_euclidean_gradient(r: so3.Mat3, gradient: so3.Mat3) -> so3.Vec3:
    """``M = (GᵀR − RᵀG)^∨ = Σ_k R_k × G_k`` (rows) for the Euclidean gradient ``G = ∂U/∂R``."""
    torque = s3.cross(r[0], gradient[0])
    for k in (1, 2):
        torque = s3.add(torque, s3.cross(r[k], gradient[k]))
    return torque  # type: ignore[return-value]


def implicit_lhs(f: so3.Vec3, inertia: so3.Mat3, ops: Ops) -> so3.Vec3:
    """``Γ(f) = (F J_d − J_d Fᵀ)^∨`` for ``F = exp([f]×)`` (left-hand side of step 2)."""
    _, s, c = so3.rodrigues_coefficients(f, ops)
    jf = s3.matvec(inertia, f)
    return s3.add(s3.scale(s, jf), s3.scale(c, s3.cross(f, jf)))  # type: ignore[return-value]


def implicit_lhs_jacobian(f: so3.Vec3, inertia: so3.Mat3, ops: Ops) -> tuple[so3.Vec3, so3.Mat3]:
    """``Γ(f)`` and its analytic Jacobian (rows).

    With ``t = |f|²``, ``s = sin|f|/|f|``, ``c = (1 − cos|f|)/|f|²`` and their ``t``-derivatives:
    ``∂Γ/∂f = s J + 2 s' (Jf) fᵀ + c ([f]× J − [Jf]×) + 2 c' (f × Jf) fᵀ``.
    """
    _, s, c, ds, dc = so3.rodrigues_coefficients(f, ops, with_derivative=True)
    jf = s3.matvec(inertia, f)
    f_cross_jf = s3.cross(f, jf)
    gamma = s3.add(s3.scale(s, jf), s3.scale(c, f_cross_jf))
    # Columns of [f]× J are f × (columns of J); J is symmetric so its columns are its rows.
    f_cross_j = [s3.cross(f, inertia[k]) for k in range(3)]
    jf_hat = s3.skew(jf)
    jacobian = tuple(
        tuple(s * inertia[i][j] + 2.0 * ds * jf[i] * f[j] + c * (f_cross_j[j][i] - jf_hat[i][j])
              + 2.0 * dc * f_cross_jf[i] * f[j] for j in range(3))
        for i in range(3))
    return gamma, jacobian  # type: ignore[return-value]


def solve_implicit(rhs: so3.Vec3, inertia: so3.Mat3, newton_iters: int, ops: Ops) -> so3.Vec3:
    """``K = newton_iters`` Newton iterations on ``Γ(f) = a`` from ``f = 0``.

    The safeguards are the S³ step's (:func:`fvin_mpc.core.fvin.solve_implicit`) at ``f = 2ξ``: the
    iterate is kept within ``|f| ≤ 2 · MAX_INCREMENT`` and the Newton determinant is floored."""
    if newton_iters < 1:
        raise ValueError(f"newton_iters must be >= 1, got {newton_iters}")

    def clamp(f: so3.Vec3) -> so3.Vec3:
        return s3.scale(2.0, clamp_increment(s3.scale(0.5, f), ops))  # type: ignore[return-value]

    f = clamp(s3.solve3(inertia, rhs))  # exact first iterate: ∂Γ/∂f(0) = J
    det_floor = SINGULAR_JACOBIAN * s3.determinant(inertia)
    for _ in range(newton_iters - 1):
        gamma, jacobian = implicit_lhs_jacobian(f, inertia, ops)
        f = clamp(s3.sub(f, guarded_solve3(jacobian, s3.sub(gamma, rhs), det_floor, ops)))
    return f


def so3_step(
    rotation: so3.Mat3,
    omega: so3.Vec3,
    u: tuple[Any, ...],
    terms: RotationTerms,
    step_size: float,
    newton_iters: int,
    ops: Ops,
    with_residual: bool = False,
) -> SO3StepResult:
    """One forced SO3FVIN step ``(R_k, ω_k, u_k) → (R_{k+1}, ω_{k+1})``; see the module docstring."""
    h = step_size
    inertia = terms.inertia(rotation)
    control_torque = s3.matvec(terms.control_gain(rotation), u)
    damping = terms.dissipation(rotation)
    applied = control_torque if damping is None else s3.sub(control_torque, s3.matvec(damping, omega))
    momentum = s3.matvec(inertia, omega)
    rhs = s3.scale(h, s3.add(momentum, s3.scale(h / 2.0, s3.add(terms.potential_torque(rotation), applied))))
    f = solve_implicit(rhs, inertia, newton_iters, ops)

    rotation_next = s3.mattmat(rotation, so3.exp(f, ops))
    _, s, c = so3.rodrigues_coefficients(f, ops)
    jf = s3.matvec(inertia, f)
    kinetic = s3.sub(s3.scale(s, jf), s3.scale(c, s3.cross(f, jf)))  # (J_d F − Fᵀ J_d)^∨
    # Π_{k+1} + (h/2) D ω_{k+1}: everything in step 4 but the end-of-step damping.
    momentum_next = s3.add(s3.scale(1.0 / h, kinetic),
                           s3.scale(h / 2.0, s3.add(terms.potential_torque(rotation_next), control_torque)))
    inertia_next = inertia if terms.constant_inertia else terms.inertia(rotation_next)
    damping_next = terms.dissipation(rotation_next)
    if damping_next is not None:
        inertia_next = tuple(tuple(inertia_next[i][j] + (h / 2.0) * damping_next[i][j] for j in range(3))
                             for i in range(3))
    omega_next = s3.solve3(inertia_next, momentum_next)  # type: ignore[arg-type]

    residual = None
    if with_residual:
        mismatch = s3.sub(implicit_lhs(f, inertia, ops), rhs)
        squared = s3.dot(mismatch, mismatch)
        nonzero = squared > 0.0  # √ has no derivative at 0: keep it finite there (as the S³ step does)
        norm = ops.where(nonzero, ops.sqrt(ops.where(nonzero, squared, 1.0 + 0.0 * squared)), 0.0 * squared)
        residual = norm / (h * (inertia[0][0] + inertia[1][1] + inertia[2][2]) / 3.0)
    return SO3StepResult(rotation=rotation_next, omega=omega_next, residual=residual)  # type: ignore[arg-type]


def total_energy(rotation: so3.Mat3, omega: so3.Vec3, terms: RotationTerms) -> Any:
    """``E = ½ ωᵀ J(R) ω + U(R)`` in the model's own scale."""
    return 0.5 * s3.dot(omega, s3.matvec(terms.inertia(rotation), omega)) + terms.potential(rotation)


class PivotedRigidBodySO3Terms:
    """A closed-form :class:`~fvin_mpc.core.rigid_body.PivotedRigidBody` as :class:`RotationTerms`
    (physical torques: the actuator axes and the joint damping themselves, not doubled)."""

    constant_inertia = True

    def __init__(self, body: Any, ops: Ops) -> None:
        self.body = body
        self.ops = ops
        self.control_dim = body.control_dim

    def _constant(self, matrix: Any, r: so3.Mat3) -> tuple[tuple[Any, ...], ...]:
        zero = 0.0 * r[0][0]
        return tuple(tuple(entry + zero for entry in row) for row in matrix)

    def inertia(self, r: so3.Mat3) -> so3.Mat3:
        return self._constant(self.body.inertia, r)  # type: ignore[return-value]

    def potential(self, r: so3.Mat3) -> Any:
        """``U = m g (z_com(R) − z_com(I))`` with ``z_com = (R c)_z``; zero when hanging at rest."""
        c = self.body.center_of_mass
        v = getattr(self.body, "vertical", (0.0, 0.0, 1.0))
        if tuple(v) != (0.0, 0.0, 1.0):  # heights along a tilted hinge's "up" (rigid_body.from_mujoco)
            height = sum(v[i] * s3.dot(r[i], c) for i in range(3) if v[i] != 0.0)
            return self.body.mass_gravity * (height - s3.dot(v, c))
        return self.body.mass_gravity * (s3.dot(r[2], c) - c[2])

    def potential_torque(self, r: so3.Mat3) -> so3.Vec3:
        # ∂U/∂R has one nonzero row, the third: m g cᵀ.
        zero = 0.0 * r[0][0]
        weighted = s3.scale(self.body.mass_gravity, self.body.center_of_mass)
        v = getattr(self.body, "vertical", (0.0, 0.0, 1.0))
        if tuple(v) != (0.0, 0.0, 1.0):  # ∂U/∂R = m g v cᵀ
            gradient = tuple(tuple(v[i] * w + zero for w in weighted) for i in range(3))
            return torque_from_euclidean_gradient(r, gradient)  # type: ignore[arg-type]
        gradient = ((zero, zero, zero), (zero, zero, zero), tuple(w + zero for w in weighted))
        return torque_from_euclidean_gradient(r, gradient)  # type: ignore[arg-type]

    def control_gain(self, r: so3.Mat3) -> tuple[tuple[Any, ...], ...]:
        return self._constant(self.body.actuator_axes, r)

    def dissipation(self, r: so3.Mat3) -> so3.Mat3 | None:
        if self.body.damping == 0.0:
            return None
        d = self.body.damping
        return self._constant(((d, 0.0, 0.0), (0.0, d, 0.0), (0.0, 0.0, d)), r)  # type: ignore[return-value]
