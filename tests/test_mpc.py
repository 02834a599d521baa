"""IPOPT MPC over the exported step: swing-up in MuJoCo, sign invariance, failures, input checks."""

from dataclasses import replace

import numpy as np
import pytest
from helpers import hinge

from fvin_mpc.control import model_export as export
from fvin_mpc.control.mpc import MPC, IpoptOptions, MPCSettings, RTIOptions
from fvin_mpc.control.rti import RealTimeMPC
from fvin_mpc.core.rigid_body import PENDULUM

UPRIGHT = np.array([0.0, 0.0, 1.0, 0.0])
HANGING = np.array([1.0, 0.0, 0.0, 0.0])


@pytest.fixture(scope="module")
def true_model():
    return export.from_rigid_body(PENDULUM, 0.05, 2, name="test_true_pendulum")


@pytest.fixture(scope="module")
def controller(true_model):
    return MPC(true_model, MPCSettings(), UPRIGHT, [-2.0], [2.0])




def test_swings_up_the_mujoco_pendulum_from_rest_and_holds(true_model):
    from fvin_mpc.control.closed_loop import episode_metrics, run_episode
    from fvin_mpc.envs import RigidBodyEnv

    env = RigidBodyEnv("pendulum")
    mpc = MPC(true_model, MPCSettings(), env.goal, env.torque_low, env.torque_high)
    episode, _ = run_episode(env, mpc, duration_s=8.0)
    metrics = episode_metrics(episode)
    assert metrics["swung_up"], metrics
    assert metrics["hold_error_rad"] < 0.05
    assert metrics["max_abs_torque"] <= 2.0
    assert metrics["controller_failures"] == 0
    # With |τ| ≤ 2 the pendulum cannot go straight up (max gravity torque is 5): it must pump.
    assert metrics["time_to_upright_s"] > 1.5
    assert np.all(np.isfinite(episode.u))


def test_goal_sign_and_state_sign_do_not_change_the_torque(true_model):
    plus = MPC(true_model, MPCSettings(), UPRIGHT, [-2.0], [2.0])
    minus = MPC(true_model, MPCSettings(), -UPRIGHT, [-2.0], [2.0])
    for theta, theta_dot in [(2.5, 1.0), (-2.9, -0.5), (1.0, 3.0)]:
        q, omega = hinge(theta, theta_dot)
        for controller in (plus, minus):
            controller.reset()
        u_plus, info_plus = plus(np.r_[q, omega])
        u_minus, info_minus = minus(np.r_[q, omega])
        plus.reset()
        u_flipped, info_flipped = plus(np.r_[-q, omega])
        assert info_plus["success"] and info_minus["success"] and info_flipped["success"]
        np.testing.assert_allclose(u_minus, u_plus, atol=1e-6)
        np.testing.assert_allclose(u_flipped, u_plus, atol=1e-6)
        assert info_minus["cost"] == pytest.approx(info_plus["cost"], rel=1e-6)
        assert info_flipped["cost"] == pytest.approx(info_plus["cost"], rel=1e-6)


def test_leaves_exact_rest(controller):
    """Hanging at rest is a stationary point; the first guess must break the symmetry."""
    controller.reset()
    u, info = controller(np.r_[HANGING, np.zeros(3)])
    assert info["success"]
    assert abs(u[0]) > 1.0


def test_failed_solve_returns_previous_plan_then_zero(true_model):
    """IPOPT stopped after one iteration: the torque is finite, bounded and the status reported."""
    good = MPC(true_model, MPCSettings(), UPRIGHT, [-2.0], [2.0])
    one_iteration = IpoptOptions(max_iter=1, cold_max_iter=1, last_iterate_max_defect=None)
    failing = MPC(true_model, MPCSettings(ipopt=one_iteration), UPRIGHT, [-2.0], [2.0])
    q, omega = hinge(0.3, 0.0)
    u, info = failing(np.r_[q, omega])
    assert not info["success"] and info["status"] == "Maximum_Iterations_Exceeded"
    assert info["fallback"] == "zero" and np.array_equal(u, [0.0])
    # After a successful plan, a failure falls back to that plan advanced by one step.
    u_good, good_info = good(np.r_[q, omega])
    failing._previous = good._previous
    u_fallback, info = failing(np.r_[q, omega])
    assert info["fallback"] == "previous-plan" and not info["success"]
    assert u_fallback[0] == pytest.approx(good_info["controls"][1, 0])
    assert np.all(np.abs(u_fallback) <= 2.0)


