"""The ``quadrotor`` scene and :class:`~fvin_mpc.envs.QuadrotorEnv`: observation conventions read off
MuJoCo (not assumed), the declared physics, seeded resets, partial periods."""

from __future__ import annotations

from dataclasses import replace

import gymnasium
import mujoco
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from fvin_mpc.core import s3
from fvin_mpc.envs import FREE_BODY_SCENES, QuadrotorEnv, ScenePhysics
from fvin_mpc.envs.scenes import get_scene, resolve_scene

SCENE = FREE_BODY_SCENES["quadrotor"]
FREE_FLIGHT = replace(SCENE.physics, gravity=False)


def rotation(q: np.ndarray) -> np.ndarray:
    return np.array(s3.rotation_matrix(tuple(q)), dtype=float)


def test_registered_and_passes_the_gymnasium_checker():
    env = gymnasium.make("fvin_mpc/Quadrotor-v0")
    assert env.spec.max_episode_steps == 250
    check_env(env.unwrapped, skip_render_check=True)
    assert get_scene("quadrotor") is SCENE and resolve_scene(str(SCENE.xml_path)) is SCENE


def test_declared_physics_and_thrust_bounds():
    env = QuadrotorEnv()
    assert env.physics == ScenePhysics(gravity=True, joint_damping=False, dry_friction=False, actuator_limits=True,
                                       contact=False)
    assert env.dt == pytest.approx(0.02) and env.frame_skip == 10
    weight = 0.5 * 9.81
    np.testing.assert_allclose(env.hover_thrust, np.full(4, weight / 4))
    np.testing.assert_array_equal(env.torque_low, np.zeros(4))
    assert env.torque_high.sum() / weight == pytest.approx(2.04, abs=0.01)  # about 2 g
    assert env.model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT


def test_the_velocities_are_world_linear_and_body_angular():
    """qvel[:3] is the world-frame velocity and qvel[3:] the body-frame angular velocity: compared with
    mj_objectVelocity in both frames and with difference quotients of the pose over a 1 µs step."""
    env = QuadrotorEnv(physics=FREE_FLIGHT)
    rng = np.random.default_rng(3)
    for _ in range(5):
        q = rng.normal(size=4)
        qpos, qvel = np.concatenate([rng.normal(size=3), q / np.linalg.norm(q)]), rng.normal(scale=4.0, size=6)
        env.set_state(qpos, qvel)
        state = env.state()
        world, local = np.zeros(6), np.zeros(6)
        mujoco.mj_objectVelocity(env.model, env.data, mujoco.mjtObj.mjOBJ_BODY, 1, world, 0)
        mujoco.mj_objectVelocity(env.model, env.data, mujoco.mjtObj.mjOBJ_BODY, 1, local, 1)
        np.testing.assert_allclose(state[7:10], world[3:], atol=1e-12)
        np.testing.assert_allclose(state[10:], local[:3], atol=1e-12)
        assert np.linalg.norm(state[10:] - world[:3]) > 1e-3  # the two frames do differ here
        # Difference quotients: ẋ = v, q̇ = ½ q ⊗ (0, ω) (body frame; the world frame would be ½ (0, ω) ⊗ q).
        delta = 1e-6
        model = env.model
        saved = model.opt.timestep
        model.opt.timestep = delta
        mujoco.mj_step(model, env.data)
        mujoco.mj_forward(model, env.data)
        model.opt.timestep = saved
        after = env.state()
        np.testing.assert_allclose((after[:3] - state[:3]) / delta, state[7:10], atol=1e-5)
        q_dot = 0.5 * np.array(s3.multiply(tuple(state[3:7]), (0.0, *state[10:])))
        np.testing.assert_allclose((after[3:7] - state[3:7]) / delta, q_dot, atol=1e-4)


def test_torque_free_flight_conserves_momenta():
    """No gravity, no thrust: x = x₀ + v₀ t and the world angular momentum R(q) J ω is constant
    (asymmetric body, so ω itself is not)."""
    env = QuadrotorEnv(physics=FREE_FLIGHT)
    inertia = np.diag(env.model.body_inertia[1])
    qpos, qvel = np.array([0.1, -0.2, 1.0, 0.8, 0.2, -0.4, 0.4]), np.array([0.5, -1.0, 2.0, 3.0, -5.0, 6.0])
    state = env.reset(options={"qpos": qpos, "qvel": qvel})[0]
    momentum = rotation(state[3:7]) @ inertia @ state[10:]
    for _ in range(50):  # 1 s
        state = env.step(np.zeros(4))[0]
    np.testing.assert_allclose(state[:3], qpos[:3] + qvel[:3] * 1.0, atol=1e-12)
    np.testing.assert_allclose(rotation(state[3:7]) @ inertia @ state[10:], momentum, rtol=1e-7)
    assert np.linalg.norm(state[10:] - qvel[3:]) > 0.1


def test_thrust_acts_along_body_z_and_hover_holds():
    env = QuadrotorEnv()
    state = env.reset(options={"hover": True})[0]
    for _ in range(25):
        state, reward, *_ = env.step(env.hover_thrust)
    np.testing.assert_allclose(state, env.goal_state, atol=1e-12)
    assert reward == pytest.approx(0.0, abs=1e-20)
    # Tilted, equal thrusts: no torque, acceleration R e_z Σu / m − g e_z (constant while ω = 0).
    q = np.array([np.cos(0.3), np.sin(0.3) * 0.6, np.sin(0.3) * 0.8, 0.0])
    env.reset(options={"qpos": np.concatenate([[0, 0, 1], q])})
    u = np.full(4, 2.0)
    state = env.step(u)[0]
    acceleration = rotation(q)[:, 2] * u.sum() / 0.5 - np.array([0, 0, 9.81])
    np.testing.assert_allclose(state[7:10], acceleration * env.dt, atol=1e-12)
    np.testing.assert_allclose(state[10:], 0.0, atol=1e-12)


