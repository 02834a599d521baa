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
    np.testing.assert_allclose(np.einsum("nji,njk->nik", R(q), R(q)), np.broadcast_to(np.eye(3), (30, 3, 3)), atol=1e-14)
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
    np.testing.assert_allclose(angle, np.arccos(np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1, 1)), atol=1e-7)


def test_solve3_inverts_random_matrices():
    rng = np.random.default_rng(9)
    m = rng.normal(size=(25, 3, 3)) + 3 * np.eye(3)
    r = rng.normal(size=(25, 3))
    mat = tuple(tuple(m[:, i, j] for j in range(3)) for i in range(3))
    np.testing.assert_allclose(np.stack(s3.solve3(mat, components(r)), -1), np.linalg.solve(m, r[..., None])[..., 0], atol=1e-13)


def test_torch_gradients_finite_at_zero_rotation():
    torch = pytest.importorskip("torch")
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
    ca = pytest.importorskip("casadi")
    ops = get_ops("casadi")
    v = ca.SX.sym("v", 3)
    q = ca.vertcat(*s3.exp(tuple(v[i] for i in range(3)), ops))
    back = ca.vertcat(*s3.log(tuple(q[i] for i in range(4)), ops))
    f = ca.Function("f", [v], [ca.jacobian(q, v), ca.jacobian(back, v), ca.hessian(ca.sum1(q), v)[0]])
    for value in f([0, 0, 0]):
        assert np.all(np.isfinite(np.array(value)))
    np.testing.assert_allclose(np.array(f([0, 0, 0])[1]), np.eye(3), atol=1e-15)
