"""Anisotropic inertia (condition number up to 1e3) and arbitrary 3-D axes against Euler's
equations.

Random :class:`~fvin_mpc.core.rigid_body.PivotedRigidBody`: a physical inertia (principal moments obey
the triangle inequality; a thin rod ``(ε, 1, 1)`` reaches condition 1e3) rotated arbitrarily, a
random centre of mass and actuator axes, optional damping. The reference is written here from
the physics, not from the package: ``q̇ = ½ q ⊗ (0, ω)``, ``J ω̇ = −ω × Jω + c × Rᵀ(−m g e_z) + B u
− d ω``, integrated by DOP853 at rtol = atol = 1e-12. The FVIN step (K = 4, converged) is second
order, with or without damping: halving ``h`` divides the maximum error over the run by ≈ 4; its
energy error (unforced) scales the same way and ``|q|`` stays 1.
"""

import numpy as np
import pytest
import strategies as S
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp

from fvin_mpc.core import fvin
from fvin_mpc.core.backend import get_ops

NP = get_ops("numpy")
K = 4  # converged: at h·Ω ≤ 0.25 the Newton error after 4 iterations is below 1e-12


def euler_rhs(body, u):
    inertia = np.array(body.inertia)
    inverse = np.linalg.inv(inertia)

    def rhs(_t, y):
        q, omega = y[:4], y[4:]
        q_dot = 0.5 * S.quat_multiply(q, np.concatenate([[0.0], omega]))
        torque = S.physical_torque(body, q, omega, u)
        omega_dot = inverse @ (torque - np.cross(omega, inertia @ omega))
        return np.concatenate([q_dot, omega_dot])

    return rhs


def reference(body, q0, omega0, u, times):
    sol = solve_ivp(euler_rhs(body, u), (0.0, times[-1]), np.concatenate([q0, omega0]), method="DOP853",
                    rtol=1e-12, atol=1e-12, t_eval=times)
    assert sol.success
    return sol.y.T  # (len(times), 7)


def fvin_run(body, q0, omega0, u, h, steps, every):
    """States after every ``every`` steps (including the start)."""
    terms = body.terms(NP)
    q, omega = S.components(q0, omega0)
    u_c = S.components(u)[0]
    out = [np.concatenate([q0, omega0])]
    for k in range(1, steps + 1):
        result = fvin.fvin_step(q, omega, u_c, terms, h, K, NP)
        q, omega = result.q, result.omega
        if k % every == 0:
            out.append(np.concatenate([S.stacked(q), S.stacked(omega)]))
    return np.array(out)


def time_scale(body, omega0, u):
    """A rate (rad/s) the step must resolve: spin, pendulum and actuator frequencies, and the
    damping's decay rate ``d/λ_min``."""
    lam_min = np.linalg.eigvalsh(np.array(body.inertia))[0]
    gravity = body.mass_gravity * np.linalg.norm(body.center_of_mass)
    actuation = np.linalg.norm(np.array(body.actuator_axes) @ u)
    return max(np.linalg.norm(omega0), np.sqrt(gravity / lam_min), np.sqrt(actuation / lam_min),
               body.damping / lam_min, 0.5)


def error(states, ref, rate):
    dq = np.minimum(
        np.linalg.norm(states[:, :4] - ref[:, :4], axis=1), np.linalg.norm(states[:, :4] + ref[:, :4], axis=1)
    )
    return np.max(dq + np.linalg.norm(states[:, 4:] - ref[:, 4:], axis=1) / rate)


