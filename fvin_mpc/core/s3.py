"""The unit-quaternion group S³ and 3×3 linear algebra, written once for every backend.

Conventions (``DESIGN.md``): ``q = (w, x, y, z)``, Hamilton product, ``q`` and ``-q``
are the same rotation; ``exp`` of a pure quaternion ``(0, v)`` is
``(cos|v|, sin|v| v/|v|)`` — no half angle, so ``q ⊗ exp(ξ)`` rotates by ``2|ξ|``.

Values are tuples of *components* (see :mod:`fvin_mpc.backend`): a quaternion is a
4-tuple, a vector a 3-tuple, a matrix a tuple of row tuples. Components may be
torch tensors, NumPy arrays, CasADi symbols or floats. Only :class:`~fvin_mpc.core.backend.Ops`
leaf functions (``sin``, ``cos``, ``sqrt``, ``where``, ``atan2``) are backend specific.

Smoothness at zero: ``sin|v|/|v|`` and friends are functions of ``t = |v|²`` with a
Taylor branch below :data:`SERIES_THRESHOLD`; the other branch sees a "safe" ``t`` so
that neither branch produces NaN in values or (reverse-mode) derivatives at ``v = 0``.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from fvin_mpc.core.backend import Ops

Quat = tuple[Any, Any, Any, Any]
Vec3 = tuple[Any, Any, Any]
Mat3 = tuple[Vec3, Vec3, Vec3]

#: Below this value of ``t = |v|²`` the Taylor series are used (their truncation error
#: is below 1e-17 there, and the closed forms lose digits to cancellation).
SERIES_THRESHOLD = 1e-2
#: ``atan2(|v|, w)/|v|`` has no cancellation, so :func:`log` needs its series only to
#: keep derivatives finite at ``v = 0``.
LOG_SERIES_THRESHOLD = 1e-6


# --------------------------------------------------------------------------- vectors
def dot(a: Sequence[Any], b: Sequence[Any]) -> Any:
    result = a[0] * b[0]
    for a_i, b_i in zip(a[1:], b[1:]):
        result = result + a_i * b_i
    return result


def cross(a: Vec3, b: Vec3) -> Vec3:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def add(a: Sequence[Any], b: Sequence[Any]) -> tuple:
    return tuple(a_i + b_i for a_i, b_i in zip(a, b))


def sub(a: Sequence[Any], b: Sequence[Any]) -> tuple:
    return tuple(a_i - b_i for a_i, b_i in zip(a, b))


def scale(s: Any, a: Sequence[Any]) -> tuple:
    return tuple(s * a_i for a_i in a)


# --------------------------------------------------------------------------- matrices
def matvec(m: Sequence[Sequence[Any]], v: Sequence[Any]) -> tuple:
    """``m @ v`` for a matrix given as row tuples (any shape)."""
    return tuple(dot(row, v) for row in m)


def mattmat(a: Mat3, b: Mat3) -> Mat3:
    """``a @ b`` for 3×3 matrices."""
    columns = tuple(tuple(b[i][j] for i in range(3)) for j in range(3))
    return tuple(tuple(dot(row, col) for col in columns) for row in a)  # type: ignore[return-value]


def skew(v: Vec3) -> Mat3:
    """``[v]×`` with ``[v]× x = v × x``."""
    return ((0.0 * v[0], -v[2], v[1]), (v[2], 0.0 * v[0], -v[0]), (-v[1], v[0], 0.0 * v[0]))


def determinant(m: Mat3) -> Any:
    return dot(m[0], cross(m[1], m[2]))


def solve3(m: Mat3, r: Vec3) -> Vec3:
    """``m⁻¹ r`` by Cramer's rule (exact for 3×3; ``m`` must be non-singular)."""
    c0, c1, c2 = cross(m[1], m[2]), cross(m[2], m[0]), cross(m[0], m[1])
    # Rows of the adjugate transposed are c0, c1, c2: m⁻¹ = [c0 c1 c2] / det.
    det = dot(m[0], c0)
    return tuple((c0[i] * r[0] + c1[i] * r[1] + c2[i] * r[2]) / det for i in range(3))  # type: ignore[return-value]


