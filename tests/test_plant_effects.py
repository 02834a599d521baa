"""The declared plant effects a model of the MJCF does not know (envs.scenes.ScenePhysics): gyro noise,
encoder quantization, actuation delay, a scaled mass, a knock while holding — each against an oracle."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from fvin_mpc.core.rigid_body import from_mujoco
from fvin_mpc.envs import SCENES, RigidBodyEnv
from fvin_mpc.envs.quadrotor_env import QuadrotorEnv
from fvin_mpc.envs.scenes import FREE_BODY_SCENES, IMPULSE_HOLD_S, SceneError

PENDULUM = SCENES["pendulum"].physics


def pendulum(**effects) -> RigidBodyEnv:
    return RigidBodyEnv("pendulum", physics=replace(PENDULUM, **effects))


def hinge_angle(q: np.ndarray) -> float:
    """The pendulum's angle about +y from its quaternion (w, 0, sin θ/2, 0)."""
    return 2.0 * math.atan2(q[2], q[0])


def test_actuation_delay_is_the_nominal_plant_fed_the_torques_one_period_late():
    torques = [1.0, -0.5, 2.0, 0.3]
    delayed, nominal = pendulum(actuation_delay_s=0.05), RigidBodyEnv("pendulum")
    delayed.reset(options={"qpos": [0.3]})
    nominal.reset(options={"qpos": [0.3]})
    late = [delayed.step(np.array([u]))[0] for u in torques]
    shifted = [nominal.step(np.array([u]))[0] for u in [0.0] + torques[:-1]]
    np.testing.assert_array_equal(late, shifted)
    # A reset empties the line: the first period again feels no torque.
    delayed.reset(options={"qpos": [0.3]})
    nominal.reset(options={"qpos": [0.3]})
    np.testing.assert_array_equal(delayed.step(np.array([2.0]))[0], nominal.step(np.array([0.0]))[0])


def test_actuation_delay_carries_across_partial_periods():
    """A latency-aware loop steps part of a period at a time; the delay counts MuJoCo steps, not calls."""
    whole, parts = pendulum(actuation_delay_s=0.05), pendulum(actuation_delay_s=0.05)
    for env in (whole, parts):
        env.reset(options={"qpos": [0.3]})
    whole.step(np.array([1.0]))
    whole.step(np.array([-1.0]))
    parts.step(np.array([1.0]), substeps=4)
    parts.step(np.array([1.0]), substeps=6)
    parts.step(np.array([-1.0]), substeps=10)
    np.testing.assert_array_equal(whole.state(), parts.state())


@pytest.mark.parametrize("scale", [0.7, 1.3])
def test_mass_scale_is_a_denser_rod(scale):
    """Mass and inertia × s: θ̈ = −15 sin θ + 3τ/s (gravity torque and inertia scale together)."""
    env = pendulum(mass_scale=scale)
    theta0, torque, steps = 1.0, 1.5, 20
    env.reset(options={"qpos": [theta0]})
    angles = []
    for _ in range(steps):
        env.step(np.array([torque]))
        angles.append(env.data.qpos[0])
    times = 0.05 * np.arange(1, steps + 1)
    ode = solve_ivp(lambda t, x: [x[1], -15.0 * math.sin(x[0]) + 3.0 * torque / scale], (0.0, times[-1]),
                    [theta0, 0.0], method="DOP853", rtol=1e-12, atol=1e-12, t_eval=times)
    np.testing.assert_allclose(angles, ode.y[0], rtol=0, atol=1e-7)
    # The plant changed, not the file: a body read off a fresh nominal env has the MJCF's mass.
    assert from_mujoco(env.model, "pendulum").mass_gravity == pytest.approx(10.0 * scale)
    nominal = RigidBodyEnv("pendulum")
    assert from_mujoco(nominal.model, "pendulum").mass_gravity == pytest.approx(10.0)


