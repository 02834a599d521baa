"""One control problem, two solvers: IPOPT to convergence and the real-time iteration agree on it,
and the features that belong to the problem (the disturbance estimate, the torque reserve, free bodies,
references) are honoured by both. The planar and ball-joint agreement is tests/test_rti.py's
``test_iterations_reach_the_ipopt_optimum_on_a_fixed_problem``; the free body is here."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import iterated_rti_plan

from fvin_mpc.control.flight import quadrotor_mpc_settings
from fvin_mpc.control.model_export import from_closed_form
from fvin_mpc.control.mpc import MPC, MPCSettings
from fvin_mpc.control.problem import ConstantReference, control_bounds
from fvin_mpc.control.rti import RealTimeMPC
from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings
from fvin_mpc.core import s3
from fvin_mpc.core.quadrotor import QUADROTOR
from fvin_mpc.core.space import R3S3

HOVER = np.array([0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])


@pytest.fixture(scope="module")
def craft():
    return from_closed_form(R3S3, QUADROTOR, 0.02, 2, name="true:quadrotor")


def test_ipopt_and_the_rti_reach_the_same_plan_for_a_free_body(craft):
    """From a tilted, displaced, turning start: IPOPT to convergence and RTI iterations with the
    measured state fixed reach the same plan (same cost, same first thrusts)."""
    settings = quadrotor_mpc_settings(horizon=15, compile="none", disturbance_gain=0.0, ipopt={"tol": 1e-10})
    low, high = np.zeros(4), np.full(4, 2.5)
    tilt = 0.4
    x0 = HOVER.copy()
    x0[:3] += (0.2, -0.1, 0.1)
    x0[3:7] = (np.cos(tilt / 2), np.sin(tilt / 2), 0.0, 0.0)
    x0[10:] = (0.5, -0.3, 0.2)
    ipopt = MPC(craft, MPCSettings(**{**settings.__dict__, "solver": "ipopt"}), HOVER, low, high)
    u_ipopt, info = ipopt(x0)
    assert info["success"] and info["status"] == "Solve_Succeeded"
    controller = RealTimeMPC(craft, settings, HOVER, low, high)
    plan, cost, gap = iterated_rti_plan(controller, x0, 30)
    assert gap < 1e-8
    # IPOPT's objective is the same sum of squares; the RTI's QP keeps a barrier floor on the boxes
    assert cost == pytest.approx(info["cost"], rel=1e-4)
    np.testing.assert_allclose(plan.controls[0], u_ipopt, atol=1e-3)
    np.testing.assert_allclose(plan.states, info["states"], atol=1e-3)


def test_the_ipopt_mpc_flies_a_free_body_and_tracks_a_moved_reference(craft):
    """IPOPT on R³ × S³ (the rotation-vector residual, sound upside down): from upside down at the
    hover point, a few waiting-mode periods on the model turn the craft over; a reference moved
    1 m up is followed."""
    settings = quadrotor_mpc_settings(horizon=20, compile="none", solver="ipopt")
    low, high = np.zeros(4), np.full(4, 2.5)
    controller = MPC(craft, settings, HOVER, low, high)
    x = HOVER.copy()
    x[3:7] = (0.0, 1.0, 0.0, 0.0)  # upside down
    for _ in range(60):
        u, info = controller(x)
        assert info["success"] and np.all(u >= low - 1e-9) and np.all(u <= high + 1e-9)
        x = craft(x, u)[0]
    assert abs(x[3]) > 0.98 and np.linalg.norm(x[:3] - HOVER[:3]) < 0.3
    above = HOVER.copy()
    above[2] += 1.0
    controller.set_reference(ConstantReference(above))
    for _ in range(100):
        x = craft(x, controller(x)[0])[0]
    assert np.linalg.norm(x[:3] - above[:3]) < 0.05


def test_the_disturbance_estimate_removes_the_ipopt_hold_error():
    """A constant torque on the plant the model does not know: with the estimate (on by default, as in
    the RTI) IPOPT holds the pendulum upright without the steady error it leaves without it."""
    env = scene_env("pendulum", true_model=True)
    model = scene_model(env, true_model=True)
    errors = {}
    for gain in (0.0, 0.5):
        controller = scene_mpc(env, model, scene_mpc_settings(env, disturbance_gain=gain, compile="none",
                                                              cold_starts=("goal",)))
        x = np.concatenate([controller.goal, np.zeros(3)])
        for _ in range(60):
            u, info = controller(x)
            x = model(x, u + 0.2)[0]  # the plant: 0.2 units of torque the model lacks
        errors[gain] = float(s3.geodesic_angles(x[:4], controller.goal))
        if gain > 0:
            assert info["disturbance"][0] == pytest.approx(0.2, rel=0.05)
    env.close()
    assert errors[0.0] > 1e-3 and errors[0.5] < 1e-5, errors


def test_control_bounds_keep_the_first_control_whole():
    lower, upper = control_bounds(np.array([-1.0]), np.array([3.0]), 4, 0.25)
    assert (lower[0, 0], upper[0, 0]) == (-1.0, 3.0)
    np.testing.assert_allclose(lower[1:, 0], -0.5)
    np.testing.assert_allclose(upper[1:, 0], 2.5)


def test_one_control_weight_per_actuator_is_that_actuator_s_cost():
    """``control_weight`` as a tuple weighs each control on its own (a wrench craft's thrust in N beside
    moments in N·m); a scalar weighs them alike, as before."""
    from fvin_mpc.control.problem import residual_functions

    weights = (0.5, 2.0, 8.0, 32.0)
    u = np.array([1.0, -2.0, 0.5, 0.25])
    stage = {}
    for weight in (weights, 0.5):
        settings = quadrotor_mpc_settings(control_weight=weight)
        function, _ = residual_functions(R3S3.layout, settings, 4, 30.0, None, None)
        residual = np.asarray(function(HOVER, u, HOVER, np.zeros(4))).ravel()
        stage[weight] = residual[-4:]
    np.testing.assert_allclose(stage[weights], np.sqrt(weights) * u, rtol=1e-12)
    np.testing.assert_allclose(stage[0.5], np.sqrt(0.5) * u, rtol=1e-12)
    with pytest.raises(ValueError, match="control_weight"):
        MPCSettings(control_weight=(1.0, -1.0))


@pytest.mark.parametrize("shape, rank", [((6, 4), 4), ((6, 8), 6), ((6, 8), 4), ((6, 6), 4), ((3, 1), 1)])
def test_the_least_squares_inverse_is_the_damped_pseudo_inverse_whatever_the_shape(shape, rank):
    """``B⁺`` is the damped pseudo-inverse for tall, wide and rank-deficient ``B`` (more rotors than rates;
    rotors that all push along one axis), where ``(BᵀB)⁻¹Bᵀ`` was singular."""
    import casadi as ca

    from fvin_mpc.control.problem import LEAST_SQUARES_RIDGE, least_squares_inverse

    rng = np.random.default_rng(rank + shape[1])
    b = rng.normal(size=(shape[0], rank)) @ rng.normal(size=(rank, shape[1]))
    symbol = ca.SX.sym("b", *shape)
    inverse = np.asarray(ca.Function("inverse", [symbol], [least_squares_inverse(symbol)])(b))
    # the damped pseudo-inverse from the SVD: σ / (σ² + λ) on each singular direction
    u, sigma, vt = np.linalg.svd(b, full_matrices=False)
    damped = vt.T @ np.diag(sigma / (sigma**2 + LEAST_SQUARES_RIDGE * np.sum(b**2))) @ u.T
    np.testing.assert_allclose(inverse, damped, atol=1e-5 * np.abs(damped).max())  # an unpivoted solve at cond 1e6
    # …which is the pseudo-inverse where B is well conditioned, and solves B u = r on B's range
    if sigma[rank - 1] > 0.1 * np.linalg.norm(b):
        np.testing.assert_allclose(inverse, np.linalg.pinv(b, rcond=1e-10), atol=1e-3 * np.abs(damped).max())
    np.testing.assert_allclose(b @ inverse @ b, b, atol=1e-3 * np.linalg.norm(b))


def test_the_goal_control_of_crafts_with_six_and_eight_rotors_holds_them(tmp_path):
    """The control that holds the goal (five Newton steps with ``B⁺``) of family crafts with eight tilted
    rotors and six untilted ones: finite, within the thrust bounds, and it holds the craft at rest in the
    model; where the closed form's level hover is unique up to the null space, the same forces. Before,
    ``(BᵀB)⁻¹Bᵀ`` gave goal thrusts of 1e11–1e14 N on every such draw."""
    from fvin_mpc.control.flight import quadrotor_mpc
    from fvin_mpc.core.quadrotor import from_mujoco
    from fvin_mpc.envs import QuadrotorEnv
    from fvin_mpc.envs.flyer_family import flyer_scene, write_flyers

    facts = {seed: flyer_scene(seed)[1] for seed in range(7000, 7014)}
    eight = next(s for s, f in facts.items() if f["rotors"] == 8 and f["actuation"] == "rotors")
    six = next(s for s, f in facts.items() if f["rotors"] == 6 and f["max_tilt_deg"] == 0.0)
    for path in write_flyers([eight, six], tmp_path):
        env = QuadrotorEnv(path)
        craft = from_mujoco(env.model, env.body_name)
        model = from_closed_form(R3S3, craft, env.dt, 2, name="true")
        controller = quadrotor_mpc(env, model, quadrotor_mpc_settings(compile="none"))
        u_goal = controller._u_goal
        assert np.all(np.isfinite(u_goal))
        assert np.all(u_goal >= env.torque_low - 1e-9) and np.all(u_goal <= env.torque_high + 1e-9)
        stepped = np.asarray(model.step(env.goal_state, u_goal)[0]).ravel()
        # at rest after one step: to 1e-6 m/s, the lateral force the damped inverse leaves to the attitude
        np.testing.assert_allclose(stepped[7:], 0.0, atol=1e-6)
        wrench = np.vstack([np.array(craft.force_map), np.array(craft.torque_map)])
        weight = craft.mass * craft.gravity
        np.testing.assert_allclose(wrench @ u_goal, wrench @ np.array(craft.hover_controls), atol=1e-6 * weight)