def symmetric_from_cholesky(lower: Sequence[Any], epsilon: float = 0.0) -> Mat3:
    """``L Lᵀ + εI`` from the lower triangle ``lower = (L00, L11, L22, L10, L20, L21)``."""
    l00, l11, l22, l10, l20, l21 = lower
    j00 = l00 * l00 + epsilon
    j11 = l10 * l10 + l11 * l11 + epsilon
    j22 = l20 * l20 + l21 * l21 + l22 * l22 + epsilon
    j10 = l10 * l00
    j20 = l20 * l00
    j21 = l20 * l10 + l21 * l11
    return ((j00, j10, j20), (j10, j11, j21), (j20, j21, j22))


# --------------------------------------------------------------------------- S³
def multiply(p: Quat, q: Quat) -> Quat:
    """Hamilton product ``p ⊗ q``."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return (
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    )


def conjugate(q: Quat) -> Quat:
    return (q[0], -q[1], -q[2], -q[3])


def imaginary(q: Quat) -> Vec3:
    return (q[1], q[2], q[3])


def negate(q: Quat) -> Quat:
    return (-q[0], -q[1], -q[2], -q[3])


def _series(t: Any, coefficients: Sequence[float]) -> Any:
    """``Σ c_i tⁱ`` in Horner form."""
    result = coefficients[-1]
    for c in reversed(coefficients[:-1]):
        result = c + t * result
    return result


# Taylor coefficients in t = |v|² (truncation error < 1e-17 for t < SERIES_THRESHOLD).
_COS_SERIES = (1.0, -1 / 2, 1 / 24, -1 / 720, 1 / 40320, -1 / 3628800)
_SINC_SERIES = (1.0, -1 / 6, 1 / 120, -1 / 5040, 1 / 362880, -1 / 39916800)
_SINC_DERIVATIVE_SERIES = (-1 / 6, 1 / 60, -1 / 1680, 1 / 90720, -1 / 7983360)


def trig_of_sqrt(t: Any, ops: Ops, with_derivative: bool = False) -> tuple[Any, ...]:
    """``(cos√t, sin√t/√t)`` and, if asked, ``d/dt[sin√t/√t] = (cos√t − sin√t/√t)/(2t)``.

    Smooth at ``t = 0``: below :data:`SERIES_THRESHOLD` the Taylor series are used and the
    closed forms see a safe ``t``, so neither branch produces NaN in values or derivatives.
    """
    small = t < SERIES_THRESHOLD
    safe_t = ops.where(small, SERIES_THRESHOLD + 0.0 * t, t)
    root = ops.sqrt(safe_t)
    cos_closed = ops.cos(root)
    sinc_closed = ops.sin(root) / root
    cos_value = ops.where(small, _series(t, _COS_SERIES), cos_closed)
    sinc_value = ops.where(small, _series(t, _SINC_SERIES), sinc_closed)
    if not with_derivative:
        return cos_value, sinc_value
    derivative_closed = (cos_closed - sinc_closed) / (2.0 * safe_t)
    derivative = ops.where(small, _series(t, _SINC_DERIVATIVE_SERIES), derivative_closed)
    return cos_value, sinc_value, derivative


def cos_sqrt(t: Any, ops: Ops) -> Any:
    """``cos(√t)``, smooth at ``t = 0``."""
    return trig_of_sqrt(t, ops)[0]


def sinc_sqrt(t: Any, ops: Ops) -> Any:
    """``sin(√t)/√t``, smooth at ``t = 0``."""
    return trig_of_sqrt(t, ops)[1]


def sinc_sqrt_derivative(t: Any, ops: Ops) -> Any:
    """``d/dt [sin(√t)/√t]``, smooth at ``t = 0`` (value −1/6)."""
    return trig_of_sqrt(t, ops, with_derivative=True)[2]


def exp(v: Vec3, ops: Ops) -> Quat:
    """``exp((0, v)) = (cos|v|, sin|v| v/|v|)`` — the unit quaternion rotating by ``2|v|``."""
    c, s = trig_of_sqrt(dot(v, v), ops)
    return (c, s * v[0], s * v[1], s * v[2])


def log(q: Quat, ops: Ops) -> Vec3:
    """Inverse of :func:`exp` for unit ``q``: ``v`` with ``|v| ≤ π``, ``exp(v) = q``.

    Not sign invariant: ``log(-q)`` is the other branch. Use :func:`geodesic_angle` for
    a sign-invariant distance.
    """
    w = q[0]
    t = q[1] * q[1] + q[2] * q[2] + q[3] * q[3]
    # Near the identity (t small, w > 0) angle/|v| = asin(s)/s is a series in t = s².
    # Near -1 (t small, w < 0) the closed form is fine unless t is exactly 0, where
    # log(-1) has no unique direction and 0 is returned.
    near_identity = ops.where(w > 0.0, ops.where(t < LOG_SERIES_THRESHOLD, 1.0, 0.0), 0.0) > 0.5
    safe_t = ops.where(near_identity, 1.0 + 0.0 * t, ops.where(t > 0.0, t, 1.0 + 0.0 * t))
    norm_v = ops.sqrt(safe_t)
    ratio_closed = ops.atan2(norm_v, w) / norm_v
    ratio_series = 1.0 + t / 6.0 + 3.0 * t * t / 40.0 + 5.0 * t * t * t / 112.0 + 35.0 * t**4 / 1152.0
    ratio = ops.where(near_identity, ratio_series, ratio_closed)
    return (ratio * q[1], ratio * q[2], ratio * q[3])


def rotation_matrix(q: Quat) -> Mat3:
    """``R(q)`` of eq. (3.10); ``R(q) = R(-q)``."""
    w, x, y, z = q
    return (
        (w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z),
    )


def axis_angle(q: Quat, p: Quat, axis: Vec3) -> float:
    """Angle (rad, in ``[0, π]``) between the world directions of the body-fixed ``axis`` at
    orientations ``q`` and ``p`` (floats): a pivoted body's tilt from upright when ``axis`` is its centre
    of mass's direction and ``p`` the goal, whatever the turn about the vertical."""
    here, there = matvec(rotation_matrix(q), axis), matvec(rotation_matrix(p), axis)
    return math.atan2(math.sqrt(sum(c * c for c in cross(here, there))), float(dot(here, there)))


