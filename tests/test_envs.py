"""The Gymnasium environment over MuJoCo scenes: API, state convention, physics switches, oracles."""

from __future__ import annotations

import warnings
from dataclasses import replace
from pathlib import Path

import gymnasium
import mujoco
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from helpers import assert_same_rotation, hinge_quaternion
from scipy.integrate import solve_ivp

from fvin_mpc import envs
from fvin_mpc.envs import SCENES, RigidBodyEnv, ScenePhysics
from fvin_mpc.envs.pendulum_v1 import (
    scene_angle_from_v1,
    state_from_v1_observation,
    v1_angle_from_scene,
    v1_observation_from_state,
)

BUILT_IN = sorted(SCENES)
HINGE_AXIS_Y = np.array([0.0, 1.0, 0.0])






def rollout(env: RigidBodyEnv, controls: np.ndarray) -> np.ndarray:
    return np.array([env.step(u)[0] for u in controls])


def write_mjcf(path: Path, body_xml: str, extra_world: str = "", actuators: str | None = None,
               option: str = 'timestep="0.005" integrator="RK4" gravity="0 0 -10"') -> Path:
    actuators = '<motor name="m" joint="j" ctrlrange="-2 2"/>' if actuators is None else actuators
    path.write_text(f"""<mujoco>
  <compiler autolimits="true"/>
  <option {option}/>
  <worldbody>{extra_world}{body_xml}</worldbody>
  <actuator>{actuators}</actuator>
</mujoco>""")
    return path


HINGE_BODY = """
    <body name="link">
      <joint name="j" type="hinge" axis="0 1 0"/>
      <inertial pos="0 0 -0.5" mass="1" diaginertia="0.1 0.1 0.01"/>
      <geom type="capsule" fromto="0 0 0 0 0 -1" size="0.05" mass="0"/>
    </body>"""


# --------------------------------------------------------------------------- Gymnasium API
KNOWN_CHECK_ENV_WARNINGS = (
    "recommend using a symmetric and normalized space",  # torques in N·m, not [-1, 1], on purpose
    "observation space minimum value is -infinity",  # ω is unbounded
    "observation space maximum value is infinity",
)


def assert_check_env_passes(env: RigidBodyEnv) -> None:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped, skip_render_check=True)  # its render check aborts headless (DESIGN.md)
    # The passive checker reports real problems (observation outside its space, wrong dtype...)
    # as warnings; only the three recommendations we accept are allowed.
    unexpected = [str(w.message) for w in caught if not any(k in str(w.message) for k in KNOWN_CHECK_ENV_WARNINGS)]
    assert unexpected == []


@pytest.mark.parametrize("scene", BUILT_IN)
def test_check_env_passes(scene):
    env = RigidBodyEnv(scene)
    assert_check_env_passes(env)
    env.close()


@pytest.mark.parametrize("scene", BUILT_IN)
def test_render_rgb_array(scene):
    env = RigidBodyEnv(scene, render_mode="rgb_array", width=96, height=64)
    env.reset(options={"random": True}, seed=3)
    image = env.render()
    assert image.shape == (64, 96, 3) and image.dtype == np.uint8
    assert image.std() > 5.0  # not a constant (black) frame
    env.close()
    env.close()  # closing twice is allowed
    with pytest.warns(UserWarning, match="render_mode"):
        assert RigidBodyEnv(scene).render() is None  # no render_mode: warns, renders nothing


def test_render_mode_validated():
    with pytest.raises(ValueError, match="render_mode"):
        RigidBodyEnv("pendulum", render_mode="human")


def test_accessors_and_metadata():
    env = RigidBodyEnv("spherical_pendulum")
    spec = SCENES["spherical_pendulum"]
    assert env.body_name == "pendulum" and env.joint_type == "ball"
    assert env.dt == pytest.approx(0.05) and env.frame_skip == 10
    assert env.physics == spec.physics
    np.testing.assert_allclose(env.goal, [0.0, 0.0, 1.0, 0.0], atol=1e-15)  # read off the potential: upright
    np.testing.assert_array_equal(env.torque_low, [-1.5] * 3)
    np.testing.assert_array_equal(env.torque_high, [1.5] * 3)
    assert env.action_space.dtype == np.float64 and env.observation_space.shape == (7,)
    assert env.metadata == {"render_modes": ["rgb_array"], "render_fps": 20}
    assert isinstance(env.model, mujoco.MjModel) and isinstance(env.data, mujoco.MjData)
    assert RigidBodyEnv("pendulum").joint_type == "hinge"


