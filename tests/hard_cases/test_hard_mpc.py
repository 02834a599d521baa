"""The IPOPT MPC on hard inputs: q vs −q and goal vs −goal, nearly-unit and non-unit
quaternions, exact rest, forced IPOPT failures, NaN/inf/wrong shapes.

MPC objects are built once per module over the closed-form pendulum (cheap to build: the
compiled NLP functions are cached on disk and shared with ``tests/test_mpc.py``); solves cost
milliseconds, so these properties get tens of examples, the input checks (no solve) hundreds.
"""

from dataclasses import replace

import numpy as np
import pytest
import strategies as S
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from fvin_mpc.control import model_export as export
from fvin_mpc.control.mpc import MPC, SUCCESS_STATUSES, IpoptOptions, MPCSettings
from fvin_mpc.core.rigid_body import PENDULUM
from fvin_mpc.core.state import UNIT_NORM_TOLERANCE

UPRIGHT = np.array([0.0, 0.0, 1.0, 0.0])
LOW, HIGH = np.array([-2.0]), np.array([2.0])

# IPOPT limited to one iteration on warm and cold solves.
# the fallback path: an unconverged last iterate is never flown here (tests/test_mpc.py covers that rule)
ONE_ITERATION = MPCSettings(ipopt=IpoptOptions(max_iter=1, cold_max_iter=1, last_iterate_max_defect=None))
angles = S.floats(-np.pi, np.pi)
rates = S.floats(-8.0, 8.0)


@pytest.fixture(scope="module")
def model():
    # Same name and settings as tests/test_mpc.py: the compiled library is shared.
    return export.from_rigid_body(PENDULUM, 0.05, 2, name="test_true_pendulum")


@pytest.fixture(scope="module")
def controllers(model):
    return {
        "plus": MPC(model, MPCSettings(), UPRIGHT, LOW, HIGH),
        "minus": MPC(model, MPCSettings(), -UPRIGHT, LOW, HIGH),
        "max_iter_1": MPC(model, ONE_ITERATION, UPRIGHT, LOW, HIGH),
        # |ω| ≤ 0.05/h = 1 rad/s on every predicted state: infeasible from a fast state.
        "infeasible": MPC(model, replace(MPCSettings(), omega_bound_fraction=0.05), UPRIGHT, LOW, HIGH),
    }


def fresh(controller):
    controller.reset()
    return controller


# ----------------------------------------------------------------------------- q vs −q, goal vs −goal
@settings(max_examples=S.budget(12))
@given(theta=angles, theta_dot=rates)
@S.counted
def test_state_sign_and_goal_sign_give_the_same_cost_and_torque(controllers, theta, theta_dot):
    q, omega = S.hinge(theta, theta_dot)
    u_plus, info_plus = fresh(controllers["plus"])(np.r_[q, omega])
    u_goal, info_goal = fresh(controllers["minus"])(np.r_[q, omega])
    u_flip, info_flip = fresh(controllers["plus"])(np.r_[-q, omega])
    assert info_plus["status"] == info_goal["status"] == info_flip["status"]
    for u in (u_plus, u_goal, u_flip):
        assert np.all(np.isfinite(u)) and np.all((LOW <= u) & (u <= HIGH))
    np.testing.assert_allclose(u_goal, u_plus, atol=1e-6)
    np.testing.assert_allclose(u_flip, u_plus, atol=1e-6)
    if info_plus["success"]:
        assert info_goal["cost"] == pytest.approx(info_plus["cost"], rel=1e-6, abs=1e-9)
        assert info_flip["cost"] == pytest.approx(info_plus["cost"], rel=1e-6, abs=1e-9)
        # The flipped plan is the same motion: states equal up to the sign of q.
        np.testing.assert_allclose(info_flip["states"][:, :4], -info_plus["states"][:, :4], atol=1e-5)


# ----------------------------------------------------------------------------- non-unit quaternions
@settings(max_examples=S.budget(8))
@given(theta=angles, theta_dot=rates, delta=S.floats(-0.99 * UNIT_NORM_TOLERANCE, 0.99 * UNIT_NORM_TOLERANCE))
@S.counted
def test_nearly_unit_quaternion_gives_the_unit_quaternions_torque(controllers, theta, theta_dot, delta):
    q, omega = S.hinge(theta, theta_dot)
    u_unit, _ = fresh(controllers["plus"])(np.r_[q, omega])
    u_scaled, _ = fresh(controllers["plus"])(np.r_[(1.0 + delta) * q, omega])
    np.testing.assert_allclose(u_scaled, u_unit, atol=1e-6)


@settings(max_examples=S.budget(300))
@given(q=S.unit_quaternions(), omega=S.vectors(3, -10.0, 10.0),
       norm=st.one_of(S.floats(1.0 + 1.01 * UNIT_NORM_TOLERANCE, 1.1), S.floats(0.9, 1.0 - 1.01 * UNIT_NORM_TOLERANCE),
                      S.log_uniform(1e-8, 1e8).filter(lambda r: abs(r - 1.0) > 1.01 * UNIT_NORM_TOLERANCE)))
@S.counted
def test_far_from_unit_quaternion_is_refused_without_solving(controllers, q, omega, norm):
    controller = controllers["plus"]
    before = controller._previous
    with pytest.raises(ValueError, match="not a unit quaternion"):
        controller(np.r_[norm * q, omega])
    assert controller._previous is before  # nothing planned, nothing sent


