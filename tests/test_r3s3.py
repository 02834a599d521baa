"""The combined R³ × S³ step (:mod:`fvin_mpc.core.fvin_r3s3`) on the closed-form quadrotor
(:mod:`fvin_mpc.core.quadrotor`): Velocity-Verlet exactness, convergence order against Newton–Euler
(solve_ivp, DOP853), |q| and energy over 10⁴ steps, NumPy ↔ torch ↔ CasADi parity, the sign flip,
and hard cases (fast spins, far translations).

The reference dynamics are written here from the physics (``strategies.rotation_matrix``,
``strategies.quat_multiply``), not from the package's step.
"""

import casadi as ca
import numpy as np
import pytest
import strategies as S
import torch
from helpers import random_unit_quaternions
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp

from fvin_mpc.core import fvin_r3s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.quadrotor import QUADROTOR, Quadrotor

NP = get_ops("numpy")
TETHERED = Quadrotor(mass=QUADROTOR.mass, inertia=QUADROTOR.inertia, rotor_sites=QUADROTOR.rotor_sites,
                     rotor_spins=QUADROTOR.rotor_spins, yaw_coefficient=QUADROTOR.yaw_coefficient,
                     tether_stiffness=6.0, tether_site=(0.05, -0.03, 0.04), tether_anchor=(0.2, -0.1, 0.6))
THRUST = QUADROTOR.hover_thrust * np.array([1.06, 0.95, 1.08, 0.93])  # constant, unequal: torques on all axes
TUMBLE = np.array([4.0, -3.0, 6.0])
Q0 = np.array([0.9, 0.2, -0.3, 0.25]) / np.linalg.norm([0.9, 0.2, -0.3, 0.25])
X0, V0 = np.array([0.3, -0.2, 1.0]), np.array([0.5, 0.1, 2.0])


# ----------------------------------------------------------------------------- helpers
def comps(a):
    return tuple(np.array([float(c)]) for c in a)


def step(body, state, u, h, k=6, backend="numpy", with_residual=False, force_rule="trapezoid"):
    """One package step on a 13-vector ``(x, q, v, ω)``: the next 13-vector (and the residual)."""
    ops = get_ops(backend)
    wrap = (lambda a: tuple(torch.tensor([float(c)], dtype=torch.float64) for c in a)) if backend == "torch" else comps
    out = fvin_r3s3.r3s3_step(wrap(state[:3]), wrap(state[3:7]), wrap(state[7:10]), wrap(state[10:]), wrap(u),
                              body.terms(ops), h, k, ops, with_residual, force_rule)
    flat = np.concatenate([S.stacked(out.x), S.stacked(out.q), S.stacked(out.v), S.stacked(out.omega)])
    return (flat, None if out.residual is None else S.stacked((out.residual,))[0]) if with_residual else flat


def rollout(body, state, u, h, steps, k=6, force_rule="trapezoid"):
    """``steps`` steps on a batch ``(n, 13)`` at once (components of shape ``(n,)``)."""
    state = np.atleast_2d(state)
    x, q, v, w = (tuple(state[:, j] for j in idx) for idx in (range(3), range(3, 7), range(7, 10), range(10, 13)))
    uu = tuple(np.full(state.shape[0], float(c)) for c in u)
    terms = body.terms(NP)
    for _ in range(steps):
        out = fvin_r3s3.r3s3_step(x, q, v, w, uu, terms, h, k, NP, force_rule=force_rule)
        x, q, v, w = out.x, out.q, out.v, out.omega
    return np.stack([*x, *q, *v, *w], -1)