def test_make_registered_ids_and_truncation():
    envs.register_envs()  # idempotent: no error, no re-registration
    for env_id, scene in envs.ENV_IDS.items():
        assert gymnasium.spec(env_id).kwargs == {"scene": scene}
        assert gymnasium.spec(env_id).max_episode_steps == 200
    env = gymnasium.make("fvin_mpc/Pendulum-v0")
    env.reset(seed=0)
    for k in range(1, 201):
        _, reward, terminated, truncated, info = env.step(np.zeros(1))
        assert not terminated and np.isfinite(reward)
        assert truncated == (k == 200)
    assert info["time"] == pytest.approx(10.0)
    env.close()


def test_reward_and_info_at_rest():
    env = RigidBodyEnv("pendulum")
    _, info = env.reset()
    assert info["angle_from_goal"] == pytest.approx(np.pi)  # hanging; goal upright
    assert info["time"] == 0.0 and info["energy"] == pytest.approx(-5.0)  # m g z_com = 10 · (−0.5)
    # Upright at rest stays there for one step (unstable, but exact equilibrium): reward ≈ −0.001 u².
    env.reset(options={"qpos": [np.pi]})
    _, reward, terminated, truncated, info = env.step(np.zeros(1))
    assert reward == pytest.approx(0.0, abs=1e-20) and info["angle_from_goal"] == pytest.approx(0.0, abs=1e-9)
    assert not terminated and not truncated
    env.reset()
    _, reward, *_ , info = env.step(np.array([2.0]))
    omega = env.state()[4:]
    assert reward == pytest.approx(-(info["angle_from_goal"] ** 2 + 0.1 * omega @ omega + 0.001 * 4.0))


# --------------------------------------------------------------------------- reset / step contract
@pytest.mark.parametrize("scene", ["pendulum", "spherical_pendulum"])
def test_random_reset_is_deterministic_under_a_seed(scene):
    a, b = RigidBodyEnv(scene), RigidBodyEnv(scene)
    obs_a, _ = a.reset(seed=7, options={"random": True, "max_omega": 3.0})
    obs_b, _ = b.reset(seed=7, options={"random": True, "max_omega": 3.0})
    np.testing.assert_array_equal(obs_a, obs_b)
    controls = np.full((5, a.action_space.shape[0]), 0.5)
    np.testing.assert_array_equal(rollout(a, controls), rollout(b, controls))
    obs_c, _ = b.reset(seed=8, options={"random": True, "max_omega": 3.0})
    assert not np.allclose(obs_a, obs_c)
    for seed in range(20):
        obs, _ = a.reset(seed=seed, options={"random": True, "max_omega": 3.0})
        assert np.linalg.norm(obs[:4]) == pytest.approx(1.0) and np.linalg.norm(obs[4:]) <= 3.0


def test_default_reset_is_hanging_at_rest():
    for scene in BUILT_IN:
        env = RigidBodyEnv(scene)
        obs, _ = env.reset(seed=1)
        np.testing.assert_array_equal(obs, [1, 0, 0, 0, 0, 0, 0])
        np.testing.assert_array_equal(env.data.qpos, env.model.qpos0)


