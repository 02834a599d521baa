"""The Pendulum-v1 reference: DP on the exact map, its rollouts and polish, against brute force and the MPC."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from benchmarks import pendulum_v1_exact as exact
from benchmarks import pendulum_v1_mpc as v1
from benchmarks import pendulum_v1_reference as ref


def brute_force(theta0: float, rate0: float, levels: np.ndarray, steps: int) -> tuple[float, np.ndarray]:
    """Best return over every sequence of ``levels`` torques (the exact map, vectorized)."""
    sequences = np.array(list(itertools.product(levels, repeat=steps)))
    theta, rate = np.full(len(sequences), theta0), np.full(len(sequences), rate0)
    returns = np.zeros(len(sequences))
    for k in range(steps):
        returns -= exact.v1_cost(theta, rate, sequences[:, k])
        theta, rate = exact.v1_map(theta, rate, sequences[:, k])
    best = int(np.argmax(returns))
    return float(returns[best]), sequences[best]


def test_vectorized_map_is_the_scalar_step():
    rng = np.random.default_rng(0)
    theta, rate, u = rng.uniform(-4, 4, 50), rng.uniform(-9, 9, 50), rng.uniform(-2, 2, 50)
    new_theta, new_rate = exact.v1_map(theta, rate, u)
    cost = exact.v1_cost(theta, rate, u)
    for i in range(50):
        assert (new_theta[i], new_rate[i], -cost[i]) == pytest.approx(exact.v1_step(theta[i], rate[i], u[i]), abs=1e-14)
    assert np.abs(new_rate).max() == exact.MAX_SPEED  # the clip is exercised


def test_two_step_values_are_the_continuous_torque_minimum_within_the_interpolation_bound():
    """V_1 is the stage cost exactly; V_2 = c + min_u [0.001u² + c(f(x, u))] with c interpolated bilinearly:
    against the minimum over 4001 torques of the exact c, within the interpolation bound
    (Δθ² max|c_θθ| + Δθ̇² max|c_θ̇θ̇|)/8 = (2Δθ² + 0.2Δθ̇²)/8 (+ the breakpoint spacing term) where c is smooth."""
    n_theta, n_rate = 64, 33
    tables = ref.solve_value_tables(n_theta, n_rate, steps=2)
    theta = -np.pi + 2 * np.pi * np.arange(n_theta) / n_theta
    rate = np.linspace(-8, 8, n_rate)
    grid_theta, grid_rate = np.meshgrid(theta, rate, indexing="ij")
    np.testing.assert_allclose(tables.values[1], exact.v1_cost(grid_theta, grid_rate, 0.0), rtol=1e-6)
    torques = np.linspace(-2, 2, 4001)
    next_theta, next_rate = exact.v1_map(grid_theta[..., None], grid_rate[..., None], torques)
    two_step = exact.v1_cost(grid_theta, grid_rate, 0.0) + (
        0.001 * torques**2 + exact.v1_cost(next_theta, next_rate, 0.0)).min(axis=-1)
    d_theta, d_rate = 2 * np.pi / n_theta, 16 / (n_rate - 1)
    breakpoint_term = 0.001 * (d_rate / exact.RATE_GAIN_TORQUE / 2) ** 2
    bound = (2 * d_theta**2 + 0.2 * d_rate**2) / 8 + breakpoint_term + 1e-4  # + float32 storage
    # c has a kink at θ = ±π (angle_normalize wraps): away from it the bound holds.
    smooth = np.abs(np.abs(next_theta.mean(axis=-1)) - np.pi) > 3 * d_theta
    error = tables.values[2] - two_step
    assert np.abs(error[smooth]).max() <= bound
    assert smooth.mean() > 0.8
    # The interpolant of a convex c over-estimates it: the DP's value is never below the exact minimum by more
    # than rounding.
    assert error[smooth].min() > -1e-4


@pytest.mark.parametrize("theta0, rate0", [(2.0, 0.5), (-2.9, 0.1), (0.5, -1.0)])
def test_reference_is_the_brute_force_optimum_on_a_short_horizon(theta0, rate0):
    """4 steps: every sequence of 21 torque levels, the best one polished, is the optimum; the DP search
    (its own rollout polished) must find it, and cannot beat the brute force's grid by less than nothing."""
    steps = 4
    best_grid, best_sequence = brute_force(theta0, rate0, np.linspace(-2, 2, 21), steps)
    optimizers = ref.polishers(steps)
    optimum = max(o.solve(theta0, rate0, best_sequence)[0] for o in optimizers)
    assert optimum >= best_grid - 1e-9
    tables = ref.solve_value_tables(128, 129, steps=steps)
    controls, returns = ref.greedy_rollouts(tables, [theta0], [rate0])
    reference = ref.reference_for_seed(theta0, rate0, {"dp": controls[0]}, optimizers)
    assert reference["return"] == pytest.approx(optimum, abs=1e-6)
    assert returns[0] <= optimum + 1e-9  # the rollout is a feasible trajectory of the exact map


def test_polish_keeps_the_clip_and_refines_a_bang_bang_guess_in_place():
    """A guess that hits the speed clip: its polished trajectories satisfy the clipped map and are no worse
    than the guess (the local polish does not jump to a worse local optimum)."""
    steps = 60
    theta0, rate0 = np.pi - 0.3, 6.0  # near hanging, fast: full torque along θ̇ reaches the clip
    guess = np.full(steps, 2.0)
    guess_return, states = exact.replay(theta0, rate0, guess)
    assert np.abs(states[:, 1]).max() == exact.MAX_SPEED
    results = ref.polish(theta0, rate0, {"guess": guess}, ref.polishers(steps))
    assert results["guess"]["guess"] == pytest.approx(guess_return)
    assert results["guess"]["polished"] >= guess_return - 1e-9


def test_mpc_never_beats_the_search():
    """On seeds where the old reference (three first guesses) lost to the MPC by ~17, the DP search — without
    the MPC's own episode as a first guess — is not beaten by the MPC beyond rounding."""
    config = v1.BenchmarkConfig(episodes=2, seed=11, reference_grids=((128, 65), (256, 129)))
    records = v1.run_benchmark(config, workers=1, progress=False)
    for record in records:
        assert record["return"] <= record["search_return"] + 1e-3
        assert record["reference_return"] >= record["search_return"]
        assert record["reference_return"] >= record["return"] - 1e-3


def test_rti_benchmark_takes_the_pendulum_scenes_dynamics_unless_told():
    """The benchmark is the ``pendulum`` scene's task: its RTI uses the scene's dynamics constraint
    (``rti.dynamics``) by default, and an explicit choice wins; either way the label says which."""
    from fvin_mpc.control.presets import PRESETS

    scene_choice = PRESETS["pendulum"].fields_for("rti")["rti"]["dynamics"]
    default = v1.BenchmarkConfig(episodes=1, reference=False, solver="rti")
    assert v1.rti_dynamics(default) == scene_choice
    assert v1.build_mpc(default).settings.rti.dynamics == scene_choice
    other = "unrolled" if scene_choice == "implicit" else "implicit"
    assert v1.build_mpc(v1.BenchmarkConfig(episodes=1, reference=False, solver="rti",
                                           rti_dynamics=other)).settings.rti.dynamics == other
