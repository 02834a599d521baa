"""The Pendulum-v1 study's exact map (benchmarks.pendulum_v1_exact), its MPC settings and the episode NLP."""

import gymnasium
import numpy as np
import pytest

from benchmarks import pendulum_v1_exact as exact
from benchmarks import pendulum_v1_mpc as v1
from benchmarks.pendulum_v1_reference import best_of, polish
from fvin_mpc.control.scene import DEFAULT_TERMINAL_ENERGY_WEIGHT


def test_v1_step_replicates_gymnasium_exactly():
    env = gymnasium.make("Pendulum-v1")
    rng = np.random.default_rng(0)
    for seed in range(3):
        env.reset(seed=seed)
        clipped = 0
        for _ in range(200):  # pumping (torque along θ̇, beyond the bound) reaches the speed clip
            theta, theta_dot = (float(x) for x in env.unwrapped.state)
            u = float(np.float32(np.copysign(2.5, theta_dot) + rng.uniform(-0.3, 0.3)))
            _, reward, *_ = env.step(np.array([u], dtype=np.float32))
            theta, theta_dot, expected = exact.v1_step(theta, theta_dot, u)
            # One step from the same state; gymnasium mixes in the float32 action, hence 1e-6.
            assert expected == pytest.approx(reward, rel=1e-6, abs=1e-9)
            np.testing.assert_allclose(env.unwrapped.state, [theta, theta_dot], rtol=1e-6, atol=1e-9)
            clipped += abs(theta_dot) == exact.MAX_SPEED
        assert clipped > 0


def test_benchmark_settings_cost_matches_the_reward_near_upright():
    """4 sin²(a/2) ≈ a² and the ω, u weights are Pendulum-v1's; the speed bound is its clip."""
    settings = v1.benchmark_settings()
    for angle in (0.01, 0.1, 0.3):
        assert settings.orientation_weight * np.sin(angle / 2) ** 2 == pytest.approx(angle**2, rel=0.01)
    assert (settings.omega_weight, settings.control_weight) == (0.1, 0.001)
    assert settings.omega_bound_fraction / exact.DT == pytest.approx(exact.MAX_SPEED)
    # The terminal energy weight is the scenes' default unless given: one place to tune it.
    assert settings.terminal_energy_weight == DEFAULT_TERMINAL_ENERGY_WEIGHT > 0
    assert v1.benchmark_settings(terminal_energy_weight=0.0).terminal_energy_weight == 0.0


def test_episode_optimizer_beats_its_guess_and_its_return_is_replayable():
    optimizer = exact.EpisodeOptimizer(steps=60)
    theta0, theta_dot0 = 0.8, -0.3  # θ = 0 upright in Pendulum-v1
    guess = np.zeros(60)
    guess_return, _ = exact.replay(theta0, theta_dot0, guess)
    total, controls, status, defect = optimizer.solve(theta0, theta_dot0, guess)
    assert status in ("Solve_Succeeded", "Solved_To_Acceptable_Level") and defect < 1e-8
    assert total > guess_return + 10.0
    # Over 3 s the open-loop replay stays close to the optimized trajectory; its return is the NLP's value.
    assert total == pytest.approx(exact.replay(theta0, theta_dot0, controls)[0], rel=1e-4)
    # The reference's polish (pendulum_v1_reference) keeps the better of the guess and its optimum.
    value, source = best_of(polish(theta0, theta_dot0, {"zero": guess}, [optimizer]))
    assert value == pytest.approx(total) and source == "zero (polished)"
    # Optimality check against simple perturbations of the optimum (a local optimum of a smooth problem).
    rng = np.random.default_rng(1)
    for _ in range(5):
        perturbed = np.clip(controls + 0.05 * rng.normal(size=60), -2, 2)
        assert exact.replay(theta0, theta_dot0, perturbed)[0] <= total + 1e-6