def observed_orders(body, q0, direction, spin, u, coarse=16):
    """``(orders, errors)`` of runs with h, h/2, h/4 against the ODE over ``2/rate`` seconds."""
    lam_min = np.linalg.eigvalsh(np.array(body.inertia))[0]
    gravity_rate = np.sqrt(body.mass_gravity * np.linalg.norm(body.center_of_mass) / lam_min)
    omega0 = spin * max(gravity_rate, 1.0) * direction
    rate = time_scale(body, omega0, u)
    duration = 2.0 / rate
    times = np.linspace(0.0, duration, coarse + 1)
    ref = reference(body, q0, omega0, u, times)
    peak = max(rate, np.abs(ref[:, 4:]).max())
    h = duration / coarse
    assume(h * peak <= 0.25)  # the coarse run must resolve the fastest rate reached
    errors = [error(fvin_run(body, q0, omega0, u, h / 2**i, coarse * 2**i, 2**i), ref, peak) for i in range(3)]
    assume(errors[-1] > 1e-9)  # well above the reference's own error
    return np.log2(np.array(errors[:-1]) / np.array(errors[1:])), errors, h * peak


@pytest.mark.parametrize("damping", [False, True], ids=["undamped", "damped"])
@settings(max_examples=S.budget(25))
@given(q0=S.unit_quaternions(), direction=S.unit_vectors(), spin=S.floats(0.0, 1.0), data=st.data())
@S.counted
def test_step_converges_at_second_order_to_eulers_equations(damping, q0, direction, spin, data):
    """Gravity and a constant actuator torque, with or without viscous damping ``−dω``: order 2
    (slope of the max error in h). The discrete forces take the damping at both ends of the step,
    ``f⁻ = (h/2)(g u − D ω_k)`` and ``f⁺ = (h/2)(g u − D ω_{k+1})`` (the trapezoidal rule; ``f⁺`` is
    linear in ``ω_{k+1}``, so step 5 is a 3×3 linear solve), which keeps the step symmetric.
    (Holding ``−D ω_k`` in both, as an earlier version did, is first order: ``HYPOTHESIS_PROFILE=thorough``
    found orders 0.77 on such a body.)"""
    body = data.draw(S.rigid_bodies(max_condition=1e3, physical=True, gravity=True, damping=damping,
                                    scales=(0.05, 5.0)))
    u = data.draw(S.vectors(body.control_dim, -1.0, 1.0))
    orders, errors, resolution = observed_orders(body, q0, direction, spin, u)
    assert 1.7 <= orders[-1] <= 2.3, (orders, errors)
    assert orders[0] >= 1.5, (orders, errors)
    assert errors[0] <= 10.0 * resolution**2, (errors, resolution)


@settings(max_examples=S.budget(12))
@given(body=S.rigid_bodies(max_condition=1e3, physical=True, gravity=True, scales=(0.05, 5.0)),
       q0=S.unit_quaternions(), direction=S.unit_vectors(), spin=S.floats(0.0, 1.0))
@S.counted
def test_unforced_energy_error_is_second_order_and_norm_stays_one(body, q0, direction, spin):
    lam_min = np.linalg.eigvalsh(np.array(body.inertia))[0]
    gravity_rate = np.sqrt(body.mass_gravity * np.linalg.norm(body.center_of_mass) / lam_min)
    omega0 = spin * max(gravity_rate, 1.0) * direction
    zero = np.zeros(body.control_dim)
    rate = time_scale(body, omega0, zero)
    # Energy scale: the kinetic energy at the rate plus the potential's range.
    scale = 0.5 * lam_min * rate**2 + 2 * body.mass_gravity * np.linalg.norm(body.center_of_mass)
    h = 0.03 / rate
    drifts = []
    for i in range(2):
        states = fvin_run(body, q0, omega0, zero, h / 2**i, 100 * 2**i, 1)
        assert np.abs(np.linalg.norm(states[:, :4], axis=1) - 1.0).max() < 1e-13
        energy = np.asarray(fvin.total_energy(tuple(states[:, :4].T), tuple(states[:, 4:].T), body.terms(NP)))
        drifts.append(np.abs(energy - energy[0]).max())
    assert drifts[0] <= 0.05 * scale, (drifts, scale)  # bounded, O((hΩ)²)
    if drifts[0] > 1e-9 * scale:  # (a torque-free symmetric case conserves it to rounding)
        assert 2.8 <= drifts[0] / drifts[1] <= 5.5, drifts
