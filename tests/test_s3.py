"""S³ algebra: identities checked in NumPy (float64), torch and CasADi."""

import numpy as np
import pytest

from fvin_mpc.core import s3
from fvin_mpc.core.backend import get_ops

NP = get_ops("numpy")


def random_unit_quaternions(n, seed=0):
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def components(array):
    return tuple(array[..., i] for i in range(array.shape[-1]))


def test_G_transpose_is_imaginary_part_of_product():
    q = components(random_unit_quaternions(50))
    x = components(np.random.default_rng(1).normal(size=(50, 3)))
    expected = s3.imaginary(s3.multiply(q, (0.0 * x[0], *x)))
    np.testing.assert_allclose(s3.G_transpose_apply(q, x), expected, atol=1e-15)
    # G(q) itself is qs I − [qv]×, so Gᵀ x computed from the matrix agrees too.
    G = np.stack([np.stack(row, -1) for row in ((q[0], q[3], -q[2]), (-q[3], q[0], q[1]), (q[2], -q[1], q[0]))], -2)
    np.testing.assert_allclose(np.stack(s3.G_apply(q, x), -1), np.einsum("nij,nj->ni", G, np.stack(x, -1)), atol=1e-15)


def test_H_transpose_is_product_with_pure_quaternion_and_H_is_its_adjoint():
    rng = np.random.default_rng(2)
    q = components(random_unit_quaternions(50))
    x = components(rng.normal(size=(50, 3)))
    y = components(rng.normal(size=(50, 4)))
    np.testing.assert_allclose(s3.H_transpose_apply(q, x), s3.multiply(q, (0.0 * x[0], *x)), atol=1e-15)
    # ⟨H y, x⟩ = ⟨y, Hᵀ x⟩ and H annihilates q itself (the normal direction of S³).
    np.testing.assert_allclose(s3.dot(s3.H_apply(q, y), x), s3.dot(y, s3.H_transpose_apply(q, x)), atol=1e-14)
    np.testing.assert_allclose(s3.H_apply(q, q), np.zeros((3, 50)), atol=1e-15)


def test_rotation_matrix_is_orthonormal_sign_invariant_and_a_homomorphism():
    p = components(random_unit_quaternions(30, 3))
    q = components(random_unit_quaternions(30, 4))
    R = lambda a: np.moveaxis(np.array(s3.rotation_matrix(a)), -1, 0)  # noqa: E731
    np.testing.assert_allclose(R(q), R(s3.negate(q)), atol=0)
    np.testing.assert_allclose(
        np.einsum("nji,njk->nik", R(q), R(q)), np.broadcast_to(np.eye(3), (30, 3, 3)), atol=1e-14
    )
    np.testing.assert_allclose(np.linalg.det(R(q)), 1.0, atol=1e-14)
    np.testing.assert_allclose(R(s3.multiply(p, q)), R(p) @ R(q), atol=1e-14)
    # R(q) x = Im(q ⊗ (0,x) ⊗ q*)
    x = np.random.default_rng(5).normal(size=(30, 3))
    rotated = s3.imaginary(s3.multiply(s3.multiply(q, (0.0 * x[:, 0], *components(x))), s3.conjugate(q)))
    np.testing.assert_allclose(np.stack(rotated, -1), np.einsum("nij,nj->ni", R(q), x), atol=1e-14)