def test_unconverged_solve_flies_its_last_iterate_only_when_it_is_a_model_trajectory(true_model):
    """Stopped at its iteration limit (25 of the 70 this solve needs) with every dynamics defect within
    the tolerance: with no earlier plan it beats the zero torque, so it is flown and said so. With the
    tolerance at zero nothing unconverged is flown."""
    q, omega = hinge(2.5, 1.0)
    x0 = np.r_[q, omega]
    # the exact-Hessian retry off: the limited Gauss–Newton solve itself is what is flown
    limited_options = IpoptOptions(max_iter=25, cold_max_iter=25, exact_retry=False)
    limited = MPC(true_model, MPCSettings(ipopt=limited_options), UPRIGHT, [-2.0], [2.0])
    u, info = limited(x0)
    assert not info["success"] and info["status"] == "Maximum_Iterations_Exceeded"
    assert info["fallback"] == "last-iterate" and np.isfinite(info["cost"])
    assert u[0] == pytest.approx(np.clip(info["controls"][0, 0], -2.0, 2.0))
    states, controls = info["states"], info["controls"]
    stepped = np.array([true_model.rollout(states[k], controls[k:k + 1])[1] for k in range(len(controls))])
    assert np.max(np.abs(stepped - states[1:])) <= 1e-4 + 1e-9
    strict_options = IpoptOptions(max_iter=25, cold_max_iter=25, last_iterate_max_defect=0.0,
                                   exact_retry=False)
    strict = MPC(true_model, MPCSettings(ipopt=strict_options), UPRIGHT, [-2.0], [2.0])
    u, info = strict(x0)
    assert info["fallback"] == "zero" and np.array_equal(u, [0.0])
    with pytest.raises(ValueError, match="last_iterate_max_defect"):
        IpoptOptions(last_iterate_max_defect=-1.0)


def test_infeasible_problem_falls_back_within_bounds(true_model):
    """An ω bound the measured state already violates makes the NLP infeasible."""
    controller = MPC(true_model, replace(MPCSettings(), omega_bound_fraction=0.05), UPRIGHT, [-2.0], [2.0])
    q, omega = hinge(0.0, 6.0)  # |ω| = 6 > 0.05/h = 1, and torque 2 cannot brake it in one step
    u, info = controller(np.r_[q, omega])
    assert not info["success"]
    assert np.all(np.isfinite(u)) and np.all(np.abs(u) <= 2.0)


@pytest.mark.parametrize("q, omega, message", [
    (np.array([1.0, 0, 0]), np.zeros(3), "shape"),
    (HANGING, np.zeros(4), "shape"),
    (np.array([np.nan, 0, 0, 1.0]), np.zeros(3), "NaN or inf"),
    (HANGING, np.array([0.0, np.inf, 0.0]), "NaN or inf"),
    (2.0 * HANGING, np.zeros(3), "not a unit quaternion"),
])
def test_rejects_bad_states(controller, q, omega, message):
    with pytest.raises(ValueError, match=message):
        controller(np.r_[q, omega])


def test_nearly_unit_quaternion_is_normalized(controller):
    q, omega = hinge(2.0, 0.5)
    controller.reset()
    u_exact, _ = controller(np.r_[q, omega])
    controller.reset()
    u_scaled, _ = controller(np.r_[q * (1 + 5e-4), omega])
    np.testing.assert_allclose(u_scaled, u_exact, atol=1e-6)


