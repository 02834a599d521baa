"""The FVIN step against independent references: a high-accuracy ODE solution of
θ̈ = −15 sin θ + 3u, energy and norm conservation, finite differences of the Newton
Jacobian, and backend parity."""

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from fvin_mpc.core import fvin, s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.networks import LearnedTerms, ModelConfig, init_weights
from fvin_mpc.core.rigid_body import PENDULUM

NP = get_ops("numpy")
TRUE = PENDULUM.terms(NP)


def hinge_state(theta, omega):
    theta, omega = np.asarray(theta, float), np.asarray(omega, float)
    zero = 0.0 * theta
    return (np.cos(theta / 2), zero, np.sin(theta / 2), zero), (zero, omega, zero)


def rollout(q, omega, u, terms, h, steps, newton_iters=5):
    for _ in range(steps):
        out = fvin.fvin_step(q, omega, u, terms, h, newton_iters, NP)
        q, omega = out.q, out.omega
    return q, omega


def ode_solution(theta0, omega0, u, duration):
    sol = solve_ivp(lambda t, y: [y[1], -15 * np.sin(y[0]) + 3 * u], (0, duration), [theta0, omega0],
                    method="DOP853", rtol=1e-12, atol=1e-12)
    return sol.y[0, -1], sol.y[1, -1]


def test_second_order_convergence_against_ode():
    """Halving h divides the 2 s error by ≈ 4 (log–log slope 2), as for Störmer–Verlet."""
    theta0, omega0, u = 1.0, 0.5, 0.7
    exact_theta, exact_omega = ode_solution(theta0, omega0, u, 2.0)
    steps = np.array([0.05, 0.025, 0.0125, 0.00625])
    errors = []
    for h in steps:
        q, omega = rollout(*hinge_state(theta0, omega0), (np.array(u),), TRUE, h, int(round(2.0 / h)))
        theta = 2 * np.arctan2(q[2], q[0])
        errors.append(np.hypot(theta - exact_theta, 0.1 * (omega[1] - exact_omega)))
    slope = np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert slope == pytest.approx(2.0, abs=0.05), (slope, errors)
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    assert np.all(np.abs(ratios - 4.0) < 0.2), ratios


def test_energy_bounded_and_norm_preserved_over_10k_unforced_steps():
    q, omega = hinge_state(np.linspace(0.2, 2.8, 6), np.zeros(6))
    e0 = fvin.total_energy(q, omega, TRUE)
    max_rel, max_norm_err = 0.0, 0.0
    for _ in range(10_000):
        out = fvin.fvin_step(q, omega, (0.0 * q[0],), TRUE, 0.05, 3, NP)
        q, omega = out.q, out.omega
        energy = fvin.total_energy(q, omega, TRUE)
        max_rel = max(max_rel, np.max(np.abs(energy - e0) / e0))
        max_norm_err = max(max_norm_err, np.max(np.abs(np.sqrt(s3.dot(q, q)) - 1)))
    # Variational integrators oscillate around the true energy instead of drifting.
    assert max_rel < 0.03, max_rel
    assert max_norm_err < 1e-12, max_norm_err


def test_newton_jacobian_matches_finite_differences():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(3, 3))
    inertia_matrix = a @ a.T + 0.5 * np.eye(3)
    inertia = tuple(tuple(float(x) for x in row) for row in inertia_matrix)
    for xi0 in [np.zeros(3), np.array([1e-4, -2e-4, 3e-5]), rng.normal(size=3) * 0.3, rng.normal(size=3) * 0.6]:
        phi, jac = fvin.implicit_lhs_jacobian(tuple(xi0), inertia, NP)
        numeric = np.empty((3, 3))
        eps = 1e-6
        for j in range(3):
            d = np.zeros(3)
            d[j] = eps
            plus = np.array(fvin.implicit_lhs(tuple(xi0 + d), inertia, NP), dtype=float)
            minus = np.array(fvin.implicit_lhs(tuple(xi0 - d), inertia, NP), dtype=float)
            numeric[:, j] = (plus - minus) / (2 * eps)
        np.testing.assert_allclose(np.array(jac, dtype=float), numeric, atol=1e-8)
        np.testing.assert_allclose(np.array(phi, dtype=float), np.array(fvin.implicit_lhs(tuple(xi0), inertia, NP), dtype=float))
    # ∂Φ/∂ξ(0) = −J (DESIGN.md)
    np.testing.assert_allclose(np.array(fvin.implicit_lhs_jacobian((0.0, 0.0, 0.0), inertia, NP)[1], dtype=float), -inertia_matrix, atol=1e-15)