def test_reset_with_qpos_qvel_sets_them_exactly():
    env = RigidBodyEnv("pendulum")
    env.reset(options={"qpos": [0.123456789], "qvel": [-4.5]})
    assert env.data.qpos[0] == 0.123456789 and env.data.qvel[0] == -4.5 and env.data.time == 0.0
    ball = RigidBodyEnv("spherical_pendulum")
    raw = np.array([2.0, -1.0, 0.5, 0.25])  # not unit: normalized by reset
    obs, _ = ball.reset(options={"qpos": raw, "qvel": [0.1, -0.2, 0.3]})
    np.testing.assert_allclose(ball.data.qpos, raw / np.linalg.norm(raw), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(ball.data.qvel, [0.1, -0.2, 0.3])
    np.testing.assert_allclose(obs[4:], [0.1, -0.2, 0.3], atol=1e-15)
    # set_state does the same without resetting time.
    ball.step(np.zeros(3))
    ball.set_state([1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    assert ball.data.time == pytest.approx(0.05)
    np.testing.assert_array_equal(ball.state()[4:], [0.0, 0.0, 1.0])


@pytest.mark.parametrize(
    "options",
    [
        {"qpos": [0.1, 0.2]},
        {"qpos": [[0.1]]},
        {"qvel": np.zeros(3)},
        {"qpos": [np.nan]},
        {"qvel": [np.inf]},
        {"qpos": "zero"},
        {"random": True, "qpos": [0.0]},
        {"random": True, "max_omega": -1.0},
        {"max_omega": 2.0},
        {"qpoz": [0.0]},
    ],
)
def test_bad_reset_options_raise(options):
    env = RigidBodyEnv("pendulum")
    env.reset(options={"qpos": [0.5], "qvel": [0.25]})
    with pytest.raises(ValueError):
        env.reset(options=options)
    assert env.data.qpos[0] == 0.5 and env.data.qvel[0] == 0.25  # left as it was


def test_bad_ball_reset_options_raise():
    env = RigidBodyEnv("spherical_pendulum")
    for options in ({"qpos": np.zeros(4)}, {"qpos": [1.0]}, {"qvel": [0.0]}, {"qpos": [1, 0, 0, np.nan]}):
        with pytest.raises(ValueError):
            env.reset(options=options)


@pytest.mark.parametrize("action", [np.zeros(2), np.zeros((1, 1)), 0.5, [np.nan], np.array([np.inf]), ["a"]])
def test_bad_action_raises_and_sends_nothing(action):
    env = RigidBodyEnv("pendulum")
    env.reset(options={"qpos": [1.0]})
    env.step(np.array([0.7]))
    qpos, time, ctrl = env.data.qpos.copy(), env.data.time, env.data.ctrl.copy()
    with pytest.raises(ValueError, match="action"):
        env.step(action)
    np.testing.assert_array_equal(env.data.qpos, qpos)
    np.testing.assert_array_equal(env.data.ctrl, ctrl)
    assert env.data.time == time


def test_actions_outside_bounds_are_clipped():
    a, b = RigidBodyEnv("pendulum"), RigidBodyEnv("pendulum")
    a.reset(), b.reset()
    obs_a, reward_a, *_ = a.step(np.array([50.0]))
    obs_b, reward_b, *_ = b.step(np.array([2.0]))
    np.testing.assert_array_equal(obs_a, obs_b)
    assert reward_a == reward_b  # the cost sees the applied torque


# --------------------------------------------------------------------------- state convention
def test_pendulum_observation_is_hinge_state():
    """q = (cos θ/2, 0, sin θ/2, 0) and ω = (0, θ̇, 0): checked after steps, not only at reset."""
    env = RigidBodyEnv("pendulum")
    rng = np.random.default_rng(0)
    for _ in range(5):
        env.reset(options={"qpos": rng.uniform(-np.pi, np.pi, 1), "qvel": rng.uniform(-6, 6, 1)})
        for u in rng.uniform(-2, 2, size=(8, 1)):
            obs, *_ = env.step(u)
            theta, theta_dot = env.data.qpos[0], env.data.qvel[0]
            assert_same_rotation(obs[:4], hinge_quaternion(theta), atol=1e-12)
            np.testing.assert_allclose(obs[4:], theta_dot * HINGE_AXIS_Y, rtol=0, atol=1e-12)


def test_spherical_observation_is_ball_state():
    """For a ball joint on a body hanging from the world, qpos is q and qvel is the body-frame ω."""
    env = RigidBodyEnv("spherical_pendulum")
    rng = np.random.default_rng(1)
    for _ in range(5):
        env.reset(seed=int(rng.integers(100)), options={"random": True, "max_omega": 6.0})
        for u in rng.uniform(-1.5, 1.5, size=(8, 3)):
            obs, *_ = env.step(u)
            assert_same_rotation(obs[:4], env.data.qpos, atol=1e-12)
            np.testing.assert_allclose(obs[4:], env.data.qvel, rtol=0, atol=1e-12)
            # ω is body-frame: world-frame ω = R(q) ω matches MuJoCo's world angular velocity.
            body = mujoco.mj_name2id(env.model, mujoco.mjtObj.mjOBJ_BODY, env.body_name)
            world = np.zeros(6)
            mujoco.mj_objectVelocity(env.model, env.data, mujoco.mjtObj.mjOBJ_BODY, body, world, 0)
            np.testing.assert_allclose(env.data.xmat[body].reshape(3, 3) @ obs[4:], world[:3], atol=1e-12)


@pytest.mark.parametrize(
    "theta0, theta_dot0, torque",
    [(0.0, 0.0, 1.0), (1.0, -2.0, -2.0), (3.0, 0.5, 0.7), (-2.5, 4.0, 0.0)],
)
def test_pendulum_scene_matches_the_ode(theta0, theta_dot0, torque):
    """MuJoCo's pendulum scene integrates θ̈ = −15 sin θ + 3τ (Pendulum-v1's physics, θ = 0 hanging)."""
    env = RigidBodyEnv("pendulum")
    env.reset(options={"qpos": [theta0], "qvel": [theta_dot0]})
    steps = 40  # 2 s
    times = env.dt * np.arange(1, steps + 1)
    reference = solve_ivp(
        lambda t, x: [x[1], -15.0 * np.sin(x[0]) + 3.0 * torque],
        (0.0, times[-1]), [theta0, theta_dot0], method="DOP853", rtol=1e-12, atol=1e-12, t_eval=times,
    )
    theta, theta_dot = [], []
    for _ in range(steps):
        env.step(np.array([torque]))
        theta.append(env.data.qpos[0])
        theta_dot.append(env.data.qvel[0])
    # Measured (RK4, h = 5 ms, 400 steps): at most 2.3e-8 rad and 4.7e-8 rad/s over these cases.
    # The bound leaves ~4× headroom; an inertia or gear error of 1e-6 would already exceed it.
    np.testing.assert_allclose(theta, reference.y[0], rtol=0, atol=1e-7)
    np.testing.assert_allclose(theta_dot, reference.y[1], rtol=0, atol=2e-7)


# --------------------------------------------------------------------------- physics switches
def energy_trace(env: RigidBodyEnv, steps: int) -> np.ndarray:
    energy = [env.data.energy.sum()]
    for _ in range(steps):
        energy.append(env.step(np.zeros(env.action_space.shape))[4]["energy"])
    return np.array(energy)


@pytest.mark.parametrize("scene, qpos, qvel", [
    ("pendulum", [2.0], [1.0]),
    ("spherical_pendulum", [0.8, 0.3, 0.4, 0.2], [1.0, 2.0, -3.0]),
])
def test_energy_conserved_without_damping_or_friction(scene, qpos, qvel):
    env = RigidBodyEnv(scene)
    assert not env.physics.joint_damping and not env.physics.dry_friction
    env.reset(options={"qpos": qpos, "qvel": qvel})
    energy = energy_trace(env, 200)  # 10 s, control 0
    # Measured drift 1e-8 (pendulum) and 4e-8 J (spherical) with RK4 at 5 ms, on energies of 1–2 J.
    assert np.max(np.abs(energy - energy[0])) < 1e-6


def test_damping_dissipates_and_can_be_switched_off():
    damped = RigidBodyEnv("pendulum_damped")
    assert damped.physics.joint_damping
    assert not damped.model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_DAMPER
    damped.reset(options={"qpos": [2.0]})
    energy = energy_trace(damped, 200)
    assert np.all(np.diff(energy) < 0)  # strictly decreasing while it swings
    assert energy[-1] < energy[0] - 5.0  # 2.08 J at the start, close to the −5 J minimum after 10 s
    # The same MJCF, damping declared off: conservative again.
    undamped = RigidBodyEnv("pendulum_damped", physics=replace(SCENES["pendulum_damped"].physics, joint_damping=False))
    assert undamped.model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_DAMPER
    assert undamped.model.dof_damping[0] == 0.1  # still in the file, switched off
    undamped.reset(options={"qpos": [2.0]})
    energy = energy_trace(undamped, 200)
    assert np.max(np.abs(energy - energy[0])) < 1e-6


def test_gravity_off_means_free_rotation():
    physics = replace(SCENES["pendulum"].physics, gravity=False)
    env = RigidBodyEnv("pendulum", physics=physics)
    assert env.model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_GRAVITY
    env.reset(options={"qvel": [0.3]})
    observations = rollout(env, np.zeros((40, 1)))
    np.testing.assert_allclose(observations[:, 5], 0.3, rtol=0, atol=1e-12)  # ω constant: no potential exchange
    assert env.data.qpos[0] == pytest.approx(0.3 * 2.0, abs=1e-12)  # θ = θ̇ t
    # With gravity the same start slows down as it rises.
    env = RigidBodyEnv("pendulum")
    env.reset(options={"qvel": [0.3]})
    assert abs(rollout(env, np.zeros((4, 1)))[-1, 5]) < 0.29


def test_contact_switched_off_unless_declared(tmp_path):
    # A hinged rod hanging through a floor: its geoms collide if contact acts.
    xml = write_mjcf(
        tmp_path / "floor.xml", HINGE_BODY,
        extra_world='<geom name="floor" type="plane" pos="0 0 -0.8" size="2 2 .1"/>',
    )
    base = ScenePhysics(gravity=True, joint_damping=False, dry_friction=False, actuator_limits=True, contact=True)
    with_contact = RigidBodyEnv(xml, physics=base)
    with_contact.reset()
    assert with_contact.data.ncon > 0  # the test scene can collide
    without = RigidBodyEnv(xml, physics=replace(base, contact=False))
    assert without.model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
    without.reset()
    for _ in range(10):
        without.step(np.array([1.0]))
        assert without.data.ncon == 0
    for scene in BUILT_IN:  # built-in scenes: contact not declared, flag set
        env = RigidBodyEnv(scene)
        assert not env.physics.contact and env.model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
    # Declared on where nothing can collide: a false declaration.
    with pytest.raises(ValueError, match="contact"):
        RigidBodyEnv("pendulum", physics=replace(SCENES["pendulum"].physics, contact=True))


def test_sensor_noise():
    start = {"qpos": [1.0], "qvel": [0.5]}
    a, b = RigidBodyEnv("pendulum"), RigidBodyEnv("pendulum")
    assert a.physics.sensor_noise_std == 0.0
    obs_a, _ = a.reset(seed=1, options=start)
    obs_b, _ = b.reset(seed=2, options=start)
    np.testing.assert_array_equal(obs_a, obs_b)
    np.testing.assert_array_equal(rollout(a, np.ones((3, 1))), rollout(b, np.ones((3, 1))))

    noisy = replace(SCENES["pendulum"].physics, sensor_noise_std=0.01)
    a, b = RigidBodyEnv("pendulum", physics=noisy), RigidBodyEnv("pendulum", physics=noisy)
    obs_a, info_a = a.reset(seed=1, options=start)
    obs_b, info_b = b.reset(seed=2, options=start)
    assert not np.allclose(obs_a, obs_b)
    assert info_a == info_b  # info (and reward) use the true state
    observations = np.concatenate([[obs_a], rollout(a, np.ones((50, 1)))])
    np.testing.assert_allclose(np.linalg.norm(observations[:, :4], axis=1), 1.0, rtol=0, atol=1e-14)
    omega_true = a.state()[4:]
    assert np.all(observations[:, [4, 6]] != 0.0)  # noise on all entries, not only the moving ones
    assert np.abs(observations[-1, 4:] - omega_true).max() < 0.1  # ~ 0.01 standard deviation
    # Same seed, same noise.
    c = RigidBodyEnv("pendulum", physics=noisy)
    np.testing.assert_array_equal(c.reset(seed=1, options=start)[0], obs_a)


# --------------------------------------------------------------------------- user MJCF
def test_user_mjcf_defaults(tmp_path):
    xml = write_mjcf(tmp_path / "p.xml", HINGE_BODY, option='timestep="0.002" gravity="0 0 -9.81"')
    env = RigidBodyEnv(str(xml))
    assert env.body_name == "link" and env.joint_type == "hinge"
    # The period follows the speed scale ω_s = √(2·ΔE/J) = √(2 · 9.81 J / 0.35 kg·m²) = 7.49 rad/s: the
    # multiple of 2 ms nearest to 0.387 rad / ω_s = 51.7 ms (the pendulum scene's turn per step, 50 ms × √60).
    assert env.speed_scale == pytest.approx((2 * 9.81 / 0.35) ** 0.5)
    assert env.frame_skip == 26 and env.dt == pytest.approx(0.052)
    # The task read off the potential: the centre of mass hangs below the pivot at qpos0, so the
    # goal is half a turn about the hinge, and episodes start at rest at qpos0.
    np.testing.assert_allclose(env.goal, [0, 0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(env.rest, [1, 0, 0, 0], atol=1e-15)
    np.testing.assert_allclose(env.reset()[0], [1, 0, 0, 0, 0, 0, 0], atol=1e-15)
    assert env.physics == ScenePhysics(gravity=True, joint_damping=False, dry_friction=False,
                                       actuator_limits=True, contact=False)  # inferred: one geom, nothing to hit
    np.testing.assert_array_equal(env.torque_high, [2.0])
    assert_check_env_passes(env)


def test_user_mjcf_validation(tmp_path):
    two_bodies = write_mjcf(
        tmp_path / "two.xml", HINGE_BODY + HINGE_BODY.replace('"link"', '"other"').replace('"j"', '"k"')
    )
    with pytest.raises(ValueError, match="pass body="):
        RigidBodyEnv(two_bodies)
    with pytest.raises(ValueError, match="only degree of freedom"):
        RigidBodyEnv(two_bodies, body="link")
    slide = write_mjcf(tmp_path / "slide.xml", HINGE_BODY.replace('type="hinge"', 'type="slide"'))
    with pytest.raises(ValueError, match="hinge or a ball"):
        RigidBodyEnv(slide)
    unactuated = write_mjcf(tmp_path / "free.xml", HINGE_BODY, actuators="")
    with pytest.raises(ValueError, match="not actuated"):
        RigidBodyEnv(unactuated)
    with pytest.raises(ValueError, match="no body named"):
        RigidBodyEnv("pendulum", body="nope")
    with pytest.raises(ValueError, match="whole multiple"):
        RigidBodyEnv("pendulum", control_period=0.0525)
    with pytest.raises(ValueError, match="unknown scene"):
        RigidBodyEnv("pendulumm")
    with pytest.raises(ValueError, match="not found"):
        RigidBodyEnv(tmp_path / "missing.xml")
    with pytest.raises(ValueError, match="goal"):
        RigidBodyEnv("pendulum", goal=[0, 0, 0, 0])
    # Unbounded actuators without declared limits give an unbounded action space.
    env = RigidBodyEnv("pendulum", physics=replace(SCENES["pendulum"].physics, actuator_limits=False))
    assert np.all(np.isinf(env.action_space.high))


def test_a_fast_scene_keeps_the_shortest_default_period(tmp_path):
    """A body whose speed scale asks for less than 20 ms (ω_s = 40 rad/s: 9.7 ms) is still controlled
    at 20 ms, the multiple of its 2 ms timestep (an MPC solve must fit in a period)."""
    from fvin_mpc.envs.rigid_body_env import STEP_ANGLE, scale_control_period

    assert scale_control_period(40.0, 0.002) == pytest.approx(0.02)
    assert scale_control_period(STEP_ANGLE / 0.1, 0.002) == pytest.approx(0.1)  # a slow body: 100 ms
    assert scale_control_period(STEP_ANGLE / 0.1, 0.03) == pytest.approx(0.09)  # the nearest multiple of 30 ms


def test_control_period_multiple():
    env = RigidBodyEnv("pendulum", control_period=0.02)
    assert env.frame_skip == 4 and env.metadata["render_fps"] == 50


# --------------------------------------------------------------------------- Pendulum-v1 adapter
def test_pendulum_v1_conversion_round_trip():
    rng = np.random.default_rng(0)
    theta_v1 = rng.uniform(-np.pi, np.pi, 100)
    theta_dot = rng.uniform(-8, 8, 100)
    observation = np.stack([np.cos(theta_v1), np.sin(theta_v1), theta_dot], axis=-1)
    states = state_from_v1_observation(observation)
    q, omega = states[:, :4], states[:, 4:]
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0)
    np.testing.assert_allclose(v1_observation_from_state(states), observation, atol=1e-14)
    flipped = np.concatenate([-q, omega], axis=-1)
    np.testing.assert_allclose(v1_observation_from_state(flipped), observation, atol=1e-14)  # sign invariant
    # Upright in Pendulum-v1 is the scene's goal; hanging is its rest.
    scene = RigidBodyEnv("pendulum")
    assert_same_rotation(state_from_v1_observation([1.0, 0.0, 0.0])[:4], scene.goal, 1e-15)
    assert_same_rotation(state_from_v1_observation([-1.0, 0.0, 0.0])[:4], scene.rest, 1e-15)
    np.testing.assert_allclose(v1_angle_from_scene(scene_angle_from_v1(theta_v1)), theta_v1, atol=1e-14)
    # Each q is the scene's orientation at the converted hinge angle.
    for k in range(5):
        assert_same_rotation(q[k], hinge_quaternion(scene_angle_from_v1(theta_v1[k])), 1e-14)


def test_pendulum_v1_torque_direction_agrees():
    """A positive torque turns both pendulums the same way (θ_scene = θ_v1 + π, ω = θ̇, τ = τ)."""
    v1 = gymnasium.make("Pendulum-v1").unwrapped  # unmodified; its state is set directly
    ours = RigidBodyEnv("pendulum")

    def one_step(theta_v1, theta_dot, torque):
        v1.reset(seed=0)
        v1.state = np.array([theta_v1, theta_dot])
        v1_obs = v1.step(np.array([torque], dtype=np.float32))[0]
        x = state_from_v1_observation([np.cos(theta_v1), np.sin(theta_v1), theta_dot])
        q, omega = x[:4], x[4:]
        assert_same_rotation(q, hinge_quaternion(scene_angle_from_v1(theta_v1)), 1e-14)
        ours.reset(options={"qpos": [scene_angle_from_v1(theta_v1)], "qvel": [omega[1]]})
        return float(v1_obs[2]), float(ours.step(np.array([torque]))[0][5])

    # Torque response over one step, same state: Pendulum-v1 gives exactly 3·Δτ·dt = 0.6 rad/s.
    for theta_v1, theta_dot in [(0.5, 0.0), (3.0, -1.0), (-2.0, 2.0)]:
        v1_plus, ours_plus = one_step(theta_v1, theta_dot, 2.0)
        v1_minus, ours_minus = one_step(theta_v1, theta_dot, -2.0)
        assert v1_plus - v1_minus == pytest.approx(0.6, abs=1e-6)
        assert ours_plus - ours_minus == pytest.approx(0.6, abs=0.01)  # the same sign and size

    # Whole trajectories agree up to Pendulum-v1's semi-implicit Euler error (dt = 0.05), while
    # the mirrored convention (θ_scene = π − θ_v1, ω = −θ̇, i.e. the opposite torque sign) does not.
    for theta_v1, theta_dot, torque in [
        (np.pi - 0.2, 0.0, 2.0),
        (np.pi + 0.5, 1.0, -2.0),
        (0.3, 0.0, 2.0),
        (2.5, -1.0, -1.5),
    ]:
        v1.reset(seed=0)
        v1.state = np.array([theta_v1, theta_dot])
        mirrored = RigidBodyEnv("pendulum")
        ours.reset(options={"qpos": [scene_angle_from_v1(theta_v1)], "qvel": [theta_dot]})
        mirrored.reset(options={"qpos": [np.pi - theta_v1], "qvel": [-theta_dot]})
        error, mirrored_error = 0.0, 0.0
        for _ in range(5):
            v1_obs = v1.step(np.array([torque], dtype=np.float32))[0].astype(np.float64)
            obs = ours.step(np.array([torque]))[0]
            ours_as_v1 = v1_observation_from_state(obs)
            error = max(error, np.abs(ours_as_v1 - v1_obs)[:2].max())
            mirrored.step(np.array([torque]))
            mirrored_theta_v1 = np.pi - mirrored.data.qpos[0]
            mirrored_as_v1 = np.array([np.cos(mirrored_theta_v1), np.sin(mirrored_theta_v1)])
            mirrored_error = max(mirrored_error, np.abs(mirrored_as_v1 - v1_obs[:2]).max())
        # Measured (max |Δcos|, |Δsin|): 0.02–0.07 correct vs 0.20–0.42 mirrored over these cases.
        assert error < 0.08
        assert mirrored_error > 2.5 * error
