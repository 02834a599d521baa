"""The learned model's value function for Pendulum-v1 and the MPC's terminal-cost hook."""

from dataclasses import replace
from itertools import product

import casadi as ca
import numpy as np
import pytest
from helpers import hinge

from benchmarks import pendulum_v1_exact as exact
from benchmarks import pendulum_v1_mpc as v1
from benchmarks import pendulum_v1_value as pv
from fvin_mpc.control import model_export as export
from fvin_mpc.control.mpc import MPC, IpoptOptions, MPCSettings
from fvin_mpc.core.rigid_body import PENDULUM
from fvin_mpc.envs.pendulum_v1 import state_from_v1_observation

UPRIGHT = np.array([0.0, 0.0, 1.0, 0.0])


@pytest.fixture(scope="module")
def true_model():
    return export.from_rigid_body(PENDULUM, 0.05, 2, name="test_true_pendulum")


def _lattice(n_theta=8, n_rate=5, torques=(-2.0, 0.0, 2.0)):
    """A map that sends grid points to grid points: θ index += rate index − 2, rate index += torque index − 1."""
    thetas, rates = pv.grid_axes(n_theta, n_rate)
    i, j, k = np.meshgrid(np.arange(n_theta), np.arange(n_rate), np.arange(len(torques)), indexing="ij")
    next_j = np.clip(j + k - 1, 0, n_rate - 1)
    return thetas, rates, np.array(torques), thetas[(i + next_j - 2) % n_theta], rates[next_j], next_j


def test_value_iteration_equals_brute_force_on_a_lattice():
    """Where the map stays on the grid the interpolation is exact: the DP's V_T is the minimum over every
    torque sequence of the summed stage costs."""
    thetas, rates, torques, next_theta, next_rate, next_j = _lattice()
    steps = 3
    value = pv.value_iteration(next_theta, next_rate, torques, steps)
    n_theta, n_rate = len(thetas), len(rates)
    for i0, j0 in product(range(n_theta), range(n_rate)):
        best = np.inf
        for sequence in product(range(len(torques)), repeat=steps):
            i, j, total = i0, j0, 0.0
            for k in sequence:
                total += float(exact.v1_cost(thetas[i], rates[j], torques[k]))
                j_next = int(next_j[i, j, k])
                i, j = (i + j_next - 2) % n_theta, j_next
            best = min(best, total)
        assert value[i0, j0] == pytest.approx(best, abs=1e-9), (i0, j0)


def test_value_iteration_noise_averages_and_zero_steps_is_zero():
    thetas, rates, torques, next_theta, next_rate, _ = _lattice()
    assert np.all(pv.value_iteration(next_theta, next_rate, torques, 0) == 0.0)
    sharp = pv.value_iteration(next_theta, next_rate, torques, 2)
    smooth = pv.value_iteration(next_theta, next_rate, torques, 2, noise=(0.5, 2.0))
    assert not np.allclose(sharp, smooth)
    # One step to go has no next value to average: noise changes nothing.
    np.testing.assert_allclose(pv.value_iteration(next_theta, next_rate, torques, 1, noise=(0.5, 2.0)),
                               pv.value_iteration(next_theta, next_rate, torques, 1))
    with pytest.raises(ValueError):
        pv.value_iteration(next_theta, next_rate, torques[:2], 1)


def test_interpolation_is_periodic_in_theta_and_exact_at_grid_points():
    thetas, rates = pv.grid_axes(16, 9)
    table = np.cos(thetas)[:, None] + 0.1 * rates[None, :] ** 2
    np.testing.assert_allclose(pv.interpolate(table, thetas[:, None], rates[None, :]), table, atol=1e-12)
    theta, rate = np.array([0.3, -3.1, 3.0]), np.array([0.5, -7.0, 2.2])
    np.testing.assert_allclose(pv.interpolate(table, theta + 2 * np.pi, rate), pv.interpolate(table, theta, rate))