def newton_euler(body, u):
    """``d/dt (x, q, v, ω)`` of the physical body (independent of the package)."""
    m, inertia = body.mass, np.array(body.inertia)
    sites, spins = np.array(body.rotor_sites), np.array(body.rotor_spins)
    k, a, b = body.tether_stiffness, np.array(body.tether_site), np.array(body.tether_anchor)
    torque_u = sum(np.cross(r, [0, 0, ui]) + body.yaw_coefficient * s * ui * np.array([0, 0, 1.0])
                   for r, s, ui in zip(sites, spins, u))

    def rhs(_, y):
        x, q, v, w = y[:3], y[3:7], y[7:10], y[10:]
        rot = S.rotation_matrix(q / np.linalg.norm(q))
        d = x + rot @ a - b
        force = -m * body.gravity * np.array([0, 0, 1.0]) + rot[:, 2] * np.sum(u) - k * d
        torque = torque_u + np.cross(a, rot.T @ (-k * d))
        qdot = 0.5 * S.quat_multiply(q, np.concatenate([[0.0], w]))
        wdot = np.linalg.solve(inertia, torque - np.cross(w, inertia @ w))
        return np.concatenate([v, qdot, force / m, wdot])

    return rhs


def reference(body, state, u, duration):
    sol = solve_ivp(newton_euler(body, u), (0.0, duration), state, method="DOP853", rtol=1e-12, atol=1e-12)
    return sol.y[:, -1]


def errors(a, b):
    """Max-norm errors of (x, q up to sign, v, ω) between two 13-vectors."""
    dq = min(np.max(np.abs(a[3:7] - b[3:7])), np.max(np.abs(a[3:7] + b[3:7])))
    return np.array([np.max(np.abs(a[:3] - b[:3])), dq, np.max(np.abs(a[7:10] - b[7:10])),
                     np.max(np.abs(a[10:] - b[10:]))])


def orders(body, state, u, duration=1.0, steps=(100, 200, 400), force_rule="trapezoid"):
    truth = reference(body, state, u, duration)
    errs = np.array([errors(rollout(body, state, u, duration / n, n, force_rule=force_rule)[0], truth) for n in steps])
    slopes = -np.diff(np.log2(errs), axis=0)  # per halving of h, per (x, q, v, ω)
    return errs, slopes


def energy(body, state):
    terms = body.terms(NP)
    c = [tuple(state[..., j] for j in idx) for idx in (range(3), range(3, 7), range(7, 10), range(10, 13))]
    return fvin_r3s3.total_energy(*c, terms)


#: ``J = jI``: ``Φ(ξ) = −(j/2) sin(2|ξ|) n``, solvable exactly while ``|C| ≤ j/2`` (DESIGN.md).
ISOTROPIC = Quadrotor(mass=QUADROTOR.mass, inertia=((3e-3, 0, 0), (0, 3e-3, 0), (0, 0, 3e-3)),
                      rotor_sites=QUADROTOR.rotor_sites, rotor_spins=QUADROTOR.rotor_spins,
                      yaw_coefficient=QUADROTOR.yaw_coefficient)
START = np.concatenate([X0, Q0, V0, TUMBLE])


# ----------------------------------------------------------------------------- the closed-form body
def test_quadrotor_terms_match_the_physics_and_their_gradients():
    terms = TETHERED.terms(NP)
    rng = np.random.default_rng(3)
    for _ in range(5):
        x, q, u = rng.normal(size=3), rng.normal(size=4), rng.uniform(0, 3, 4)
        q /= np.linalg.norm(q)
        rot = S.rotation_matrix(q)
        np.testing.assert_allclose(S.stacked(terms.translational_force(comps(x), comps(q), comps(u))),
                                   rot[:, 2] * u.sum(), atol=1e-14)
        torque = sum(np.cross(r, [0, 0, ui]) + TETHERED.yaw_coefficient * s * ui * np.array([0, 0, 1.0])
                     for r, s, ui in zip(TETHERED.rotor_sites, TETHERED.rotor_spins, u))
        gain = np.array([[float(e[0]) for e in row] for row in terms.control_gain(comps(x), comps(q))])
        np.testing.assert_allclose(gain @ u, 2.0 * torque, atol=1e-14)  # g = 2B
        d = x + rot @ np.array(TETHERED.tether_site) - np.array(TETHERED.tether_anchor)
        expected_u = TETHERED.mass * TETHERED.gravity * x[2] + 0.5 * TETHERED.tether_stiffness * d @ d
        assert abs(float(terms.potential(comps(x), comps(q))[0]) - expected_u) < 1e-12
        # Gradients against central differences of U (q off the sphere too: U is a polynomial in q).
        eps = 1e-6
        pot = lambda xx, qq: float(terms.potential(comps(xx), comps(qq))[0])  # noqa: E731
        fd_x = [(pot(x + eps * e, q) - pot(x - eps * e, q)) / (2 * eps) for e in np.eye(3)]
        fd_q = [(pot(x, q + eps * e) - pot(x, q - eps * e)) / (2 * eps) for e in np.eye(4)]
        np.testing.assert_allclose(S.stacked(terms.potential_gradient_x(comps(x), comps(q))), fd_x, atol=1e-7)
        np.testing.assert_allclose(S.stacked(terms.potential_gradient_q(comps(x), comps(q))), fd_q, atol=1e-7)