def test_newton_converges_quadratically_below_the_solvability_limit():
    q, omega = hinge_state(np.array([0.3]), np.array([8.0]))
    u = (np.array([1.5]),)
    reference = fvin.fvin_step(q, omega, u, TRUE, 0.05, 12, NP)
    errors = [abs(float(fvin.fvin_step(q, omega, u, TRUE, 0.05, k, NP).omega[1][0] - reference.omega[1][0])) for k in (1, 2, 3)]
    assert errors[0] > 1e-2 and errors[1] < 1e-2 * errors[0] and errors[2] < 1e-6
    assert float(fvin.fvin_step(q, omega, u, TRUE, 0.05, 5, NP, with_residual=True).residual[0]) < 1e-12


def test_residual_flags_states_past_the_solvability_limit():
    """Past h|ω| ≈ 1 there is no solution: the residual says so instead of a silent state."""
    h = 0.05
    q, omega = hinge_state(np.array([0.0, 0.0]), np.array([10.0, 25.0]))
    out = fvin.fvin_step(q, omega, (np.zeros(2),), TRUE, h, 6, NP, with_residual=True)
    assert out.residual[0] < 1e-9
    assert out.residual[1] > 1.0
    assert all(np.all(np.isfinite(c)) for c in (*out.q, *out.omega))


def test_sign_invariant_variant_predicts_the_same_rotation_for_q_and_minus_q():
    config = ModelConfig(variant="sign-invariant")
    terms = LearnedTerms(init_weights(config, seed=3), config, NP)
    rng = np.random.default_rng(4)
    q = rng.normal(size=(20, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    omega, u = rng.normal(size=(20, 3)), rng.normal(size=(20, 1))
    comps = lambda a: tuple(a[:, i] for i in range(a.shape[1]))  # noqa: E731
    plus = fvin.fvin_step(comps(q), comps(omega), comps(u), terms, 0.05, 3, NP)
    minus = fvin.fvin_step(comps(-q), comps(omega), comps(u), terms, 0.05, 3, NP)
    np.testing.assert_allclose(np.stack(minus.q), -np.stack(plus.q), atol=1e-14)
    np.testing.assert_allclose(np.stack(minus.omega), np.stack(plus.omega), atol=1e-13)
    # The plain variant has no such guarantee.
    plain = ModelConfig(variant="plain")
    terms_plain = LearnedTerms(init_weights(plain, seed=3), plain, NP)
    p = fvin.fvin_step(comps(q), comps(omega), comps(u), terms_plain, 0.05, 3, NP)
    m = fvin.fvin_step(comps(-q), comps(omega), comps(u), terms_plain, 0.05, 3, NP)
    assert np.abs(np.stack(m.omega) - np.stack(p.omega)).max() > 1e-6


@pytest.mark.parametrize("variant", ["sign-invariant", "fixed-inertia", "plain"])
@pytest.mark.parametrize("control_dim", [1, 3])
def test_torch_and_numpy_backends_agree(variant, control_dim):
    torch = pytest.importorskip("torch")
    from fvin_mpc.learning.model import S3FVIN

    config = ModelConfig(variant=variant, control_dim=control_dim, dissipation=control_dim == 3, newton_iters=3)
    weights = init_weights(config, seed=1)
    model = S3FVIN(config, weights)
    rng = np.random.default_rng(2)
    q = rng.normal(size=(8, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    omega, u = rng.normal(size=(8, 3)), rng.normal(size=(8, control_dim))
    out = model.step(*(torch.as_tensor(a) for a in (q, omega, u)))
    terms = LearnedTerms(weights, config, NP)
    comps = lambda a: tuple(a[:, i] for i in range(a.shape[1]))  # noqa: E731
    ref = fvin.fvin_step(comps(q), comps(omega), comps(u), terms, config.step_size, 3, NP)
    np.testing.assert_allclose(out.q.detach().numpy(), np.stack(ref.q, -1), atol=1e-14)
    np.testing.assert_allclose(out.omega.detach().numpy(), np.stack(ref.omega, -1), atol=1e-13)


def test_learned_potential_gradient_matches_finite_differences():
    config = ModelConfig()
    terms = LearnedTerms(init_weights(config, seed=5), config, NP)
    q = np.array([0.3, -0.2, 0.8, 0.1])
    grad = np.array(terms.potential_gradient(tuple(q)), dtype=float)
    numeric = np.array([(terms.potential(tuple(q + e)) - terms.potential(tuple(q - e))) / 2e-6 for e in 1e-6 * np.eye(4)], dtype=float)
    np.testing.assert_allclose(grad, numeric.ravel(), atol=1e-9)


def test_true_pendulum_potential_gradient_matches_finite_differences():
    q = np.array([0.3, -0.2, 0.8, 0.1])
    grad = np.array(TRUE.potential_gradient(tuple(q)), dtype=float)
    numeric = np.array([(TRUE.potential(tuple(q + e)) - TRUE.potential(tuple(q - e))) / 2e-6 for e in 1e-6 * np.eye(4)])
    np.testing.assert_allclose(grad, numeric, atol=1e-8)