def test_rotor_torques_roll_pitch_and_yaw():
    """Body torque from rotor i: r_i × e_z + κ s_i e_z (s = +1, −1, +1, −1), κ = 0.016 m."""
    env = QuadrotorEnv(physics=FREE_FLIGHT)
    arm = 0.17 / np.sqrt(2.0)
    sites = np.array([[arm, arm, 0], [-arm, arm, 0], [-arm, -arm, 0], [arm, -arm, 0]])
    spins = np.array([1.0, -1.0, 1.0, -1.0])
    torque_map = np.array([np.cross(r, [0, 0, 1]) + 0.016 * s * np.array([0, 0, 1]) for r, s in zip(sites, spins)]).T
    inertia = np.diag([2.3e-3, 2.9e-3, 4.6e-3])
    for u in (np.array([1.0, 0.0, 0.0, 0.0]), np.array([0.0, 0.3, 0.0, 0.7]), np.array([0.2, 0.9, 0.5, 0.1])):
        env.reset(options={"hover": True})
        state = env.step(u, substeps=1)[0]  # from rest: ω̇ = J⁻¹ B u, up to the O(Δt²) gyroscopic term in one sub-step
        np.testing.assert_allclose(state[10:], np.linalg.solve(inertia, torque_map @ u) * 0.002, rtol=1e-3)


def test_seeded_resets_cover_upside_down_and_tumbling():
    env = QuadrotorEnv()
    first = env.reset(seed=7)[0]
    np.testing.assert_array_equal(env.reset(seed=7)[0], first)
    states = np.array([env.reset(seed=seed)[0] for seed in range(200)])
    np.testing.assert_array_equal(states[:, :3], np.tile(env.hover_point, (200, 1)))
    np.testing.assert_allclose(np.linalg.norm(states[:, 3:7], axis=1), 1.0, atol=1e-15)
    np.testing.assert_array_equal(states[:, 7:10], 0.0)
    speeds = np.linalg.norm(states[:, 10:], axis=1)
    assert speeds.max() <= 10.0 and speeds.max() > 9.0
    body_z_up = np.array([rotation(q)[2, 2] for q in states[:, 3:7]])
    assert (body_z_up < -0.9).sum() >= 5  # upside down
    offset = env.reset(seed=1, options={"max_offset": 0.5, "max_speed": 2.0, "max_omega": 0.0})[0]
    assert 0 < np.linalg.norm(offset[:3] - env.hover_point) <= 0.5 and 0 < np.linalg.norm(offset[7:10]) <= 2.0
    with pytest.raises(ValueError, match="unknown reset options"):
        env.reset(options={"random": True})
    with pytest.raises(ValueError, match="random start only"):
        env.reset(options={"hover": True, "max_omega": 1.0})


def test_partial_periods_add_up_to_a_period():
    a, b = QuadrotorEnv(), QuadrotorEnv()
    a.reset(seed=4)
    b.reset(seed=4)
    u = np.array([2.0, 0.5, 1.5, 1.0])
    whole = a.step(u)[0]
    b.step(u, substeps=3)
    split = b.step(u, substeps=7)[0]
    np.testing.assert_array_equal(split, whole)
    with pytest.raises(ValueError, match="substeps"):
        a.step(u, substeps=11)


def test_collected_flights_are_seeded_stay_in_range_and_round_trip(tmp_path):
    from fvin_mpc import collect
    from fvin_mpc.core.data import load_data
    from fvin_mpc.learning.collection import collect_quadrotor

    data = collect_quadrotor(trajectories=6, steps=12, seed=3, tumbling_fraction=0.5, progress=False)
    assert data.state.shape == (6, 13, 13) and data.u.shape == (6, 12, 4) and data.num_transitions == 72
    np.testing.assert_array_equal(collect_quadrotor(trajectories=6, steps=12, seed=3, progress=False).state, data.state)
    np.testing.assert_allclose(np.linalg.norm(data.state[..., 3:7], axis=-1), 1.0, atol=1e-12)
    assert np.all(data.u >= 0.0) and np.all(data.u <= 2.5)
    assert np.linalg.norm(data.state[..., :3] - np.array([0, 0, 1.0]), axis=-1).max() <= 6.0
    assert data.metadata["transitions"] == 72 and data.metadata["collector"] == "stabilized-flight"
    # The recorded states are what the env reports: replaying the controls reproduces them.
    env = QuadrotorEnv()
    env.reset(options={"qpos": data.state[0, 0, :7], "qvel": data.state[0, 0, 7:]})
    for k in range(12):
        np.testing.assert_allclose(env.step(data.u[0, k])[0], data.state[0, k + 1], rtol=0, atol=1e-12)
    out = tmp_path / "q.npz"
    assert (
        collect.main(["--scene", "quadrotor", "--trajectories", "3", "--steps", "5", "--out", str(out), "--quiet"]) == 0
    )
    loaded = load_data(out)
    assert loaded.state.shape == (3, 6, 13) and loaded.metadata["configuration_space"] == "R3xS3"