# ----------------------------------------------------------------------------- Velocity-Verlet
@pytest.mark.parametrize("force_rule", fvin_r3s3.FORCE_RULES)
def test_free_fall_is_velocity_verlet_and_exact_for_constant_gravity(force_rule):
    """No thrust, ``U = m g x_z`` independent of ``q``: the translation is exact whatever the tumble."""
    h, n = 0.01, 300
    out = rollout(QUADROTOR, START, np.zeros(4), h, n, force_rule=force_rule)[0]
    t, g = h * n, np.array([0.0, 0.0, QUADROTOR.gravity])
    np.testing.assert_allclose(out[:3], X0 + V0 * t - 0.5 * g * t * t, rtol=0, atol=1e-12)
    np.testing.assert_allclose(out[7:10], V0 - g * t, rtol=0, atol=1e-12)
    # The rotation is the torque-free S³ step, untouched by the fall: same as starting at rest at the origin.
    still = rollout(QUADROTOR, np.concatenate([np.zeros(3), Q0, np.zeros(3), TUMBLE]), np.zeros(4), h, n)[0]
    np.testing.assert_array_equal(out[3:], np.concatenate([still[3:7], out[7:10], still[10:]]))


# ----------------------------------------------------------------------------- convergence order
@pytest.mark.parametrize("body", [QUADROTOR, TETHERED], ids=["free", "tethered"])
@pytest.mark.parametrize("omega0", [np.zeros(3), TUMBLE], ids=["level-start", "tumbling"])
def test_trapezoid_rule_is_second_order_against_newton_euler(body, omega0):
    state = np.concatenate([X0, Q0, V0, omega0])
    errs, slopes = orders(body, state, THRUST)
    assert np.all((slopes > 1.85) & (slopes < 2.15)), (errs, slopes)


def test_eq_3_6_hold_rule_is_first_order_in_translation_when_the_thrust_turns():
    """Eq. 3.6 holds ``F_x = R(q_k) e_z Σu`` over the step: with a tumbling body the velocity
    error is ``O(h)``; the rotation (not driven by the translation here) stays second order."""
    errs, slopes = orders(QUADROTOR, START, THRUST, force_rule="hold")
    assert np.all((slopes[:, [0, 2]] > 0.75) & (slopes[:, [0, 2]] < 1.25)), (errs, slopes)
    assert np.all((slopes[:, [1, 3]] > 1.85) & (slopes[:, [1, 3]] < 2.15)), (errs, slopes)
    trapezoid = np.array(
        [errors(rollout(QUADROTOR, START, THRUST, 1 / 400, 400)[0], reference(QUADROTOR, START, THRUST, 1.0))]
    )
    assert trapezoid[0, 2] < errs[-1, 2] / 4