def test_encoder_rounds_the_observed_angle_only():
    step = 2.0 * math.pi / 4096
    env, exact = pendulum(encoder_bits=12), RigidBodyEnv("pendulum")
    for theta in (0.3001, -2.71828, 1e-5, math.pi - 1e-4):
        observation, info = env.reset(options={"qpos": [theta], "qvel": [0.7]})
        truth, truth_info = exact.reset(options={"qpos": [theta], "qvel": [0.7]})
        observed = hinge_angle(observation[:4])
        assert abs(math.remainder(observed - theta, 2 * math.pi)) <= 0.5 * step + 1e-12
        assert abs(math.remainder(observed / step - round(observed / step), 1.0)) < 1e-6  # on the grid
        np.testing.assert_array_equal(observation[4:], truth[4:])  # the rate is not the encoder's
        assert info == truth_info  # reward and info use the true state
    with pytest.raises(SceneError, match="hinge"):
        RigidBodyEnv("spherical_pendulum", physics=replace(SCENES["spherical_pendulum"].physics, encoder_bits=12))


def test_gyro_noise_is_on_the_rate_only_with_the_declared_spread():
    sigma = 0.1
    env, exact = pendulum(gyro_noise_std=sigma), RigidBodyEnv("pendulum")
    errors = []
    for seed in range(400):
        observation, _ = env.reset(seed=seed, options={"qpos": [1.0], "qvel": [0.5]})
        truth, _ = exact.reset(options={"qpos": [1.0], "qvel": [0.5]})
        np.testing.assert_array_equal(observation[:4], truth[:4])
        errors.append(observation[4:] - truth[4:])
    errors = np.array(errors).ravel()
    # 1,200 draws: the sample deviation is within 10 % of σ far beyond 3 standard errors (2 %).
    assert np.std(errors) == pytest.approx(sigma, rel=0.1)
    assert abs(np.mean(errors)) < 4 * sigma / math.sqrt(errors.size)


def test_knock_comes_once_after_holding_and_changes_the_rate_by_its_size():
    env = pendulum(impulse_delta_omega=2.0)
    env.reset(seed=3, options={"qpos": [math.pi]})  # upright at rest: held from the first period on
    rates, times = [], []
    for _ in range(60):
        observation, *_ = env.step(np.zeros(1))
        rates.append(observation[5])
        times.append(env.data.time)
    jumps = np.flatnonzero(np.abs(np.diff(rates)) > 1.0)
    assert jumps.size == 1 and env.knocked
    # Held from t = 0.05 s (the first period's end); the knock lands at the first period start ≥ 1 s later.
    assert times[jumps[0]] == pytest.approx(0.05 + IMPULSE_HOLD_S)
    # Over one period the upright pendulum's rate changes by |θ̈|·h ≤ 15·h·|sin θ| ≈ 0 near the top, so the
    # jump is the knock's 2 rad/s.
    assert abs(rates[jumps[0] + 1] - rates[jumps[0]]) == pytest.approx(2.0, abs=0.05)
    # A body that never holds is never knocked.
    env.reset(seed=3)
    for _ in range(60):
        env.step(np.zeros(1))
    assert not env.knocked


def test_effects_are_validated_and_refused_where_not_simulated():
    for name, value in [("gyro_noise_std", -0.1), ("actuation_delay_s", float("nan")), ("mass_scale", 0.0),
                        ("impulse_delta_omega", -1.0), ("encoder_bits", 0), ("encoder_bits", 12.0)]:
        with pytest.raises(ValueError, match=name):
            replace(PENDULUM, **{name: value})
    quadrotor = FREE_BODY_SCENES["quadrotor"]
    with pytest.raises(SceneError, match="gyro_noise_std"):
        QuadrotorEnv(physics=replace(quadrotor.physics, gyro_noise_std=0.1))


def test_a_gyro_on_the_hinge_axis_leaves_the_other_rates_exact():
    env, exact = pendulum(gyro_noise_std=0.1, gyro_axes="joint"), RigidBodyEnv("pendulum")
    observation, _ = env.reset(seed=5, options={"qpos": [1.0], "qvel": [0.5]})
    truth, _ = exact.reset(options={"qpos": [1.0], "qvel": [0.5]})
    assert observation[5] != truth[5]  # the hinge is about +y
    np.testing.assert_array_equal(observation[[0, 1, 2, 3, 4, 6]], truth[[0, 1, 2, 3, 4, 6]])
    with pytest.raises(ValueError, match="gyro_axes"):
        replace(PENDULUM, gyro_axes="yaw")