@pytest.mark.parametrize("scale", [0.0, 1e-12, 1e-7, 1e-3, 0.09, 0.11, 1.0, 3.0])
def test_exp_log_round_trip_including_zero_and_tiny_angles(scale):
    rng = np.random.default_rng(6)
    direction = rng.normal(size=(20, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    v = components(direction * scale)
    q = s3.exp(v, NP)
    np.testing.assert_allclose(s3.dot(q, q), 1.0, atol=1e-15)
    np.testing.assert_allclose(np.stack(s3.log(q, NP), -1), np.stack(v, -1), atol=1e-14, rtol=1e-13)
    np.testing.assert_allclose(q[0], np.cos(scale), atol=1e-16)


def test_exp_rotates_by_twice_the_norm():
    v = (np.array(0.0), np.array(0.3), np.array(0.0))
    R = np.array(s3.rotation_matrix(s3.exp(v, NP)), dtype=float)
    assert np.isclose(np.arccos((np.trace(R) - 1) / 2), 0.6)


def test_smooth_functions_match_closed_forms_across_the_series_threshold():
    t = np.concatenate([np.linspace(0, 2 * s3.SERIES_THRESHOLD, 2001), [0.5, 2.0]])
    c, s, ds = s3.trig_of_sqrt(t, NP, with_derivative=True)
    root = np.sqrt(t[1:])
    np.testing.assert_allclose(c[1:], np.cos(root), atol=1e-16, rtol=1e-15)
    np.testing.assert_allclose(s[1:], np.sin(root) / root, atol=1e-16, rtol=1e-15)
    # The derivative's closed form cancels catastrophically for small t; check it with mpmath-free
    # high-order central differences of the (exact) sinc instead.
    h = 1e-4
    big = t > 10 * h
    sinc = lambda x: np.sin(np.sqrt(x)) / np.sqrt(x)  # noqa: E731
    numeric = (sinc(t[big] - 2 * h) - 8 * sinc(t[big] - h) + 8 * sinc(t[big] + h) - sinc(t[big] + 2 * h)) / (12 * h)
    np.testing.assert_allclose(ds[big], numeric, atol=1e-11)
    assert ds[0] == pytest.approx(-1 / 6, abs=1e-16)


def test_sign_invariant_distance_and_geodesic_angle():
    q = components(random_unit_quaternions(40, 7))
    p = components(random_unit_quaternions(40, 8))
    np.testing.assert_allclose(s3.sign_invariant_distance(q, p), s3.sign_invariant_distance(s3.negate(q), p))
    angle = s3.geodesic_angle(q, p, NP)
    np.testing.assert_allclose(angle, s3.geodesic_angle(s3.negate(q), p, NP))
    R = lambda a: np.moveaxis(np.array(s3.rotation_matrix(a)), -1, 0)  # noqa: E731
    relative = np.einsum("nji,njk->nik", R(q), R(p))
    np.testing.assert_allclose(
        angle, np.arccos(np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1, 1)), atol=1e-7
    )


def test_geodesic_angles_of_arrays_are_geodesic_angle():
    """The NumPy form over ``(..., 4)`` arrays: the backend form's angle (to the arccos form's resolution near 0),
    the same for ``±q``, one angle per row, broadcast against one goal, and 0 and π where they must be."""
    q, p = random_unit_quaternions(40, 7), random_unit_quaternions(40, 8)
    angles = s3.geodesic_angles(q, p)
    assert angles.shape == (40,)
    np.testing.assert_allclose(angles, s3.geodesic_angle(components(q), components(p), NP), atol=1e-7)
    np.testing.assert_array_equal(angles, s3.geodesic_angles(-q, p))
    np.testing.assert_array_equal(s3.geodesic_angles(q, p[0]), [s3.geodesic_angles(row, p[0]) for row in q])
    assert s3.geodesic_angles(q[0], q[0]) < 3e-8 and s3.geodesic_angles(q[0], -q[0]) < 3e-8
    assert s3.geodesic_angles((1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0)) == pytest.approx(np.pi)


def test_solve3_inverts_random_matrices():
    rng = np.random.default_rng(9)
    m = rng.normal(size=(25, 3, 3)) + 3 * np.eye(3)
    r = rng.normal(size=(25, 3))
    mat = tuple(tuple(m[:, i, j] for j in range(3)) for i in range(3))
    np.testing.assert_allclose(
        np.stack(s3.solve3(mat, components(r)), -1), np.linalg.solve(m, r[..., None])[..., 0], atol=1e-13
    )


def test_torch_gradients_finite_at_zero_rotation():
    import torch
    ops = get_ops("torch")
    v = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    q = s3.exp(tuple(v.unbind()), ops)
    back = s3.log(q, ops)
    (grad,) = torch.autograd.grad(sum(c.sum() for c in q) + sum(b.sum() for b in back), v, create_graph=True)
    (second,) = torch.autograd.grad(grad.sum(), v)
    assert torch.isfinite(grad).all() and torch.isfinite(second).all()
    # d/dv of exp at 0 is [0; I] and of log∘exp is I: the sum of all components has gradient 1 + 1.
    torch.testing.assert_close(grad, torch.full((3,), 2.0, dtype=torch.float64))


def test_casadi_derivatives_finite_at_zero_rotation():
    import casadi as ca
    ops = get_ops("casadi")
    v = ca.SX.sym("v", 3)
    q = ca.vertcat(*s3.exp(tuple(v[i] for i in range(3)), ops))
    back = ca.vertcat(*s3.log(tuple(q[i] for i in range(4)), ops))
    f = ca.Function("f", [v], [ca.jacobian(q, v), ca.jacobian(back, v), ca.hessian(ca.sum1(q), v)[0]])
    for value in f([0, 0, 0]):
        assert np.all(np.isfinite(np.array(value)))
    np.testing.assert_allclose(np.array(f([0, 0, 0])[1]), np.eye(3), atol=1e-15)


# ----------------------------------------------------------------------------- every identity, every backend
# As jaxlie checks each group property on each group: the S³ algebra is written once for NumPy,
# torch and CasADi, so each identity is checked in each. Inputs come from the hard-case strategies
# (tests/strategies.py: uniform on S³ plus ±1, ±i, ±j, ±k; tiny and zero rotation vectors); the
# references (Hamilton product, R(q)) are the independent ones written there.
import functools  # noqa: E402
import math  # noqa: E402

import strategies as S  # noqa: E402
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

BACKENDS = ["numpy", "torch", "casadi-sx", "casadi-dm"]


def close(actual, expected, atol):
    """``|actual − expected| ≤ atol`` elementwise — absolute only (assert_allclose's default rtol of
    1e-7 would swamp these float64 tolerances)."""
    np.testing.assert_allclose(actual, np.broadcast_to(expected, np.shape(actual)), rtol=0, atol=atol)


def _flatten(value):
    if isinstance(value, (tuple, list)):
        return [leaf for item in value for leaf in _flatten(item)]
    return [value]


@functools.lru_cache(maxsize=None)
def _casadi_function(fn, dims):
    """``fn`` traced once on SX symbols (one per input component) as a CasADi Function."""
    import casadi as ca
    inputs = [ca.SX.sym(f"a{i}", d) for i, d in enumerate(dims)]
    out = _flatten(fn(get_ops("casadi"), *(tuple(x[j] for j in range(x.shape[0])) for x in inputs)))
    return ca.Function("identity", inputs, [ca.vertcat(*out)])


def evaluate(backend, fn, *arrays):
    """``fn(ops, *component_tuples)`` on rows of ``arrays`` (each ``(n, d)``) in ``backend``; the
    output's leaves stacked as a float64 ``(n, k)`` array."""
    arrays = [np.atleast_2d(np.asarray(a, dtype=float)) for a in arrays]
    n = arrays[0].shape[0]
    if backend == "numpy":
        out = _flatten(fn(get_ops("numpy"), *(tuple(a[:, j] for j in range(a.shape[1])) for a in arrays)))
        return np.stack([np.broadcast_to(np.asarray(x, dtype=float), (n,)) for x in out], -1)
    if backend == "torch":
        import torch
        tensors = [torch.as_tensor(a, dtype=torch.float64) for a in arrays]
        out = _flatten(fn(get_ops("torch"), *(tuple(t.unbind(-1)) for t in tensors)))
        for x in out:
            assert not isinstance(x, torch.Tensor) or x.dtype == torch.float64
        return np.stack([np.broadcast_to(torch.as_tensor(x).detach().numpy(), (n,)) for x in out], -1)
    import casadi as ca
    if backend == "casadi-sx":  # symbolic, then evaluated numerically on all rows at once
        function = _casadi_function(fn, tuple(a.shape[1] for a in arrays))
        return np.array(function.map(n)(*(a.T for a in arrays))).T
    rows = []  # casadi-dm: every leaf operation evaluated on numeric DM scalars
    for i in range(n):
        out = _flatten(fn(get_ops("casadi"), *(tuple(ca.DM(float(x)) for x in a[i]) for a in arrays)))
        rows.append([float(ca.DM(x)) for x in out])
    return np.array(rows)


def quaternion_batches(max_size=6):
    return st.lists(S.unit_quaternions(), min_size=1, max_size=max_size).map(np.array)


def vector_batches(max_size=6, low=-3.0, high=3.0):
    return st.lists(S.vectors(3, low, high), min_size=1, max_size=max_size).map(np.array)


#: Rotation vectors |v| < π/2 (where log is exp's inverse), zero and tiny ones included.
_SMALL_NORMS = st.one_of(st.just(0.0), S.log_uniform(1e-12, 1e-2), S.floats(0.0, np.pi / 2 - 1e-6))
rotation_vector_batches = st.lists(st.tuples(S.unit_vectors(), _SMALL_NORMS).map(lambda p: p[0] * p[1]),
                                   min_size=1, max_size=6).map(np.array)


def on_every_backend(examples: int, **strategies_of_arguments):
    """The decorators of an identity test: every backend, ``examples`` Hypothesis cases each (counted)."""
    def decorate(test):
        test = S.counted(test)
        test = given(**strategies_of_arguments)(test)
        test = settings(max_examples=S.budget(examples))(test)
        return pytest.mark.parametrize("backend", BACKENDS)(test)
    return decorate


def _exp_log(ops, q):
    return s3.exp(s3.log(q, ops), ops)


def _log_exp(ops, v):
    return s3.log(s3.exp(v, ops), ops)


def _exp(ops, v):
    return s3.exp(v, ops)


def _times_conjugate(ops, q):
    return s3.multiply(q, s3.conjugate(q)), s3.multiply(s3.conjugate(q), q)


def _associativity(ops, p, q, r):
    return s3.sub(s3.multiply(s3.multiply(p, q), r), s3.multiply(p, s3.multiply(q, r)))


def _product(ops, p, q):
    return s3.multiply(p, q)


def _rotation(ops, q):
    return s3.rotation_matrix(q)


def _rotation_of_product(ops, p, q):
    return s3.rotation_matrix(s3.multiply(p, q))


def _G_and_H(ops, q, x, y):
    pure = (0.0 * x[0], *x)
    return (s3.G_transpose_apply(q, x), s3.imaginary(s3.multiply(q, pure)), s3.H_transpose_apply(q, x),
            s3.multiply(q, pure), s3.dot(s3.G_apply(q, y), x), s3.dot(y, s3.G_transpose_apply(q, x)),
            s3.G_apply(q, x))


def _H_adjoint(ops, q, x, y4):
    return s3.dot(s3.H_apply(q, y4), x), s3.dot(y4, s3.H_transpose_apply(q, x)), s3.H_apply(q, q)


@on_every_backend(25, q=quaternion_batches())
def test_exp_of_log_is_plus_or_minus_q(backend, q):
    back = evaluate(backend, _exp_log, q)
    error = np.minimum(np.abs(back - q).max(1), np.abs(back + q).max(1))
    assert error.max() <= 1e-14, (q, back)


@on_every_backend(25, v=rotation_vector_batches)
def test_log_of_exp_is_v_below_a_quarter_turn(backend, v):
    back = evaluate(backend, _log_exp, v)
    assert np.all(np.abs(back - v) <= 1e-15 + 1e-12 * np.linalg.norm(v, axis=1, keepdims=True)), (v, back - v)


@on_every_backend(25, v=st.one_of(rotation_vector_batches, vector_batches(low=-10.0, high=10.0)))
def test_exp_is_a_unit_quaternion_rotating_by_twice_the_norm(backend, v):
    q = evaluate(backend, _exp, v)
    close(np.linalg.norm(q, axis=1), 1.0, atol=2e-16 * 4)
    norm = np.linalg.norm(v, axis=1)
    close(q[:, 0], np.cos(norm), atol=1e-15)  # DESIGN.md: no half angle


@on_every_backend(25, q=quaternion_batches())
def test_q_times_its_conjugate_is_the_identity(backend, q):
    out = evaluate(backend, _times_conjugate, q)
    identity = np.tile([1.0, 0.0, 0.0, 0.0], 2)
    close(out, identity, atol=1e-15)  # |q|² = 1 to rounding


@on_every_backend(25, p=quaternion_batches(3), q=quaternion_batches(3), r=quaternion_batches(3))
def test_product_is_associative_and_is_the_hamilton_product(backend, p, q, r):
    n = min(len(p), len(q), len(r))
    p, q, r = p[:n], q[:n], r[:n]
    close(evaluate(backend, _associativity, p, q, r), 0.0, atol=1e-15)
    independent = np.array([S.quat_multiply(a, b) for a, b in zip(p, q)])
    close(evaluate(backend, _product, p, q), independent, atol=1e-15)


@on_every_backend(25, p=quaternion_batches(4), q=quaternion_batches(4))
def test_rotation_matrix_orthonormal_det_one_and_a_homomorphism(backend, p, q):
    n = min(len(p), len(q))
    p, q = p[:n], q[:n]
    rp = evaluate(backend, _rotation, p).reshape(n, 3, 3)
    rq = evaluate(backend, _rotation, q).reshape(n, 3, 3)
    close(np.einsum("nji,njk->nik", rq, rq), np.broadcast_to(np.eye(3), rq.shape), atol=1e-14)
    close(np.linalg.det(rq), 1.0, atol=1e-14)
    close(rq, np.array([S.rotation_matrix(a) for a in q]), atol=1e-15)
    close(evaluate(backend, _rotation_of_product, p, q).reshape(n, 3, 3), rp @ rq, atol=1e-14)


@on_every_backend(25, q=quaternion_batches(4), x=vector_batches(4), y=vector_batches(4))
def test_G_transpose_and_H_transpose_are_products_with_a_pure_quaternion(backend, q, x, y):
    """``G(q)ᵀx = Im(q ⊗ (0,x))``, ``H(q)ᵀx = q ⊗ (0,x)`` (DESIGN.md), ``G_apply`` the adjoint of
    ``G_transpose_apply``, and ``G(q) = q_s I − [q_v]×`` as a matrix."""
    n = min(len(q), len(x), len(y))
    q, x, y = q[:n], x[:n], y[:n]
    out = evaluate(backend, _G_and_H, q, x, y)
    product = np.array([S.quat_multiply(a, np.concatenate([[0.0], b])) for a, b in zip(q, x)])
    close(out[:, 0:3], product[:, 1:], atol=1e-14)
    close(out[:, 3:6], product[:, 1:], atol=1e-14)
    close(out[:, 6:10], product, atol=1e-14)
    close(out[:, 10:14], product, atol=1e-14)
    close(out[:, 14], out[:, 15], atol=1e-13)
    skew = np.array([[[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]] for v in q[:, 1:]])
    g_matrix = q[:, 0, None, None] * np.eye(3) - skew
    close(out[:, 16:19], np.einsum("nij,nj->ni", g_matrix, x), atol=1e-14)


@on_every_backend(25, q=quaternion_batches(4), x=vector_batches(4),
                  y=st.lists(S.vectors(4, -3.0, 3.0), min_size=4, max_size=4).map(np.array))
def test_H_is_the_adjoint_of_H_transpose_and_annihilates_q(backend, q, x, y):
    n = min(len(q), len(x))
    out = evaluate(backend, _H_adjoint, q[:n], x[:n], y[:n])
    close(out[:, 0], out[:, 1], atol=1e-13)
    close(out[:, 2:5], 0.0, atol=1e-15)


def _sinc_derivatives(backend, t):
    """``(d/dt, d²/dt²)`` of :func:`s3.sinc_sqrt` at the points ``t``: autodiff in torch and CasADi,
    a central difference of the backend's own values in NumPy (and CasADi-DM)."""
    if backend == "torch":
        import torch
        x = torch.as_tensor(t, dtype=torch.float64).requires_grad_(True)
        (first,) = torch.autograd.grad(s3.sinc_sqrt(x, get_ops("torch")).sum(), x, create_graph=True)
        (second,) = torch.autograd.grad(first.sum(), x)
        return first.detach().numpy(), second.numpy()
    if backend == "casadi-sx":
        import casadi as ca
        x = ca.SX.sym("t")
        value = s3.sinc_sqrt(x, get_ops("casadi"))
        first = ca.jacobian(value, x)
        f = ca.Function("d", [x], [first, ca.jacobian(first, x)])
        pairs = [f(float(ti)) for ti in t]
        return np.array([float(a) for a, _ in pairs]), np.array([float(b) for _, b in pairs])
    step = 1e-5  # NumPy / DM: the function must be smooth through t = 0 (negative t included)
    value = lambda s: evaluate(backend, lambda ops, a: s3.sinc_sqrt(a[0], ops), np.reshape(s, (-1, 1)))[:, 0]  # noqa: E731
    first = (value(t - 2 * step) - 8 * value(t - step) + 8 * value(t + step) - value(t + 2 * step)) / (12 * step)
    second = (value(t + step) - 2 * value(t) + value(t - step)) / step**2
    return first, second


@pytest.mark.parametrize("backend", BACKENDS)
def test_sinc_is_smooth_at_zero_with_finite_derivatives(backend):
    """``sin√t/√t = 1 − t/6 + t²/120 − …``: at 0 the first derivative is −1/6 and the second 1/60,
    finite in every backend; near the series threshold both branches agree to the closed form's
    derivative ``(cos√t − sin√t/√t)/(2t)``."""
    t = np.array([0.0, 1e-300, 1e-12, 1e-6, 0.5 * s3.SERIES_THRESHOLD, 2 * s3.SERIES_THRESHOLD, 0.5, 2.0])
    first, second = _sinc_derivatives(backend, t)
    assert np.all(np.isfinite(first)) and np.all(np.isfinite(second))
    # Reference: the closed form where it does not cancel, else the term-wise derivative of
    # sin√t/√t = Σ (−t)^k / (2k+1)!.
    root = np.sqrt(np.where(t > 0, t, 1.0))
    series_first = sum(k * (-1) ** k * t ** (k - 1) / math.factorial(2 * k + 1) for k in range(1, 10))
    closed = np.where(t > 0.1, (np.cos(root) - np.sin(root) / root) / (2 * np.where(t > 0, t, 1.0)), series_first)
    exact = backend in ("torch", "casadi-sx")
    # Just above the threshold autodiff of the closed form cancels to ≈ ε/t (2e-15 at t = 0.02).
    close(first, closed, atol=1e-14 if exact else 1e-9)
    close(second[:4], 1 / 60 - t[:4] / 840, atol=1e-16 if exact else 1e-4)