@pytest.mark.parametrize("hessian", ["exact", "limited-memory"])
def test_hessian_options_reach_the_same_plan(true_model, controller, hessian):
    """Near upright the NLP is well posed: every Hessian option converges to the same optimum."""
    other = MPC(true_model, MPCSettings(ipopt=IpoptOptions(hessian=hessian, tol=1e-9)), UPRIGHT, [-2.0], [2.0])
    reference = MPC(true_model, MPCSettings(ipopt=IpoptOptions(tol=1e-9)), UPRIGHT, [-2.0], [2.0])
    q, omega = hinge(np.pi - 0.3, 0.5)
    u_ref, info_ref = reference(np.r_[q, omega])
    u_other, info_other = other(np.r_[q, omega])
    assert info_ref["success"] and info_other["success"]
    np.testing.assert_allclose(u_other, u_ref, atol=1e-4)
    assert info_other["cost"] == pytest.approx(info_ref["cost"], rel=1e-6)


def test_uncompiled_solver_matches_compiled(true_model):
    compiled = MPC(true_model, MPCSettings(ipopt=IpoptOptions(tol=1e-9)), UPRIGHT, [-2.0], [2.0])
    interpreted = MPC(true_model, MPCSettings(compile="none", ipopt=IpoptOptions(tol=1e-9)), UPRIGHT, [-2.0], [2.0])
    assert interpreted.compile_report is None and compiled.compile_report is not None
    q, omega = hinge(1.0, -2.0)
    u_c, info_c = compiled(np.r_[q, omega])
    u_i, info_i = interpreted(np.r_[q, omega])
    np.testing.assert_allclose(u_i, u_c, atol=1e-7)
    np.testing.assert_allclose(info_i["states"], info_c["states"], atol=1e-6)


def test_plan_obeys_bounds_and_dynamics(controller, true_model):
    controller.reset()
    q, omega = hinge(0.5, 4.0)
    _, info = controller(np.r_[q, omega])
    states, controls = info["states"], info["controls"]
    assert np.all(np.abs(controls) <= 2.0 + 1e-8)
    assert np.all(np.abs(states[1:, 4:]) <= controller.omega_bound + 1e-8)
    for k in range(controller.horizon):
        np.testing.assert_allclose(true_model(states[k], controls[k])[0], states[k + 1], atol=1e-6)


def test_settings_are_validated():
    with pytest.raises(ValueError, match="horizon"):
        MPCSettings(horizon=0)
    with pytest.raises(ValueError, match="initial_torque_fraction"):
        MPCSettings(initial_torque_fraction=0.0)
    with pytest.raises(ValueError, match="omega_bound_fraction"):
        MPCSettings(omega_bound_fraction=1.5)
    for reserve in (-0.1, 1.0):
        with pytest.raises(ValueError, match="torque_reserve"):
            MPCSettings(torque_reserve=reserve)


@pytest.mark.parametrize("solver", ["ipopt", "rti"])
def test_torque_reserve_bounds_the_plan_after_its_first_control(true_model, solver):
    """The first control keeps the whole range; the later ones the middle (1 − r) of it — also for
    asymmetric bounds, with either solver (the reserve is the problem's). From hanging with a little
    speed the swing-up saturates, so the bounds bind."""
    reserve, low, high = 0.2, -1.0, 3.0
    settings = MPCSettings(torque_reserve=reserve, compile="none", solver=solver,
                           rti=RTIOptions(cold_iter=30, cold_budget_s=30.0))
    mpc = (RealTimeMPC if solver == "rti" else MPC)(true_model, settings, UPRIGHT, [low], [high])
    q, omega = hinge(0.3, 1.0)
    u, info = mpc(np.r_[q, omega])
    assert info["success"]
    controls = info["controls"][:, 0]
    middle, half_range = 0.5 * (high + low), 0.5 * (high - low)
    inner_low, inner_high = middle - (1 - reserve) * half_range, middle + (1 - reserve) * half_range
    assert np.all(controls[1:] >= inner_low - 1e-6) and np.all(controls[1:] <= inner_high + 1e-6)
    assert np.isclose(controls[1:].max(), inner_high, atol=1e-4) or np.isclose(controls[1:].min(), inner_low, atol=1e-4)
    assert low - 1e-9 <= u[0] <= high + 1e-9
    # the first control may leave the inner band (the reserve is there for it)
    assert u[0] > inner_high + 1e-3 or u[0] < inner_low - 1e-3