def G_apply(q: Quat, x: Vec3) -> Vec3:
    """``G(q) x`` with ``G(q) = q_s I − [q_v]×`` (eq. 3.16)."""
    qv = imaginary(q)
    c = cross(qv, x)
    return (q[0] * x[0] - c[0], q[0] * x[1] - c[1], q[0] * x[2] - c[2])


def G_transpose_apply(q: Quat, x: Vec3) -> Vec3:
    """``G(q)ᵀ x = Im(q ⊗ (0, x))``."""
    qv = imaginary(q)
    c = cross(qv, x)
    return (q[0] * x[0] + c[0], q[0] * x[1] + c[1], q[0] * x[2] + c[2])


def H_apply(q: Quat, y: Quat) -> Vec3:
    """``H(q) y`` with ``H(q) = [−q_v, G(q)]`` (3×4): left-trivializes a gradient in R⁴."""
    g = G_apply(q, imaginary(y))
    return (g[0] - q[1] * y[0], g[1] - q[2] * y[0], g[2] - q[3] * y[0])


def H_transpose_apply(q: Quat, x: Vec3) -> Quat:
    """``H(q)ᵀ x = q ⊗ (0, x)``."""
    return multiply(q, (0.0 * x[0], x[0], x[1], x[2]))


def sign_invariant_distance(q: Quat, p: Quat) -> Any:
    """``1 − ⟨q, p⟩²`` — zero iff ``q = ±p``; equals ``sin²(angle/2)`` for unit inputs."""
    d = dot(q, p)
    return 1.0 - d * d


def geodesic_angle(q: Quat, p: Quat, ops: Ops) -> Any:
    """Rotation angle in ``[0, π]`` between the rotations of unit ``q`` and ``p``."""
    d = dot(q, p)
    c = d * d
    # angle = 2 acos|d| = 2 atan2(√(1−d²), |d|); written with squares for sign invariance.
    return 2.0 * ops.atan2(ops.sqrt(ops.where(1.0 - c > 0.0, 1.0 - c, 0.0 * c)), ops.sqrt(c))


def geodesic_angles(q: Any, p: Any) -> np.ndarray:
    """:func:`geodesic_angle` of NumPy arrays of unit quaternions, shape ``(..., 4)`` each (broadcast), one angle in
    ``[0, π]`` per leading index: ``2 arccos |⟨q, p⟩|``, the inner product summed over the last axis in order and
    clipped to ``[0, 1]``. The form recorded states are judged by (an episode's attitude error, a gate near the
    goal): below about 3e-8 rad it reads 0 (the cosine's last bit), far below any tolerance it is compared with,
    and it is never differentiated; :func:`geodesic_angle` is the one for every backend and for angles near zero."""
    inner = np.sum(np.asarray(q, dtype=float) * np.asarray(p, dtype=float), axis=-1)
    return 2.0 * np.arccos(np.clip(np.abs(inner), 0.0, 1.0))
