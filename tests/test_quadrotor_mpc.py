"""The real-time MPC on the free body (``fvin_mpc.control.rti`` with ``(x, q, v, ω)`` states,
``fvin_mpc.control.flight``): the R³ × S³ chart, recovery to hover on the closed-form model with
MuJoCo as the plant, the flip from exactly upside down, the safe fallback, the offset-free estimate
against a known mass error (oracle) and the figure-eight reference against its own derivatives.
Behaviour only: no timings are asserted."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from fvin_mpc.control import flight
from fvin_mpc.control import model_export as export
from fvin_mpc.control.closed_loop import run_episode
from fvin_mpc.core.quadrotor import from_mujoco
from fvin_mpc.core.space import FREE_BODY, PIVOTED, R3S3, S3
from fvin_mpc.envs.quadrotor_env import QuadrotorEnv

#: The task's settings (its compiled library is shared with the commands through the on-disk cache).
#: Cold budgets this generous let the iteration caps, not the wall clock, decide: deterministic runs.
DETERMINISTIC = {"rti": {"cold_budget_s": 60.0}}


@pytest.fixture(scope="module")
def craft():
    env = QuadrotorEnv()
    return env, flight.quadrotor_model(env, true_model=True)


def tilted(env, angle=1.0, offset=(0.3, -0.2, 0.1), omega=(2.0, -1.0, 0.5)):
    """Reset options: tilted by ``angle`` about an oblique axis, off the hover point, turning."""
    axis = np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)
    q = np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])
    return {
        "qpos": np.concatenate([env.hover_point + np.asarray(offset), q]),
        "qvel": np.concatenate([np.zeros(3), omega]),
    }


def test_layouts():
    assert S3.layout is PIVOTED and R3S3.layout is FREE_BODY
    assert (PIVOTED.state_dim, PIVOTED.tangent_dim) == (7, 6)
    assert (FREE_BODY.state_dim, FREE_BODY.tangent_dim) == (13, 12)


def test_recovers_to_hover_from_a_tilted_start(craft):
    """Closed-form model, MuJoCo plant, fixed 10 ms latency: tilted 1 rad, 0.4 m off, turning."""
    env, model = craft
    controller = flight.quadrotor_mpc(env, model, flight.quadrotor_mpc_settings(**DETERMINISTIC))
    episode, _ = run_episode(env, controller, 3.0, tilted(env), latency=0.01)
    metrics = flight.flight_metrics(episode, flight.hover_reference(env))
    assert metrics["recovered"], metrics
    assert metrics["final_position_m"] < 0.01 and metrics["final_angle_rad"] < 0.01
    assert metrics["controller_failures"] == 0 and metrics["deadline_misses"] == 0


def test_flips_from_exactly_upside_down_at_rest(craft):
    """Upside down at rest is a stationary point of the projector residual's Gauss–Newton model; the
    rotation-vector residual turns the craft over (differential thrust on the first call) and recovers."""
    env, model = craft
    options, seed = flight.recovery_starts(env.hover_point, count=1)[0]
    np.testing.assert_allclose(options["state"][3:], [0.0, 1.0, 0.0, 0.0, 0, 0, 0, 0, 0, 0])
    controller = flight.quadrotor_mpc(env, model, flight.quadrotor_mpc_settings(**DETERMINISTIC))
    x0, _ = env.reset(seed=seed, options=options)
    u, info = controller(x0)
    assert info["success"]
    assert np.ptp(u) > 0.1  # a torque, not a symmetric thrust
    episode, _ = run_episode(env, controller, 4.0, options, seed=seed, latency=0.01)
    assert flight.flight_metrics(episode, flight.hover_reference(env))["recovered"]


def test_a_non_finite_disturbance_estimate_never_reaches_the_thrusts(craft):
    env, model = craft
    controller = flight.quadrotor_mpc(env, model, flight.quadrotor_mpc_settings(**DETERMINISTIC))
    x0, _ = env.reset(options=tilted(env))
    controller(x0)
    previous = controller.plan.controls.copy()
    controller.set_disturbance(np.nan)
    controller.prepare()
    u, _ = controller(model(x0, previous[0])[0])
    assert np.all(np.isfinite(u)) and np.all(env.torque_low <= u) and np.all(u <= env.torque_high)


def test_disturbance_estimate_absorbs_a_mass_error(craft):
    """Oracle: the model's craft is 10 % heavier than the plant. Hovering needs ``m g/4`` per rotor in
    the plant and the model explains it with ``u + d``: the estimate converges to ``d = (m' − m) g/4``
    and the craft hovers on the point; without the estimator it settles off it (below: the model's
    hover thrust lifts the lighter craft until the position cost balances it)."""
    env, _ = craft
    true = from_mujoco(env.model, env.body_name)
    heavy = replace(true, mass=1.1 * true.mass)
    model = export.from_quadrotor(heavy, env.dt, 2, name="heavy_quadrotor")
    start = tilted(env, angle=0.3, offset=(0.1, 0.0, 0.0), omega=(0.0, 0.0, 0.0))
    controller = flight.quadrotor_mpc(env, model, flight.quadrotor_mpc_settings(**DETERMINISTIC))
    episode, _ = run_episode(env, controller, 4.0, start, latency=0.01)
    expected = (heavy.mass - true.mass) * true.gravity / 4
    np.testing.assert_allclose(episode.controller_info[-1]["disturbance"], expected, rtol=0.02, atol=1e-3)
    offset_free = flight.flight_metrics(episode, flight.hover_reference(env))["final_position_m"]
    plain, _ = run_episode(
        env,
        flight.quadrotor_mpc(env, model, flight.quadrotor_mpc_settings(**DETERMINISTIC, disturbance_gain=0.0)),
        4.0,
        start,
        latency=0.01,
    )
    assert offset_free < 2e-3 < flight.flight_metrics(plain, flight.hover_reference(env))["final_position_m"]


def test_figure_eight_reference_is_consistent():
    """Velocity and acceleration are the position's derivatives; the reference attitude points the
    body z axis along ``p̈ + g e_z`` with no yaw, the control scale is its length over ``g``; ``ω`` is the
    attitude's body rate (``q̇ = ½ q ⊗ (0, ω)``)."""
    reference = flight.FigureEight(center=(0.0, 0.0, 1.0), amplitude=0.5, period=3.0, ramp_s=1.0)
    t = np.linspace(0.0, 6.0, 241)
    dt = 1e-5
    position, velocity, acceleration = reference.trajectory(t)
    later = t[1:]  # central differences need t − dt inside the path (it starts at t = 0)
    np.testing.assert_allclose(velocity[1:], (reference.trajectory(later + dt)[0] - reference.trajectory(later - dt)[0])
                               / (2 * dt), atol=1e-6)
    np.testing.assert_allclose(
        acceleration[1:],
        (reference.trajectory(later + dt)[1] - reference.trajectory(later - dt)[1]) / (2 * dt),
        atol=1e-5,
    )
    states, scale = reference(t)
    np.testing.assert_allclose(states[:, :3], position)
    np.testing.assert_allclose(states[:, 7:10], velocity)
    q = states[:, 3:7]
    w, v = q[:, 0], q[:, 1:]
    z_axis = np.stack([2 * (v[:, 0] * v[:, 2] + w * v[:, 1]), 2 * (v[:, 1] * v[:, 2] - w * v[:, 0]),
                       w**2 - v[:, 0] ** 2 - v[:, 1] ** 2 + v[:, 2] ** 2], axis=1)
    thrust = acceleration + [0.0, 0.0, 9.81]
    np.testing.assert_allclose(z_axis, thrust / np.linalg.norm(thrust, axis=1, keepdims=True), atol=1e-12)
    np.testing.assert_allclose(scale, np.linalg.norm(thrust, axis=1) / 9.81, atol=1e-12)
    assert np.all(np.abs(v[:, 2]) < 1e-12)  # no yaw component
    inner = (t > 0.01) & (t < 5.99) & (np.abs(t - reference.ramp_s) > 1e-3)  # the jerk has a kink at the ramp's end
    q_next, q_prev = reference(t + dt)[0][:, 3:7], reference(t - dt)[0][:, 3:7]
    q_dot = (q_next - q_prev) / (2 * dt)
    omega = states[:, 10:]
    half = 0.5 * np.stack([-(v * omega).sum(1), w * omega[:, 0] + v[:, 1] * omega[:, 2] - v[:, 2] * omega[:, 1],
                           w * omega[:, 1] + v[:, 2] * omega[:, 0] - v[:, 0] * omega[:, 2],
                           w * omega[:, 2] + v[:, 0] * omega[:, 1] - v[:, 1] * omega[:, 0]], axis=1)
    np.testing.assert_allclose(half[inner], q_dot[inner], atol=1e-5)
    # it starts at the centre at rest (the ramp) and reaches 1.5 m/s on the loop
    np.testing.assert_allclose(states[0, :3], [0.0, 0.0, 1.0], atol=1e-15)
    np.testing.assert_allclose(states[0, 7:10], 0.0, atol=1e-15)
    assert np.linalg.norm(velocity, axis=1).max() > 1.0


def test_a_skipped_observation_does_not_feed_the_disturbance_estimate(craft):
    """After a deadline miss the next measurement is two periods after the last prediction: comparing
    them would read the missed period as a disturbance. ``set_time`` with a jump drops the prediction."""
    env, model = craft
    controller = flight.quadrotor_mpc(env, model, flight.quadrotor_mpc_settings(**DETERMINISTIC))
    x0, _ = env.reset(options={"hover": True})
    u, _ = controller(x0)
    controller.prepare()
    x2 = model(model(x0, u)[0], u)[0]  # two periods later
    x2[7:10] += 0.05  # and moving: one-step "prediction error" if it were compared
    controller.set_time(2 * env.dt)
    _, info = controller(x2)
    np.testing.assert_array_equal(info["disturbance"], 0.0)
    controller.set_time(3 * env.dt)  # one step on: the estimate runs again
    _, info = controller(model(x2, u)[0] + np.r_[np.zeros(7), 0.01, 0.0, 0.0, np.zeros(3)])
    assert np.any(info["disturbance"] != 0.0)


def test_fly_command(tmp_path, capsys):
    """``python -m fvin_mpc.fly``: --help, a refused input, one recovery end to end (closed form, fixed delay)."""
    import json

    from fvin_mpc import fly
    from fvin_mpc._cli import run_command

    with pytest.raises(SystemExit) as exit_info:
        fly.main(["--help"])
    assert exit_info.value.code == 0 and "figure-eight" in capsys.readouterr().out
    assert run_command(fly.main, ["--episodes", "0"]) == 2
    path = tmp_path / "recovery.json"
    assert fly.main(["--task", "recovery", "--model", "closed-form", "--episodes", "1", "--latency", "0.01",
                     "--json", str(path), "--quiet"]) == 0
    result = json.loads(path.read_text())
    assert result["summary"]["recovered"] == "1/1" and result["episodes"][0]["initial_angle_rad"] > 3.1