# ---------------------------------------------------------------------- terminal energy cost
def _stage_cost(settings, states, controls, goal):
    """The quadratic part of the objective, recomputed from the plan with NumPy."""
    def orientation(q):
        return float(q @ q - (goal @ q) ** 2)

    n = len(controls)
    cost = sum(
        settings.orientation_weight * orientation(states[k, :4]) + settings.omega_weight * states[k, 4:] @ states[k, 4:]
        for k in range(n)
    )
    cost += settings.control_weight * float(np.sum(controls ** 2))
    return cost + settings.terminal_orientation_weight * orientation(states[n, :4]) \
        + settings.terminal_omega_weight * states[n, 4:] @ states[n, 4:]


def test_energy_cost_is_the_weighted_squared_normalized_deficit(true_model):
    """IPOPT's reported cost = the quadratic terms + W_E·((E(x_N) − E_goal)/|E_goal − E_rest|)², recomputed."""
    settings = replace(MPCSettings(), terminal_energy_weight=50.0, compile="none")
    controller = MPC(true_model, settings, UPRIGHT, [-2.0], [2.0], rest=HANGING)
    _, info = controller(np.r_[hinge(0.4, 0.0)])
    assert info["success"]
    states, controls = info["states"], info["controls"]
    zero = np.zeros(3)
    goal_energy, rest_energy = true_model.energy(np.r_[UPRIGHT, zero]), true_model.energy(np.r_[HANGING, zero])
    deficit = (true_model.energy(states[-1]) - goal_energy) / abs(goal_energy - rest_energy)
    assert abs(deficit) > 1e-3  # the term is active in this plan
    expected = _stage_cost(settings, states, controls, UPRIGHT) + 50.0 * deficit ** 2
    assert info["cost"] == pytest.approx(expected, rel=1e-9)


def test_energy_cost_gauss_newton_and_exact_hessian_reach_the_same_plan(true_model):
    """The Gauss–Newton Hessian adds 2·W_E∇e∇eᵀ; a wrong one would stall IPOPT or change the optimum."""
    plans = {}
    for hessian in ("gauss-newton", "exact"):
        settings = MPCSettings(terminal_energy_weight=100.0, compile="none",
                               ipopt=IpoptOptions(hessian=hessian, tol=1e-10))
        _, plans[hessian] = MPC(true_model, settings, UPRIGHT, [-2.0], [2.0], rest=HANGING)(
            np.r_[hinge(np.pi - 0.6, 1.0)]
        )
    assert plans["gauss-newton"]["success"] and plans["exact"]["success"]
    np.testing.assert_allclose(plans["gauss-newton"]["controls"], plans["exact"]["controls"], atol=1e-5)


def test_energy_cost_pumps_where_the_short_horizon_stalls(true_model):
    """0.35 rad from hanging, 0.27 rad/s (evaluation episode 33): the 1.5 s plan without the
    energy term keeps deferring the swing-up; with it the controller pumps and ends upright."""
    from fvin_mpc.control.closed_loop import episode_metrics, run_episode
    from fvin_mpc.envs import RigidBodyEnv

    env = RigidBodyEnv(scene="pendulum")
    start = {"random": True, "max_omega": 2.0}  # with seed 33: the evaluation's episode 33
    outcome = {}
    for weight in (0.0, 1000.0):
        controller = MPC(true_model, replace(MPCSettings(), terminal_energy_weight=weight), UPRIGHT, [-2.0], [2.0],
                         rest=HANGING)
        episode, _ = run_episode(env, controller, 8.0, start, seed=33)
        outcome[weight] = episode_metrics(episode)
    assert not outcome[0.0]["success"]
    assert outcome[1000.0]["success"] and outcome[1000.0]["time_to_upright_s"] < 4.0