def test_hold_and_trapezoid_agree_when_the_force_does_not_turn():
    """Spinning about the thrust axis from level: ``R(q) e_z`` is constant, the two rules coincide."""
    state = np.concatenate([X0, [1.0, 0, 0, 0], V0, [0, 0, 7.0]])
    hold = rollout(QUADROTOR, state, np.full(4, QUADROTOR.hover_thrust), 0.01, 100, force_rule="hold")[0]
    trap = rollout(QUADROTOR, state, np.full(4, QUADROTOR.hover_thrust), 0.01, 100)[0]
    np.testing.assert_allclose(hold, trap, rtol=0, atol=1e-13)
    np.testing.assert_allclose(hold[7:10], V0, atol=1e-12)  # hover thrust cancels gravity exactly


# ----------------------------------------------------------------------------- long runs
def test_norm_preserved_and_energy_bounded_over_10k_steps():
    """Tethered, no thrust (conservative): |q| = 1 to 1e-13 and energy oscillates without drift."""
    rng = np.random.default_rng(7)
    starts = np.concatenate([rng.normal(0, 0.3, (4, 3)), random_unit_quaternions(4, seed=7),
                             rng.normal(0, 1.0, (4, 3)), rng.normal(0, 4.0, (4, 3))], axis=1)
    h, chunk, chunks = 0.01, 500, 20
    state, energies, norms = starts, [energy(TETHERED, starts)], []
    for _ in range(chunks):
        state = rollout(TETHERED, state, np.zeros(4), h, chunk, k=4)
        energies.append(energy(TETHERED, state))
        norms.append(np.abs(np.linalg.norm(state[:, 3:7], axis=1) - 1.0))
    energies = np.array(energies)
    assert np.max(norms) < 1e-13
    relative = np.abs(energies - energies[0]) / np.abs(energies[0])
    assert np.all(np.isfinite(energies)) and np.max(relative) < 5e-3, relative.max(0)
    # No drift: the last samples are no further off than the first ones.
    assert np.max(relative[-5:]) < 3 * np.max(relative[1:6]) + 1e-12


# ----------------------------------------------------------------------------- backends
@pytest.mark.parametrize("force_rule", fvin_r3s3.FORCE_RULES)
def test_numpy_torch_casadi_agree_on_one_step(force_rule):
    h, k, u = 0.02, 3, THRUST
    state = START + np.concatenate([np.zeros(7), [0.0, 0.0, 0.0], [1.0, 2.0, -1.0]])
    ref, res_np = step(TETHERED, state, u, h, k, with_residual=True, force_rule=force_rule)
    tor, res_t = step(TETHERED, state, u, h, k, backend="torch", with_residual=True, force_rule=force_rule)
    np.testing.assert_allclose(tor, ref, rtol=0, atol=1e-12)
    assert abs(res_t - res_np) < 1e-12
    function = casadi_step(TETHERED, h, k, force_rule)
    cas = np.array(function(state, u)).ravel()
    np.testing.assert_allclose(cas, ref, rtol=0, atol=1e-12)
    # Its Jacobian in (state, u) against central differences.
    s_in, u_in = ca.SX.sym("s", 13), ca.SX.sym("u", 4)
    jac = ca.Function("J", [s_in, u_in], [ca.jacobian(function(s_in, u_in), ca.vertcat(s_in, u_in))])
    jacobian = np.array(jac(state, u))
    z, eps = np.concatenate([state, u]), 1e-6
    fd = np.stack([(np.array(function(*np.split(z + eps * e, [13]))).ravel()
                    - np.array(function(*np.split(z - eps * e, [13]))).ravel()) / (2 * eps)
                   for e in np.eye(z.size)], axis=1)
    np.testing.assert_allclose(jacobian, fd, rtol=0, atol=1e-6 * max(1.0, np.abs(fd).max()))


