"""Non-unit quaternions and a 10⁶-step unforced rollout.

Policy (``StateLayout.check`` of ``fvin_mpc.core.space``, the controller boundary): a measured ``q`` with
``|‖q‖ − 1| ≤ 1e-3`` is normalized, anything further from unit norm raises ``ValueError``. The
pure step :func:`fvin_mpc.core.fvin.fvin_step` is homogeneous math: ``q_{k+1} = q_k ⊗ exp(ξ)`` with a
unit ``exp(ξ)``, so it preserves ``‖q‖`` exactly (to rounding) whatever ``‖q_k‖`` is.
"""

import casadi as ca
import numpy as np
import pytest
import strategies as S
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from fvin_mpc.control import model_export as export
from fvin_mpc.core import fvin
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.rigid_body import PENDULUM
from fvin_mpc.core.space import S3
from fvin_mpc.core.state import UNIT_NORM_TOLERANCE

H = 0.05
NP = get_ops("numpy")
norms = st.one_of(S.log_uniform(1e-3, 1e3), S.floats(0.999, 1.001), st.sampled_from([1e-3, 0.5, 1.0, 2.0]))


# ----------------------------------------------------------------------------- the pure step
@settings(max_examples=S.budget(500))
@given(body=S.rigid_bodies(max_condition=1e3), q=S.unit_quaternions(), norm=norms, omega=S.vectors(3, -15.0, 15.0),
       k=st.integers(1, 6), data=st.data())
@S.counted
def test_step_preserves_the_norm_of_any_quaternion(body, q, norm, omega, k, data):
    u = data.draw(S.vectors(body.control_dim, -2.0, 2.0))
    out = fvin.fvin_step(*S.components(norm * q, omega, u), body.terms(NP), H, k, NP)
    q_next = S.stacked(out.q)
    assert np.all(np.isfinite(q_next)) and np.all(np.isfinite(S.stacked(out.omega)))
    assert abs(np.linalg.norm(q_next) - norm) <= 4e-16 * 8 * norm, (np.linalg.norm(q_next), norm)


@pytest.fixture(scope="module")
def pendulum_step():
    return export.from_rigid_body(PENDULUM, H, 2, name="norm_pendulum")


@settings(max_examples=S.budget(1000))
@given(q=S.unit_quaternions(), norm=norms, omega=S.vectors(3, -15.0, 15.0), u=S.vectors(1, -2.0, 2.0))
@S.counted
def test_casadi_export_preserves_the_norm_of_any_quaternion(pendulum_step, q, norm, omega, u):
    x_next, _ = pendulum_step(np.concatenate([norm * q, omega]), u)
    assert np.all(np.isfinite(x_next))
    assert abs(np.linalg.norm(x_next[:4]) - norm) <= 4e-16 * 8 * norm


# ----------------------------------------------------------------------------- the controller boundary
@settings(max_examples=S.budget(2000))
@given(q=S.unit_quaternions(), norm=st.one_of(S.floats(1 - 3e-3, 1 + 3e-3), S.log_uniform(1e-6, 1e6)),
       omega=S.vectors(3, -50.0, 50.0))
@S.counted
def test_check_state_normalizes_near_unit_and_rejects_the_rest(q, norm, omega):
    measured = norm * q
    actual_norm = np.linalg.norm(measured)
    assume(abs(abs(actual_norm - 1.0) - UNIT_NORM_TOLERANCE) > 1e-12)  # no coin flips at the boundary
    if abs(actual_norm - 1.0) <= UNIT_NORM_TOLERANCE:
        checked = S3.check(np.r_[measured, omega])
        q_checked, omega_checked = checked[:4], checked[4:]
        assert abs(np.linalg.norm(q_checked) - 1.0) <= 4e-16
        np.testing.assert_allclose(q_checked, q, atol=1e-15)
        np.testing.assert_array_equal(omega_checked, omega)
    else:
        with pytest.raises(ValueError, match="not a unit quaternion"):
            S3.check(np.r_[measured, omega])


# ----------------------------------------------------------------------------- 10⁶ steps
INITIAL_ANGLES = (0.3, 2.0, 3.0)  # small swing, large swing, near the separatrix (E close to upright)


@pytest.fixture
def million_step_rollout():
    """States ``(3 initial conditions, 10⁶ + 1, 7)`` of the closed-form pendulum, K = 3, u = 0.

    One compiled ``mapaccum`` of 10⁴ steps over a ``map`` of the initial conditions, called 100
    times (generated C is cached like the MPC's, so only the first run compiles)."""
    model = export.from_rigid_body(PENDULUM, H, 3, name="long_rollout")
    x = ca.SX.sym("x", 7)
    one = ca.Function("unforced", [x], [model.step(x, 0.0)[0]])
    batch = len(INITIAL_ANGLES)
    block = one.map(batch).mapaccum("rollout_block", 10_000)
    compiled, _ = export.compile_functions([block], prefix="hard_long_rollout")
    (run,) = compiled.values()
    x0 = np.array([np.concatenate(S.hinge(theta, 0.0)) for theta in INITIAL_ANGLES]).T  # (7, batch)
    blocks, current = [x0[:, None, :]], x0
    for _ in range(100):
        # Column ``step·batch + b`` of the (7, 10⁴·batch) output is initial condition b after the step.
        states = np.asarray(run(current)).reshape(7, 10_000, batch)
        blocks.append(states)
        current = states[:, -1, :]
    trajectory = np.concatenate(blocks, axis=1)  # (7, 10⁶ + 1, batch)
    return model, np.moveaxis(trajectory, (0, 1, 2), (2, 1, 0))


def test_million_step_rollout_keeps_unit_norm_and_energy_without_drift(million_step_rollout):
    """|q| − 1 < 1e-12 over 10⁶ steps. Variational integrators oscillate around the true energy:
    the error envelope of the last 10 % of 10⁶ steps is that of the first 10 %, and so is its mean.

    (One test, so that xdist does not run the 10⁶ steps once per worker.) K = 3: with K = 2
    (the MPC's default, 5e-4 rad/s Newton error per step) the truncated solve is no longer
    symplectic and the pendulum started at 2 rad loses ~2/3 of its energy over 10⁶ steps (~14 h
    simulated) — irrelevant over an MPC horizon, but use K ≥ 3 for long open-loop rollouts."""
    model, states = million_step_rollout
    assert states.shape == (len(INITIAL_ANGLES), 1_000_001, 7)
    norm_error = np.abs(np.linalg.norm(states[..., :4], axis=-1) - 1.0)
    assert norm_error.max() < 1e-12, norm_error.max()
    for i, theta in enumerate(INITIAL_ANGLES):
        q, omega = states[i, :, :4].T, states[i, :, 4:].T
        energy = np.asarray(fvin.total_energy(tuple(q), tuple(omega), model.numpy_terms))
        error = energy - energy[0]
        tenth = error.size // 10
        first, last = error[:tenth], error[-tenth:]
        envelope = np.abs(first).max()
        assert envelope < 0.05 * energy[0], (theta, envelope, energy[0])  # bounded: O(h²)
        assert np.abs(last).max() <= 1.02 * envelope + 1e-12, (theta, np.abs(last).max(), envelope)
        assert abs(last.mean() - first.mean()) <= 0.02 * envelope + 1e-12, (theta, first.mean(), last.mean())
        # Each trajectory visits its whole energy band in both windows (it is not slowly leaving it).
        assert last.min() <= first.min() + 0.02 * envelope and last.max() >= first.max() - 0.02 * envelope
