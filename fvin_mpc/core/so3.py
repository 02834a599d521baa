"""The rotation group SO(3) on 3×3 matrices, written once for every backend.

The SO(3) counterpart of :mod:`fvin_mpc.core.s3`, for the LieFVIN baseline
(:mod:`fvin_mpc.core.fvin_so3`). Values are tuples of components (:mod:`fvin_mpc.core.backend`):
a matrix is a tuple of three row tuples, a vector a 3-tuple; the vector and matrix helpers
(``dot``, ``cross``, ``matvec``, ``mattmat``, ``skew``, ``solve3``) are :mod:`~fvin_mpc.core.s3`'s.

Conventions (``DESIGN.md``): ``ω`` is the body-frame angular velocity, ``Ṙ = R[ω]×``; a step
``R_{k+1} = R_k exp([f]×)`` rotates by ``|f|`` about ``f`` (the rotation vector — ``f = 2ξ`` for
the S³ step's ``q_{k+1} = q_k ⊗ exp(ξ)``). ``R(q)`` is eq. (3.10) (:func:`fvin_mpc.core.s3.rotation_matrix`).

Smoothness at ``f = 0``: every coefficient is a function of the half angle through
:func:`fvin_mpc.core.s3.trig_of_sqrt` (Taylor branch near 0), so no value or derivative is NaN there.
"""

from __future__ import annotations

from typing import Any

from fvin_mpc.core import s3
from fvin_mpc.core.backend import Ops

Mat3 = s3.Mat3
Vec3 = s3.Vec3

#: Below this squared component a branch of :func:`quaternion_from_rotation` is never selected
#: (the selected one has a squared component ≥ 1/4); it only keeps the discarded branches'
#: square roots and divisions finite, so reverse-mode derivatives through ``where`` stay finite.
_BRANCH_FLOOR = 1e-6


def transpose(m: Mat3) -> Mat3:
    return tuple(tuple(m[i][j] for i in range(3)) for j in range(3))  # type: ignore[return-value]


def vee(m: Mat3) -> Vec3:
    """``(m − mᵀ)^∨ / 2``: the axial vector of ``m``'s skew part (``vee([v]×) = v``)."""
    return (0.5 * (m[2][1] - m[1][2]), 0.5 * (m[0][2] - m[2][0]), 0.5 * (m[1][0] - m[0][1]))


def rodrigues_coefficients(f: Vec3, ops: Ops, with_derivative: bool = False) -> tuple[Any, ...]:
    """``(cos|f|, sin|f|/|f|, (1 − cos|f|)/|f|²)`` and, if asked, the derivatives of the last two
    in ``t = |f|²``.

    Written on the half angle ``a = |f|/2`` (``τ = t/4``, ``σ = sin a/a``, ``γ = cos a``):
    ``sin|f|/|f| = σγ``, ``(1 − cos|f|)/|f|² = σ²/2``, ``cos|f| = 1 − τσ²·2``; with
    ``dγ/dτ = −σ/2`` and ``σ' = dσ/dτ`` the ``t``-derivatives are ``(σ'γ − σ²/2)/4`` and ``σσ'/4``.
    """
    tau = 0.25 * s3.dot(f, f)
    gamma, sigma, *rest = s3.trig_of_sqrt(tau, ops, with_derivative=with_derivative)
    sin_over = sigma * gamma
    one_minus_cos_over = 0.5 * sigma * sigma
    cosine = 1.0 - 2.0 * tau * sigma * sigma
    if not with_derivative:
        return cosine, sin_over, one_minus_cos_over
    dsigma = rest[0]
    return cosine, sin_over, one_minus_cos_over, 0.25 * (dsigma * gamma - 0.5 * sigma * sigma), 0.25 * sigma * dsigma


def exp(f: Vec3, ops: Ops) -> Mat3:
    """``exp([f]×) = I + (sin|f|/|f|)[f]× + ((1 − cos|f|)/|f|²)[f]×²`` (Rodrigues)."""
    _, s, c = rodrigues_coefficients(f, ops)
    k = s3.skew(f)
    k2 = s3.mattmat(k, k)
    one = 1.0 + 0.0 * f[0]
    return tuple(tuple((one if i == j else 0.0 * one) + s * k[i][j] + c * k2[i][j] for j in range(3))
                 for i in range(3))  # type: ignore[return-value]


def quaternion_from_rotation(r: Mat3, ops: Ops) -> s3.Quat:
    """A unit-quaternion preimage ``q`` of ``R`` under eq. (3.10) (``R(q) = R``), by Shepperd's method.

    The branch is picked by the largest of ``4w² = 1 + tr R``, ``4x² = 1 + 2R₀₀ − tr R``, … and that
    component is made positive. No continuous choice exists on all of SO(3), so the returned sign
    jumps where the branch changes (e.g. at a hinge angle of −π/2 for rotations about one axis);
    ``q`` and ``−q`` are the same rotation, so sign-invariant uses are unaffected.
    """
    trace = r[0][0] + r[1][1] + r[2][2]
    squares = (1.0 + trace, 1.0 + 2.0 * r[0][0] - trace, 1.0 + 2.0 * r[1][1] - trace, 1.0 + 2.0 * r[2][2] - trace)
    # Off-diagonal sums and differences: 4wx, 4wy, 4wz, 4xy, 4xz, 4yz.
    wx, wy, wz = r[2][1] - r[1][2], r[0][2] - r[2][0], r[1][0] - r[0][1]
    xy, xz, yz = r[0][1] + r[1][0], r[0][2] + r[2][0], r[1][2] + r[2][1]
    products = (  # row i: 4 q_i q_j for j = 0..3 (diagonal entries unused)
        (None, wx, wy, wz), (wx, None, xy, xz), (wy, xy, None, yz), (wz, xz, yz, None),
    )
    candidates = []
    for i in range(4):
        safe = ops.where(squares[i] > _BRANCH_FLOOR, squares[i], _BRANCH_FLOOR + 0.0 * squares[i])
        root = ops.sqrt(safe)  # 2|q_i|
        candidates.append(tuple(0.5 * root if j == i else products[i][j] / (2.0 * root) for j in range(4)))
    # Choose the branch of the largest square; ties go to the earlier branch.
    best, best_square = candidates[0], squares[0]
    for i in range(1, 4):
        better = squares[i] > best_square
        best = tuple(ops.where(better, a, b) for a, b in zip(candidates[i], best))
        best_square = ops.where(better, squares[i], best_square)
    return best  # type: ignore[return-value]