def casadi_step(body, h, k, force_rule):
    ops = get_ops("casadi")
    s, u = ca.SX.sym("s", 13), ca.SX.sym("u", body.control_dim)
    c = [tuple(s[i] for i in idx) for idx in (range(3), range(3, 7), range(7, 10), range(10, 13))]
    out = fvin_r3s3.r3s3_step(*c, tuple(u[i] for i in range(body.control_dim)), body.terms(ops), h, k, ops,
                              force_rule=force_rule)
    return ca.Function("F", [s, u], [ca.vertcat(*out.x, *out.q, *out.v, *out.omega)])


# ----------------------------------------------------------------------------- sign
# ----------------------------------------------------------------------------- hard cases
PAST_LIMIT = {"count": 0}


@settings(max_examples=S.budget(80))
@given(body=st.sampled_from([QUADROTOR, TETHERED, ISOTROPIC]), q=S.unit_quaternions(), axis=S.unit_vectors(),
       spin=S.floats(0.0, 2.5), h=S.log_uniform(1e-3, 0.1), k=st.integers(1, 8),
       thrust=S.floats(0.0, 4.0))
@S.counted
def test_fast_spins_stay_finite_and_report_their_residual(body, q, axis, spin, h, k, thrust):
    """``h|ω|`` up to and past ≈ 1: always finite; converged (residual ≈ 0) well inside the limit."""
    state = np.concatenate([X0, q, V0, (spin / h) * axis])
    out, residual = step(body, state, np.full(4, thrust), h, k, with_residual=True)
    assert np.all(np.isfinite(out)) and np.isfinite(residual) and residual >= 0.0
    assert abs(np.linalg.norm(out[3:7]) - 1.0) < 1e-13
    if spin <= 0.5 and k >= 6:
        assert residual < 1e-8 * max(1.0, spin / h)
    # Past the limit it says so: |Φ(ξ)| ≤ Φ_max for every ξ (λ_max(J); j/2 for J = jI), so |C| > Φ_max
    # leaves a mismatch of at least |C| − Φ_max, a residual of (|C| − Φ_max)·2/(h·tr J/3) (rad/s).
    # C from the physical torques (DESIGN.md step 2: C = −(h/2) J ω − (h²/4) τ).
    inertia = np.array(body.inertia)
    x, rot = state[:3], S.rotation_matrix(q)
    d = x + rot @ np.array(body.tether_site) - np.array(body.tether_anchor)
    torque = np.array(body.torque_map) @ np.full(4, thrust) \
        + np.cross(body.tether_site, rot.T @ (-body.tether_stiffness * d))
    rhs = -(h / 2.0) * inertia @ state[10:] - (h * h / 4.0) * torque
    phi_max = inertia[0, 0] / 2.0 if body is ISOTROPIC else np.linalg.eigvalsh(inertia).max()
    excess = np.linalg.norm(rhs) - phi_max
    PAST_LIMIT["count"] += excess > 0
    if excess > 0:
        assert residual >= (1 - 1e-9) * excess * 2.0 / (h * np.trace(inertia) / 3.0)


@settings(max_examples=S.budget(40))
@given(q=S.unit_quaternions(), direction=S.unit_vectors(), distance=S.log_uniform(1.0, 1e4),
       omega=S.vectors(3, -8.0, 8.0), thrust=S.floats(0.0, 4.0))
@S.counted
def test_far_translations_do_not_cost_rotational_accuracy(q, direction, distance, omega, thrust):
    """At ``|x|`` up to 1e4 the rotation is the one at the origin (bit for bit for the free body) and
    the displacement keeps its accuracy to ``ulp(|x|)``."""
    h = 0.01
    near = np.concatenate([np.zeros(3), q, V0, omega])
    far = near.copy()
    far[:3] = distance * direction
    a, b = step(QUADROTOR, near, np.full(4, thrust) * [1, 1.1, 0.9, 1.05], h), \
        step(QUADROTOR, far, np.full(4, thrust) * [1, 1.1, 0.9, 1.05], h)
    np.testing.assert_array_equal(b[3:], a[3:])
    np.testing.assert_allclose(b[:3] - far[:3], a[:3], rtol=0, atol=4 * np.spacing(distance))
