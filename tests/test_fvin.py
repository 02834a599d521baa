"""The FVIN step against independent references: a high-accuracy ODE solution of
θ̈ = −15 sin θ + 3u (and of the damped θ̈ = −15 sin θ + 3u − 0.3 θ̇), energy and norm
conservation, finite differences of the Newton Jacobian, and backend parity."""

import dataclasses

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from strategies import quat_multiply

from fvin_mpc.core import fvin, s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.networks import LearnedTerms, ModelConfig, init_weights
from fvin_mpc.core.rigid_body import PENDULUM, PENDULUM_DAMPED

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


def ode_solution(theta0, omega0, u, duration, damping=0.0):
    """``θ̈ = −15 sin θ + 3u − 3·damping·θ̇`` (the rod's ``1/J = 3``) by DOP853 at rtol = atol = 1e-12."""
    sol = solve_ivp(lambda t, y: [y[1], -15 * np.sin(y[0]) + 3 * u - 3 * damping * y[1]], (0, duration),
                    [theta0, omega0], method="DOP853", rtol=1e-12, atol=1e-12)
    return sol.y[0, -1], sol.y[1, -1]


def convergence_errors(body, theta0, omega0, u, steps, duration=2.0):
    """Error at ``duration`` of the FVIN rollout for each step size, against the ODE."""
    exact_theta, exact_omega = ode_solution(theta0, omega0, u, duration, body.damping)
    terms = body.terms(NP)
    errors = []
    for h in steps:
        q, omega = rollout(*hinge_state(theta0, omega0), (np.array(u),), terms, h, int(round(duration / h)))
        theta = 2 * np.arctan2(q[2], q[0])
        errors.append(np.hypot(theta - exact_theta, 0.1 * (omega[1] - exact_omega)))
    return np.array(errors)


@pytest.mark.parametrize("body", [PENDULUM, PENDULUM_DAMPED], ids=["undamped", "damped"])
def test_second_order_convergence_against_ode(body):
    """Halving h divides the 2 s error by ≈ 4 (log–log slope 2), as for Störmer–Verlet — with
    viscous damping too: ``f⁻`` takes ``−Dω_k``, ``f⁺`` takes ``−Dω_{k+1}`` (trapezoidal)."""
    steps = np.array([0.05, 0.025, 0.0125, 0.00625])
    errors = convergence_errors(body, 1.0, 0.5, 0.7, steps)
    slope = np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert slope == pytest.approx(2.0, abs=0.05), (slope, errors)
    ratios = errors[:-1] / errors[1:]
    assert np.all(np.abs(ratios - 4.0) < 0.2), ratios


def test_strong_damping_stays_second_order_and_decays():
    """Damping ten times the scene's (θ̈ = … − 3 θ̇, decay rate 1.5/s): still order 2 against the ODE,
    and the unforced swing loses energy monotonically as the true one does."""
    body = dataclasses.replace(PENDULUM_DAMPED, damping=1.0)
    steps = np.array([0.05, 0.025, 0.0125, 0.00625])
    errors = convergence_errors(body, 2.5, -1.0, 0.0, steps)
    ratios = errors[:-1] / errors[1:]
    assert np.all(np.abs(ratios - 4.0) < 0.3), (ratios, errors)
    terms = body.terms(NP)
    q, omega = hinge_state(np.array([2.5]), np.array([-1.0]))
    energies = [fvin.total_energy(q, omega, terms)[0]]
    for _ in range(200):
        out = fvin.fvin_step(q, omega, (np.zeros(1),), terms, 0.05, 4, NP)
        q, omega = out.q, out.omega
        energies.append(fvin.total_energy(q, omega, terms)[0])
    assert energies[-1] < 1e-3 * energies[0], energies[-1]


class ZeroDissipation:
    """A body's terms with ``D`` returned as an explicit zero matrix instead of ``None``."""

    def __init__(self, terms):
        self._terms = terms
        self.control_dim, self.constant_inertia = terms.control_dim, terms.constant_inertia

    def __getattr__(self, name):
        return getattr(self._terms, name)

    def dissipation(self, q):
        zero = 0.0 * q[0]
        return ((zero, zero, zero), (zero, zero, zero), (zero, zero, zero))