# ----------------------------------------------------------------------------- NaN / inf / shapes
not_numbers = st.sampled_from([None, "1.0", [1.0, "a"], {"q": 1.0}, [[1.0], [2.0, 3.0]], object()])
bad_states = st.one_of(S.non_finite_arrays((7,), -10.0, 10.0),
                       S.wrong_shapes((7,)).map(lambda shape: np.full(shape, 0.5)), not_numbers)


@settings(max_examples=S.budget(400))
@given(x=bad_states)
@S.counted
def test_non_finite_or_misshapen_state_raises_value_error_without_solving(controllers, x):
    controller = controllers["plus"]
    before = controller._previous
    with pytest.raises(ValueError):
        controller(x)
    assert controller._previous is before


# ----------------------------------------------------------------------------- exact rest
@settings(max_examples=S.budget(8))
@given(sign=st.sampled_from([1.0, -1.0]), goal=st.sampled_from(["plus", "minus"]),
       tilt=st.one_of(st.just(0.0), S.signed_log_uniform(1e-12, 1e-6)))
@S.counted
def test_leaves_exact_rest_from_either_sign_and_goal(controllers, sign, goal, tilt):
    """Hanging at rest (or 1e-12 … 1e-6 rad from it) is a stationary point of the swing-up NLP;
    the first guess must break the symmetry: a large first torque, whatever the signs.
    (The closed-loop swing-up from exact rest is ``tests/test_mpc.py::
    test_swings_up_the_mujoco_pendulum_from_rest_and_holds``; the learned model's is below.)"""
    q, omega = S.hinge(tilt, 0.0)
    u, info = fresh(controllers[goal])(np.r_[sign * q, omega])
    assert info["success"], info["status"]
    assert abs(u[0]) > 1.0, u


@pytest.mark.slow
def test_learned_checkpoint_swings_up_from_exact_rest():
    """Closed loop on MuJoCo from exact rest with the MPC planning on the shipped learned
    ``pendulum_sign-invariant`` model (slow: builds and compiles the learned-model NLP once).
    A missing shipped checkpoint is a failure, not a skip."""
    from fvin_mpc.control.closed_loop import episode_metrics, run_episode
    from fvin_mpc.control.scene import scene_model, scene_mpc
    from fvin_mpc.envs import RigidBodyEnv

    env = RigidBodyEnv("pendulum")
    controller = scene_mpc(env, scene_model(env, "pendulum_sign-invariant"))
    episode, _ = run_episode(env, controller, duration_s=8.0)
    metrics = episode_metrics(episode)
    assert abs(episode.u[0][0]) > 1.0  # left rest on the first call
    assert metrics["swung_up"], metrics
    assert metrics["max_abs_torque"] <= 2.0 and np.all(np.isfinite(episode.u))


# ----------------------------------------------------------------------------- forced failures
@settings(max_examples=S.budget(40))
@given(q=S.unit_quaternions(), omega=S.vectors(3, -10.0, 10.0))
@S.counted
def test_one_iteration_limit_returns_a_bounded_finite_torque_and_reports_failure(controllers, q, omega):
    """Any state, IPOPT allowed one iteration: the torque is finite and within bounds, and a
    failure (iteration limit, or infeasibility detected at once) is reported as such with the
    zero fallback. A state whose first guess is already optimal (e.g. upright at rest) may
    legitimately succeed within the one iteration."""
    u, info = fresh(controllers["max_iter_1"])(np.r_[q, omega])
    assert np.all(np.isfinite(u)) and np.all((LOW <= u) & (u <= HIGH))
    if info["success"]:
        assert info["status"] in SUCCESS_STATUSES and info["iterations"] <= 1 and info["fallback"] is None
    else:
        assert info["status"] not in SUCCESS_STATUSES
        assert info["fallback"] == "zero" and np.array_equal(u, [0.0])
        assert np.isnan(info["cost"])


@settings(max_examples=S.budget(10))
@given(theta=angles, theta_dot=S.floats(-4.0, 4.0))
@S.counted
def test_failure_after_a_plan_falls_back_to_that_plan_within_bounds(controllers, theta, theta_dot):
    q, omega = S.hinge(theta, theta_dot)
    good, failing = fresh(controllers["plus"]), fresh(controllers["max_iter_1"])
    _, good_info = good(np.r_[q, omega])
    assume(good_info["success"])
    failing._previous = good._previous  # the plan made one period ago
    u, info = failing(np.r_[q, omega])
    assert not info["success"] and info["fallback"] == "previous-plan"
    assert np.all(np.isfinite(u)) and np.all((LOW <= u) & (u <= HIGH))
    assert u[0] == pytest.approx(np.clip(good_info["controls"][1, 0], LOW[0], HIGH[0]))


@settings(max_examples=S.budget(8))
@given(theta=angles, theta_dot=st.one_of(S.floats(4.0, 15.0), S.floats(-15.0, -4.0)))
@S.counted
def test_infeasible_omega_bound_returns_a_bounded_finite_torque_and_reports_failure(controllers, theta, theta_dot):
    """|θ̇| ≥ 4 rad/s cannot be braked to |ω| ≤ 1 in one step with |τ| ≤ 2: the NLP is infeasible."""
    q, omega = S.hinge(theta, theta_dot)
    u, info = fresh(controllers["infeasible"])(np.r_[q, omega])
    assert not info["success"], info["status"]
    assert info["fallback"] in ("zero", "previous-plan")
    assert np.all(np.isfinite(u)) and np.all((LOW <= u) & (u <= HIGH))
    assert np.isfinite(info["step_residual"])