def test_learned_transitions_are_the_models_steps(true_model):
    thetas, rates, torques = np.array([0.0, 1.0, -2.5]), np.array([-3.0, 0.5]), np.array([-2.0, 1.0])
    next_theta, next_rate = pv.learned_transitions(true_model, thetas, rates, torques, chunk=5)
    for i, j, k in product(range(3), range(2), range(2)):
        x = state_from_v1_observation([np.cos(thetas[i]), np.sin(thetas[i]), rates[j]])
        x_next, _ = true_model(x, np.array([torques[k]]))
        from fvin_mpc.envs.pendulum_v1 import v1_observation_from_state

        observation = v1_observation_from_state(x_next)
        assert next_theta[i, j, k] == pytest.approx(np.arctan2(observation[1], observation[0]), abs=1e-12)
        assert next_rate[i, j, k] == pytest.approx(observation[2], abs=1e-12)
    # The true pendulum from hanging at rest under no torque stays there (θ = ±π in Pendulum-v1's angle).
    assert abs(abs(pv.learned_transitions(true_model, np.array([-np.pi]), np.array([0.0]), np.array([0.0]))[0])
               - np.pi).max() < 1e-9


def test_terminal_cost_hook_reproduces_the_terminal_speed_weight(true_model):
    """A terminal cost W|ω_N|² through the hook gives the same plan as terminal_omega_weight = W; the
    default (no hook) is the problem as before; a wrong shape or solver is refused."""
    settings = MPCSettings(horizon=15, compile="none", ipopt=IpoptOptions(tol=1e-9))
    x = ca.MX.sym("x", 7)
    speed = ca.Function("speed", [x], [3.0 * ca.sumsqr(x[4:])])
    with_weight = MPC(true_model, replace(settings, terminal_omega_weight=3.0), UPRIGHT, [-2.0], [2.0])
    with_hook = MPC(
        true_model, replace(settings, terminal_omega_weight=0.0), UPRIGHT, [-2.0], [2.0], terminal_cost=speed
    )
    without = MPC(true_model, replace(settings, terminal_omega_weight=0.0), UPRIGHT, [-2.0], [2.0])
    assert without.terminal_cost is None
    for theta, theta_dot in [(np.pi - 0.3, 0.5), (np.pi + 0.2, -1.0)]:  # near upright: the terminal ω matters
        state = np.r_[hinge(theta, theta_dot)]
        results = []
        for controller in (with_weight, with_hook, without):
            controller.reset()
            results.append(controller(state))
        assert all(info["success"] for _, info in results)
        np.testing.assert_allclose(results[1][1]["controls"], results[0][1]["controls"], atol=1e-5)
        assert results[1][1]["cost"] == pytest.approx(results[0][1]["cost"], rel=1e-6)
        assert np.abs(results[2][1]["controls"] - results[0][1]["controls"]).max() > 1e-3
    with pytest.raises(ValueError):
        MPC(true_model, settings, UPRIGHT, [-2.0], [2.0], terminal_cost=ca.Function("bad", [x], [x]))
    with pytest.raises(ValueError):
        MPC(
            true_model, settings.updated(solver="fatrop", ipopt={"hessian": "exact"}), UPRIGHT, [-2.0], [2.0],
            terminal_cost=speed
        )