def test_zero_dissipation_matrix_gives_the_undamped_step_bit_for_bit():
    """``D = 0`` takes the damped branch (``(2J + (h/2)·0) ω = P``), which must equal the undamped
    ``ω = ½ J⁻¹ P`` exactly: scaling by 2 is exact in floating point."""
    rng = np.random.default_rng(12)
    q = rng.normal(size=(40, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    comps = lambda a: tuple(a[:, i] for i in range(a.shape[1]))  # noqa: E731
    omega, u = comps(rng.normal(size=(40, 3)) * 4), (rng.uniform(-2, 2, 40),)
    plain = fvin.fvin_step(comps(q), omega, u, TRUE, 0.05, 3, NP, with_residual=True)
    zero = fvin.fvin_step(comps(q), omega, u, ZeroDissipation(TRUE), 0.05, 3, NP, with_residual=True)
    for a, b in zip((*plain.q, *plain.omega, plain.residual), (*zero.q, *zero.omega, zero.residual)):
        np.testing.assert_array_equal(a, b)


def test_damping_enters_f_plus_at_the_end_of_the_step():
    """Step 5 with ``f⁺ = (h/2)(g u − D ω_{k+1})``: ``π_{k+1}`` recomputed from the returned
    ``ω_{k+1}`` satisfies ``2Jω_{k+1} = (4/h) G(e) J Im(e) − (h/2) H∇U(q_{k+1}) + (h/2)(g u − D ω_{k+1})``
    with ``e = q_k* ⊗ q_{k+1}`` — written here with NumPy matrices, not the package's step."""
    terms = PENDULUM_DAMPED.terms(NP)
    h, j, d = 0.05, np.eye(3) / 3, 0.2 * np.eye(3)
    q0 = np.array([0.8, 0.1, 0.55, -0.2])
    q0 /= np.linalg.norm(q0)
    omega0, u = np.array([0.4, -3.0, 1.1]), 1.3
    out = fvin.fvin_step(*(tuple(np.array([x]) for x in a) for a in (q0, omega0, np.array([u]))), terms, h, 8, NP)
    q1, omega1 = np.array(out.q)[:, 0], np.array(out.omega)[:, 0]
    e = quat_multiply(q0 * np.array([1, -1, -1, -1]), q1)
    ev = e[1:]
    kinetic = e[0] * (j @ ev) - np.cross(ev, j @ ev)
    grad = np.array(terms.potential_gradient(tuple(q1)))
    h_grad = -q1[1:] * grad[0] + q1[0] * grad[1:] - np.cross(q1[1:], grad[1:])
    g = np.array([0.0, 2.0, 0.0])
    np.testing.assert_allclose(2 * j @ omega1, (4 / h) * kinetic - (h / 2) * h_grad + (h / 2) * (g * u - d @ omega1),
                               atol=1e-12)


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
        np.testing.assert_allclose(
            np.array(phi, dtype=float), np.array(fvin.implicit_lhs(tuple(xi0), inertia, NP), dtype=float)
        )
    # ∂Φ/∂ξ(0) = −J (DESIGN.md)
    np.testing.assert_allclose(
        np.array(fvin.implicit_lhs_jacobian((0.0, 0.0, 0.0), inertia, NP)[1], dtype=float), -inertia_matrix, atol=1e-15
    )


def test_newton_converges_quadratically_below_the_solvability_limit():
    q, omega = hinge_state(np.array([0.3]), np.array([8.0]))
    u = (np.array([1.5]),)
    reference = fvin.fvin_step(q, omega, u, TRUE, 0.05, 12, NP)
    errors = [
        abs(float(fvin.fvin_step(q, omega, u, TRUE, 0.05, k, NP).omega[1][0] - reference.omega[1][0]))
        for k in (1, 2, 3)
    ]
    assert errors[0] > 1e-2 and errors[1] < 1e-2 * errors[0] and errors[2] < 1e-6
    assert float(fvin.fvin_step(q, omega, u, TRUE, 0.05, 5, NP, with_residual=True).residual[0]) < 1e-12


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
    numeric = np.array(
        [(terms.potential(tuple(q + e)) - terms.potential(tuple(q - e))) / 2e-6 for e in 1e-6 * np.eye(4)], dtype=float
    )
    np.testing.assert_allclose(grad, numeric.ravel(), atol=1e-9)


def test_true_pendulum_potential_gradient_matches_finite_differences():
    q = np.array([0.3, -0.2, 0.8, 0.1])
    grad = np.array(TRUE.potential_gradient(tuple(q)), dtype=float)
    numeric = np.array([(TRUE.potential(tuple(q + e)) - TRUE.potential(tuple(q - e))) / 2e-6 for e in 1e-6 * np.eye(4)])
    np.testing.assert_allclose(grad, numeric, atol=1e-8)


@pytest.mark.parametrize("variant, dissipation", [("sign-invariant", False), ("plain", True)])
def test_step_residual_vanishes_at_the_converged_step_only(variant, dissipation):
    """``step_residual`` is the step's equations with both ends free: ~0 at the converged step
    (K = 8), at the Newton error at K = 2, O(1) off it — and, for sign-invariant terms, the same
    for ``±q_{k+1}`` (the plain variant's terms differ at ``−q``)."""
    config = ModelConfig(variant=variant, control_dim=3, dissipation=dissipation)
    terms = LearnedTerms(init_weights(config, seed=5), config, NP)
    rng = np.random.default_rng(6)
    q = rng.normal(size=(16, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    omega, u = 3.0 * rng.normal(size=(16, 3)), rng.normal(size=(16, 3))
    comps = lambda a: tuple(a[:, i] for i in range(a.shape[1]))  # noqa: E731
    args = (comps(q), comps(omega), comps(u))

    def residual(step, q_sign=1.0, omega_offset=0.0):
        return np.abs(np.stack(fvin.step_residual(*args, tuple(q_sign * c for c in step.q),
                                                  tuple(c + omega_offset for c in step.omega), terms, 0.05, NP)))

    converged = fvin.fvin_step(*args, terms, 0.05, 8, NP)
    assert residual(converged).max() < 1e-12
    flipped = residual(converged, q_sign=-1.0).max()
    assert flipped < 1e-12 if variant == "sign-invariant" else flipped > 1e-6
    two = residual(fvin.fvin_step(*args, terms, 0.05, 2, NP)).max()
    assert 1e-12 < two < 1e-2
    assert residual(converged, omega_offset=0.1).max() > 1e-3


def test_step_residual_of_the_closed_form_damped_pendulum_matches_its_step():
    terms = PENDULUM_DAMPED.terms(NP)
    q, omega = hinge_state(np.linspace(-3.0, 3.0, 7), np.linspace(-6.0, 6.0, 7))
    u = (np.linspace(-1.0, 1.0, 7),)
    step = fvin.fvin_step(q, omega, u, terms, 0.05, 8, NP)
    residual = np.stack(fvin.step_residual(q, omega, u, step.q, step.omega, terms, 0.05, NP))
    assert np.abs(residual).max() < 1e-12