def test_energy_cost_needs_distinct_goal_and_rest_energies(true_model):
    with pytest.raises(ValueError, match="different goal and rest energies"):
        MPC(true_model, replace(MPCSettings(), terminal_energy_weight=1.0, compile="none"), HANGING, [-2.0], [2.0],
            rest=HANGING)
    with pytest.raises(ValueError, match="needs the rest orientation"):
        MPC(true_model, replace(MPCSettings(), terminal_energy_weight=1.0, compile="none"), UPRIGHT, [-2.0], [2.0])
    with pytest.raises(ValueError, match="terminal_energy_weight"):
        MPCSettings(terminal_energy_weight=-1.0)


def test_swingup_cli_runs_with_the_scene_settings_and_overrides(tmp_path, capsys):
    import json

    from fvin_mpc import swingup

    with pytest.raises(SystemExit) as exit_info:
        swingup.main(["--help"])
    assert exit_info.value.code == 0 and "--energy-weight" in capsys.readouterr().out
    out = tmp_path / "run.json"
    assert swingup.main(["--true-model", "--duration", "0.5", "--plot", "", "--quiet", "--json", str(out)]) == 0
    summary = json.loads(out.read_text())
    from fvin_mpc.control.mpc import COLD_STARTS
    from fvin_mpc.control.scene import DEFAULT_TERMINAL_ENERGY_WEIGHT

    assert summary["terminal_energy_weight"] == DEFAULT_TERMINAL_ENERGY_WEIGHT > 0
    assert summary["horizon"] == 30 and summary["solver_failures"] == 0
    assert tuple(summary["cold_starts"]) == COLD_STARTS  # the controller the evaluation reports
    assert swingup.main(["--true-model", "--duration", "0.5", "--plot", "", "--quiet", "--json", str(out),
                         "--energy-weight", "0", "--horizon", "20"]) == 0
    summary = json.loads(out.read_text())
    assert (summary["terminal_energy_weight"], summary["horizon"]) == (0.0, 20)


def test_settings_split_into_the_problem_and_each_solvers_options(true_model):
    """``updated`` changes problem fields by name and a solver's options by a mapping of its fields (the
    rest of those options kept); each options object checks its own fields; a solver refuses what it
    cannot honour instead of ignoring it."""
    base = MPCSettings(ipopt=IpoptOptions(max_iter=7))
    changed = base.updated(horizon=12, ipopt={"tol": 1e-8}, rti={"dynamics": "implicit"})
    assert (changed.horizon, changed.ipopt.max_iter, changed.ipopt.tol) == (12, 7, 1e-8)
    assert changed.rti.dynamics == "implicit"
    assert changed.updated(rti=RTIOptions()).rti == RTIOptions()
    with pytest.raises(ValueError, match="qp_iterations"):
        RTIOptions(qp_iterations=0)
    with pytest.raises(ValueError, match="unknown qp_method"):
        RTIOptions(qp_method="newton")
    with pytest.raises(ValueError, match="warm_start"):
        IpoptOptions(warm_start="sometimes")
    with pytest.raises(ValueError, match="IpoptOptions"):
        MPCSettings(ipopt={"max_iter": 3})
    with pytest.raises(ValueError, match="RealTimeMPC"):
        MPC(true_model, MPCSettings(solver="rti"), UPRIGHT, [-2.0], [2.0])
    import casadi as ca

    x = ca.MX.sym("x", 7)
    with pytest.raises(ValueError, match="terminal_cost"):
        RealTimeMPC(true_model, MPCSettings(solver="rti"), UPRIGHT, [-2.0], [2.0],
                    terminal_cost=ca.Function("speed", [x], [ca.sumsqr(x[4:])]))
    with pytest.raises(ValueError, match="cold_start_score"):
        RealTimeMPC(true_model, MPCSettings(solver="rti"), UPRIGHT, [-2.0], [2.0],
                    cold_start_score=lambda states, controls: 0.0)