def test_cold_start_score_ranks_the_cold_plans(true_model):
    """The default ranks the cold starts by the NLP's cost; a score hook picks its own favourite (here the
    plan whose first torque is lowest), and the warm calls are untouched."""
    from fvin_mpc.control.mpc import COLD_STARTS

    settings = replace(MPCSettings(horizon=15), compile="none", cold_starts=COLD_STARTS)
    default = MPC(true_model, settings, UPRIGHT, [-2.0], [2.0])
    ranked = MPC(true_model, settings, UPRIGHT, [-2.0], [2.0], cold_start_score=lambda states, controls: controls[0, 0])
    state = np.r_[hinge(0.3, 0.2)]  # near hanging: swinging left or right first are both plans
    _, info = default(state)
    costs = {k: v for k, v in info["cold_costs"].items() if np.isfinite(v)}
    assert info["cold_start"] == min(costs, key=costs.get)
    _, ranked_info = ranked(state)
    assert ranked_info["cold_costs"] == pytest.approx(info["cold_costs"], nan_ok=True)
    first_torques = {}
    for start in costs:
        solo = MPC(true_model, replace(settings, cold_starts=(start,)), UPRIGHT, [-2.0], [2.0])
        first_torques[start] = solo(state)[1]["controls"][0, 0]
    assert ranked_info["controls"][0, 0] == pytest.approx(min(first_torques.values()), abs=1e-6)
    assert "cold_start" not in ranked(state)[1]  # a warm call


def test_plan_score_is_the_stage_costs_plus_the_value():
    thetas, rates = pv.grid_axes(32, 17)
    table = 10.0 + np.cos(thetas)[:, None] + 0.0 * rates[None, :]
    theta = np.array([2.0, 2.2, 2.5])
    rate = np.array([1.0, 2.0, 3.0])
    states = state_from_v1_observation(np.stack([np.cos(theta), np.sin(theta), rate], axis=1))
    controls = np.array([[0.5], [-1.0]])
    expected = float(np.sum(exact.v1_cost(theta[:2], rate[:2], controls[:, 0]))) + pv.interpolate(
        table, theta[2], rate[2]
    )
    assert pv.plan_score(table)(states, controls) == pytest.approx(expected, rel=1e-12)
    assert pv.plan_score(table, "mpc")(states, controls) < pv.plan_score(table)(states, controls)  # 4 sin²(θ/2) < θ²


def test_reused_reference_is_the_search_or_the_polished_mpc_episode():
    """reuse_references: reference = max(the earlier search without its MPC, this MPC's polished episode); a
    different grid or a missing seed is refused; the MPC never beats the reference."""
    theta0, theta_dot0 = 0.8, -0.3
    controls = np.zeros(exact.EPISODE_STEPS)
    guess_return, states = exact.replay(theta0, theta_dot0, controls)
    record = {"seed": 7, "theta0": theta0, "theta_dot0": theta_dot0, "return": guess_return,
              "controls": controls.tolist(), "states": states.tolist()}
    families = {"greedy": -200.0, "noisy-a": -150.0, "noisy-b": -150.0, "heuristic": -300.0, "mpc": -400.0}
    stored = {"seed": 7, "theta0": theta0, "theta_dot0": theta_dot0, "search_return": -1e6,
              "reference_source": "dp256x129 (polished)", "reference_grids": {"dp256x129": {}},
              "reference_families": families}
    previous = {"config": {"reference_grids": [[256, 129], [512, 257]]}, "episodes": [stored]}
    records = [dict(record)]
    v1.reuse_references(records, previous, ((256, 129), (512, 257)), progress=False)
    polished = records[0]["reference_families"]["mpc"]
    assert polished > guess_return + 1.0  # the zero-torque episode polished (to a local optimum)
    assert records[0]["reference_return"] == polished >= records[0]["return"]
    assert records[0]["reference_source"].startswith("mpc")
    assert not records[0]["reference_converged"]  # the noisy halves (-150) are not at the reference
    records = [dict(record)]
    v1.reuse_references(records, {**previous, "episodes": [{**stored, "search_return": 0.0}]},
                        ((256, 129), (512, 257)), progress=False)
    assert records[0]["reference_return"] == 0.0 and records[0]["reference_source"] == "dp256x129 (polished)"
    with pytest.raises(ValueError):
        v1.reuse_references([dict(record)], previous, ((256, 129), (1024, 513)), progress=False)
    with pytest.raises(ValueError):
        v1.reuse_references([{**record, "seed": 8}], previous, ((256, 129), (512, 257)), progress=False)
