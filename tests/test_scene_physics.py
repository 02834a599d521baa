"""Scene physics switches (envs.scenes) and learning the damping of a dissipative scene.

Complements the switch tests in ``tests/test_envs.py`` (gravity off, damping on/off, contact
on/off, sensor noise): every declarable effect is shown *off* when not declared, with an
oracle where there is one, and every "declared but absent" case is an error. The last test
trains the S3FVIN with and without its dissipation term on damped synthetic data.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest
from helpers import synthetic_hinge_data
from scipy.integrate import solve_ivp

from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.data import Trajectories
from fvin_mpc.core.networks import ModelConfig
from fvin_mpc.core.rigid_body import PENDULUM_DAMPED, from_mujoco
from fvin_mpc.envs import SCENES, RigidBodyEnv, ScenePhysics
from fvin_mpc.envs.scenes import ALWAYS_DISABLED, build_model, infer_physics

NP = get_ops("numpy")
DSBL = mujoco.mjtDisableBit
#: Each declarable effect and the MuJoCo disable bit that switches it off.
SWITCHES = {
    "gravity": DSBL.mjDSBL_GRAVITY,
    "joint_damping": DSBL.mjDSBL_DAMPER,
    "dry_friction": DSBL.mjDSBL_FRICTIONLOSS,
    "actuator_limits": DSBL.mjDSBL_CLAMPCTRL,
    "contact": DSBL.mjDSBL_CONTACT,
}


def rod_mjcf(path: Path, joint: str = "", option: str = 'gravity="0 0 -10"', motor: str = 'ctrlrange="-2 2"',
             extra: str = "", flags: str = "") -> Path:
    """Pendulum-v1's rod (θ̈ = −15 sin θ + 3τ without extra joint attributes) on a hinge about +y."""
    path.write_text(f"""<mujoco>
  <compiler autolimits="true"/>
  <option timestep="0.005" integrator="RK4" {option}>{flags}</option>
  <worldbody>
    <body name="rod">
      <joint name="hinge" type="hinge" axis="0 1 0" {joint}/>
      <inertial pos="0 0 -0.5" mass="1" diaginertia="0.083333333333 0.083333333333 1e-6"/>
      <geom type="capsule" fromto="0 0 0 0 0 -1" size="0.04" mass="0" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
  <actuator><motor name="torque" joint="hinge" {motor}/></actuator>
  {extra}
</mujoco>""")
    return path


def hinge_ode(theta0: float, theta_dot0: float, torque: float, damping: float, seconds: float, steps: int):
    """θ̈ = −15 sin θ + 3τ − 3·damping·θ̇ (rod inertia 1/3) at ``steps`` evenly spaced times."""
    times = seconds / steps * np.arange(1, steps + 1)
    solution = solve_ivp(
        lambda t, x: [x[1], -15.0 * np.sin(x[0]) + 3.0 * torque - 3.0 * damping * x[1]],
        (0.0, times[-1]), [theta0, theta_dot0], method="DOP853", rtol=1e-12, atol=1e-12, t_eval=times,
    )
    return solution.y[0], solution.y[1]


def run_hinge(env: RigidBodyEnv, theta0: float, theta_dot0: float, torque: float, steps: int):
    env.reset(options={"qpos": [theta0], "qvel": [theta_dot0]})
    theta, theta_dot = [], []
    for _ in range(steps):
        env.step(np.array([torque]))
        theta.append(env.data.qpos[0])
        theta_dot.append(env.data.qvel[0])
    return np.array(theta), np.array(theta_dot)


# --------------------------------------------------------------------------- flags of the built-in scenes
@pytest.mark.parametrize("scene", sorted(SCENES))
def test_built_in_scene_disables_exactly_what_it_does_not_declare(scene):
    env = RigidBodyEnv(scene)
    flags = int(env.model.opt.disableflags)
    assert flags == env.physics.disable_flags()
    assert flags & ALWAYS_DISABLED == ALWAYS_DISABLED  # springs, joint limits, equality constraints
    for effect, bit in SWITCHES.items():
        assert bool(flags & int(bit)) == (not getattr(env.physics, effect)), effect
    # What the declarations say: gravity and actuator limits everywhere, damping only in the
    # damped scene, no dry friction, no contact, no sensor noise.
    assert env.physics == ScenePhysics(gravity=True, joint_damping=scene == "pendulum_damped", dry_friction=False,
                                       actuator_limits=True, contact=False, sensor_noise_std=0.0)


# --------------------------------------------------------------------------- joint damping
@pytest.mark.parametrize("theta0, theta_dot0, torque", [(2.0, 0.0, 0.0), (-1.0, 5.0, 1.5)])
def test_damped_scene_matches_the_damped_ode(theta0, theta_dot0, torque):
    """pendulum_damped integrates θ̈ = −15 sin θ + 3τ − 0.3 θ̇; declared off, the same MJCF loses the −0.3 θ̇."""
    steps = 40  # 2 s
    reference = hinge_ode(theta0, theta_dot0, torque, 0.1, steps * 0.05, steps)
    result = run_hinge(RigidBodyEnv("pendulum_damped"), theta0, theta_dot0, torque, steps)
    # RK4 at 5 ms, as the undamped oracle test in test_envs.py (measured errors ~1e-8).
    np.testing.assert_allclose(result[0], reference[0], rtol=0, atol=1e-7)
    np.testing.assert_allclose(result[1], reference[1], rtol=0, atol=2e-7)

    undeclared = replace(SCENES["pendulum_damped"].physics, joint_damping=False)
    result = run_hinge(RigidBodyEnv("pendulum_damped", physics=undeclared), theta0, theta_dot0, torque, steps)
    reference = hinge_ode(theta0, theta_dot0, torque, 0.0, steps * 0.05, steps)
    np.testing.assert_allclose(result[0], reference[0], rtol=0, atol=1e-7)
    np.testing.assert_allclose(result[1], reference[1], rtol=0, atol=2e-7)


def test_true_model_follows_the_damping_declaration():
    """The closed-form body read off the model has the damping only while it is switched on,
    and its dissipation in the model's force units is twice the joint damping (DESIGN.md)."""
    damped = RigidBodyEnv("pendulum_damped")
    body = from_mujoco(damped.model, damped.body_name)
    assert body.damping == pytest.approx(0.1)
    assert body.damping == PENDULUM_DAMPED.damping
    identity = tuple(np.ones(1) * c for c in (1.0, 0.0, 0.0, 0.0))
    np.testing.assert_allclose(np.array(body.terms(NP).dissipation(identity), dtype=float)[..., 0], 0.2 * np.eye(3))
    undeclared = RigidBodyEnv("pendulum_damped", physics=replace(damped.physics, joint_damping=False))
    assert from_mujoco(undeclared.model, undeclared.body_name).damping == 0.0


# --------------------------------------------------------------------------- dry friction
def test_dry_friction_acts_only_when_declared(tmp_path):
    """frictionloss dissipates (friction torque × distance travelled); declared off the file is frictionless."""
    friction = 0.5  # N·m, a quarter of the motor's range
    xml = rod_mjcf(tmp_path / "friction.xml", joint=f'frictionloss="{friction}"')
    assert infer_physics(build_model(xml)[0]).dry_friction  # the file has it
    physics = ScenePhysics(gravity=True, joint_damping=False, dry_friction=True, actuator_limits=True, contact=False)
    # One MuJoCo step per control period, so the travelled distance is summed finely.
    env = RigidBodyEnv(xml, physics=physics, control_period=0.005)
    assert not env.model.opt.disableflags & DSBL.mjDSBL_FRICTIONLOSS
    env.reset(options={"qpos": [2.0], "qvel": [3.0]})
    energy, distance, speed = [env.data.energy.sum()], 0.0, abs(env.data.qvel[0])
    for _ in range(400):  # 2 s
        energy.append(env.step(np.zeros(1))[4]["energy"])
        new_speed = abs(env.data.qvel[0])
        distance += 0.5 * (speed + new_speed) * env.dt
        speed = new_speed
    energy = np.array(energy)
    # MuJoCo's friction loss is a soft constraint: at the turning point where it sticks the
    # energy rises by up to 1.5e-4 J (measured); otherwise it only falls.
    assert np.diff(energy).max() < 1e-3
    # Coulomb friction dissipates friction · distance travelled: measured ratio 0.9996.
    assert energy[0] - energy[-1] == pytest.approx(friction * distance, rel=0.01)

    # The same file, friction declared off: energy conserved and the frictionless ODE.
    off = RigidBodyEnv(xml, physics=replace(physics, dry_friction=False), control_period=0.05)
    assert off.model.opt.disableflags & DSBL.mjDSBL_FRICTIONLOSS
    assert off.model.dof_frictionloss[0] == friction  # still in the file, switched off
    theta, theta_dot = run_hinge(off, 2.0, 3.0, 0.0, 40)
    reference = hinge_ode(2.0, 3.0, 0.0, 0.0, 2.0, 40)
    np.testing.assert_allclose(theta, reference[0], rtol=0, atol=1e-7)
    np.testing.assert_allclose(theta_dot, reference[1], rtol=0, atol=2e-7)


# --------------------------------------------------------------------------- actuator limits
def test_actuator_limits_off_applies_controls_unclamped():
    """Undeclared limits: the action space is unbounded and τ = 50 N·m is applied as is
    (θ̈ = −15 sin θ + 150), not clamped to the MJCF's ctrlrange of ±2."""
    undeclared = replace(SCENES["pendulum"].physics, actuator_limits=False)
    env = RigidBodyEnv("pendulum", physics=undeclared)
    assert env.model.opt.disableflags & DSBL.mjDSBL_CLAMPCTRL
    assert np.all(np.isinf(env.action_space.low)) and np.all(np.isinf(env.action_space.high))
    theta, theta_dot = run_hinge(env, 0.5, 0.0, 50.0, 4)
    reference = hinge_ode(0.5, 0.0, 50.0, 0.0, 0.2, 4)
    np.testing.assert_allclose(theta, reference[0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(theta_dot, reference[1], rtol=0, atol=1e-6)
    assert env.data.actuator_force[0] == 50.0


def test_actuator_limits_on_are_enforced_by_mujoco_itself():
    """Declared limits: besides the env's clipping, MuJoCo clamps a control written to
    ``data.ctrl`` directly (``mjDSBL_CLAMPCTRL`` cleared)."""
    env = RigidBodyEnv("pendulum")
    assert not env.model.opt.disableflags & DSBL.mjDSBL_CLAMPCTRL
    env.reset(options={"qpos": [0.5]})
    env.data.ctrl[:] = 50.0
    for _ in range(env.frame_skip):
        mujoco.mj_step(env.model, env.data)
    assert env.data.actuator_force[0] == 2.0
    reference = hinge_ode(0.5, 0.0, 2.0, 0.0, env.dt, 1)
    assert env.data.qvel[0] == pytest.approx(reference[1][0], abs=1e-7)


# --------------------------------------------------------------------------- gravity
def test_gravity_off_on_the_spherical_pendulum_conserves_momentum_and_stays_balanced():
    """Undeclared gravity on the ball joint: a body at rest in any orientation stays there."""
    env = RigidBodyEnv("spherical_pendulum", physics=replace(SCENES["spherical_pendulum"].physics, gravity=False))
    assert env.model.opt.disableflags & DSBL.mjDSBL_GRAVITY
    q0 = np.array([0.8, 0.3, 0.4, 0.2]) / np.linalg.norm([0.8, 0.3, 0.4, 0.2])
    env.reset(options={"qpos": q0})
    for _ in range(20):
        obs = env.step(np.zeros(3))[0]
    assert min(np.abs(obs[:4] - q0).max(), np.abs(obs[:4] + q0).max()) < 1e-12
    np.testing.assert_array_equal(obs[4:], 0.0)
    assert env.data.energy[0] == 0.0  # no potential energy without gravity


# --------------------------------------------------------------------------- sensor noise
@pytest.mark.parametrize("scene", sorted(SCENES))
def test_no_sensor_noise_unless_declared(scene):
    """Undeclared noise: every observation is the simulator's state, bit for bit."""
    env = RigidBodyEnv(scene)
    assert env.physics.sensor_noise_std == 0.0
    obs, _ = env.reset(seed=0, options={"random": True, "max_omega": 3.0})
    rng = np.random.default_rng(0)
    for k in range(10):
        np.testing.assert_array_equal(obs, env.state())
        obs = env.step(rng.uniform(env.torque_low, env.torque_high))[0]


def test_sensor_noise_std_validated():
    with pytest.raises(ValueError, match="sensor_noise_std"):
        replace(SCENES["pendulum"].physics, sensor_noise_std=-0.1)
    with pytest.raises(ValueError, match="sensor_noise_std"):
        replace(SCENES["pendulum"].physics, sensor_noise_std=float("nan"))


# --------------------------------------------------------------------------- declared but absent
@pytest.mark.parametrize("effect, mjcf_kwargs", [
    ("gravity", {"option": 'gravity="0 0 0"'}),
    ("joint_damping", {}),
    ("dry_friction", {}),
    ("actuator_limits", {"motor": 'ctrlrange="-2 2" ctrllimited="false"'}),
    ("contact", {}),
])
def test_declared_effect_absent_from_the_mjcf_is_an_error(tmp_path, effect, mjcf_kwargs):
    xml = rod_mjcf(tmp_path / "rod.xml", **mjcf_kwargs)
    present = infer_physics(build_model(xml)[0])
    assert not getattr(present, effect)  # the file really lacks it
    with pytest.raises(ValueError, match=effect):
        build_model(xml, replace(present, **{effect: True}))
    with pytest.raises(ValueError, match=effect):
        RigidBodyEnv(xml, physics=replace(present, **{effect: True}))


def test_built_in_scenes_reject_effects_they_do_not_contain():
    for scene, effect in [("pendulum", "joint_damping"), ("pendulum", "dry_friction"),
                          ("spherical_pendulum", "dry_friction"), ("pendulum_damped", "dry_friction")]:
        with pytest.raises(ValueError, match=effect):
            RigidBodyEnv(scene, physics=replace(SCENES[scene].physics, **{effect: True}))


@pytest.mark.parametrize("mjcf_kwargs, message", [
    ({"joint": 'stiffness="3"'}, "springs"),
    ({"joint": 'range="-1 1"'}, "joint limits"),
    ({"extra": '<tendon><fixed name="t"><joint joint="hinge" coef="1"/></fixed></tendon>'}, "tendons"),
    ({"extra": '<equality><joint joint1="hinge"/></equality>'}, "equality"),
])
def test_effects_without_a_declaration_are_an_error(tmp_path, mjcf_kwargs, message):
    """Springs, joint limits, tendons and equality constraints have no ScenePhysics field; they
    would be switched off silently, so a file containing one is refused."""
    xml = rod_mjcf(tmp_path / "rod.xml", **mjcf_kwargs)
    with pytest.raises(ValueError, match=message):
        build_model(xml)


def test_inferred_physics_follows_the_files_own_flags(tmp_path):
    """A user MJCF is simulated as the file would be: its <flag> settings switch effects off."""
    xml = rod_mjcf(tmp_path / "rod.xml", joint='damping="0.1" frictionloss="0.2"',
                   flags='<flag gravity="disable" frictionloss="disable"/>')
    model, physics = build_model(xml)
    assert physics == ScenePhysics(gravity=False, joint_damping=True, dry_friction=False, actuator_limits=True,
                                   contact=False)
    assert model.opt.disableflags == physics.disable_flags()
    # An explicit declaration overrides the file's flags in both directions.
    model, _ = build_model(xml, replace(physics, gravity=True, joint_damping=False))
    assert not model.opt.disableflags & DSBL.mjDSBL_GRAVITY
    assert model.opt.disableflags & DSBL.mjDSBL_DAMPER


# --------------------------------------------------------------------------- learning the damping
def synthetic_damped_data(trajectories: int, steps: int, seed: int) -> Trajectories:
    return synthetic_hinge_data(PENDULUM_DAMPED, trajectories, steps, seed)


def test_training_with_dissipation_recovers_the_damping():
    """On damped data the model with ``−Dω`` fits better than the conservative one, and its D
    along the hinge, after fixing the scale λ on g, is the true 2·0.1 (factor of two: DESIGN.md)."""
    pytest.importorskip("torch")
    from fvin_mpc.core.checkpoint import Checkpoint
    from fvin_mpc.learning.training import TrainSettings, train
    from fvin_mpc.studies.model_quality import compare_components

    data = synthetic_damped_data(trajectories=24, steps=10, seed=0)
    settings = TrainSettings(iterations=80, window=2, learning_rate=3e-2, seed=3, eval_every=80)
    losses, trained = {}, None
    for dissipation in (True, False):
        config = ModelConfig(hidden_width=6, dissipation=dissipation)
        model, report = train(data, config, settings, progress=False)
        losses[dissipation] = report["final_train_loss"]
        if dissipation:
            trained = Checkpoint(config, model.numpy_weights())
    angles = np.linspace(-np.pi, np.pi, 64, endpoint=False)
    axis = np.array([0.0, 1.0, 0.0])
    hinge_quaternions = np.stack([np.cos(angles / 2), 0 * angles, np.sin(angles / 2), 0 * angles], -1)
    components = compare_components(
        trained, PENDULUM_DAMPED, hinge_quaternions, axis, rest=np.array([1.0, 0.0, 0.0, 0.0])
    )
    assert components["lambda"] > 0.0
    assert components["dissipation_axis_true"] == pytest.approx(2.0 * PENDULUM_DAMPED.damping)
    # Initial D is 0.01·I; measured after training (seeds 0/3, 1/4, 2/5 of data/training):
    # D/λ along the hinge 0.20, 0.17, 0.18 (true 0.2) and a 3–7× lower loss than without D.
    d_hinge = components["dissipation_axis"]
    assert 0.5 * 0.2 < d_hinge < 1.5 * 0.2, components
    assert losses[True] < 0.6 * losses[False], losses


def test_a_declared_mass_change_comes_at_its_time_and_reset_undoes_it():
    """``mass_change=(0.1, 2)``: masses and inertias double from the first period at or after 0.1 s (the
    hanging pendulum's constants — subtree mass — recomputed), not before; a reset brings the built plant
    back; ``impulse_at_s`` knocks at its time whether held or not."""
    physics = replace(SCENES["pendulum"].physics, mass_change=(0.1, 2.0), impulse_delta_omega=1.5, impulse_at_s=0.1)
    env = RigidBodyEnv("pendulum", physics=physics)
    built = env.model.body_mass.copy(), env.model.body_inertia.copy(), env.model.body_subtreemass.copy()
    for _ in range(2):
        env.reset(seed=0)
        rates = []
        for _ in range(2):  # the periods from 0 and 0.05 s
            assert not env.mass_changed and not env.knocked
            rates.append(env.step([0.0])[0][5])
        assert rates == [0.0, 0.0]  # hanging at rest
        assert np.array_equal(env.model.body_mass, built[0])
        rate = env.step([0.0])[0][5]  # the period from 0.1 s: changed and knocked at its start
        assert env.mass_changed and env.knocked and abs(rate) == pytest.approx(1.5, rel=0.05)
        assert np.allclose(env.model.body_mass, 2.0 * built[0]) and np.allclose(env.model.body_inertia, 2.0 * built[1])
        assert np.allclose(env.model.body_subtreemass, 2.0 * built[2])
    with pytest.raises(ValueError, match="mass_change"):
        replace(physics, mass_change=(1.0, 0.0))


@pytest.mark.parametrize("shift", [(0.0, 0.0, -0.02), (0.02, 0.0, 0.0)])
def test_a_moved_centre_of_mass_turns_the_craft_about_its_new_centre(shift):
    """A payload that moves the centre (``mass_change`` with a shift) is simulated as the craft compiled with
    that centre: one rotor's thrust turns it by ``J⁻¹ (r × F + yaw)`` about the new centre, and the frame's
    origin accelerates sideways with it (MuJoCo's compiler had made the centred body "simple": changed in place
    it kept a diagonal mass matrix and turned 8 % too slowly about its frame's origin, never sideways)."""
    from fvin_mpc.envs.quadrotor_env import QuadrotorEnv
    from fvin_mpc.envs.scenes import resolve_scene

    physics = replace(resolve_scene("quadrotor").physics, mass_change=(0.0, 1.5, shift))
    env = QuadrotorEnv("quadrotor", physics=physics)
    env.reset(seed=0, options={"hover": True})
    env.step(env.unwrapped.hover_thrust)  # the change comes with the first period
    model = env.unwrapped._model
    assert np.allclose(model.body_ipos[1], shift) and model.body_mass[1] == pytest.approx(0.75)
    data = mujoco.MjData(model)
    data.ctrl[:] = [1.0, 0.0, 0.0, 0.0]
    mujoco.mj_forward(model, data)  # level, at rest, at the origin
    site = data.site_xpos[model.actuator_trnid[0, 0]]
    yaw = model.actuator_gear[0, 5]
    torque = np.cross(site - data.xipos[1], [0.0, 0.0, 1.0]) + [0.0, 0.0, yaw]
    expected = torque / model.body_inertia[1]  # diagonal inertia, the body's axes
    np.testing.assert_allclose(data.qacc[3:6], expected, rtol=1e-9)
    # Newton at the centre: the origin's acceleration is the centre's, F/m, plus α × (origin − centre).
    centre = np.array([0.0, 0.0, 1.0 / 0.75]) + model.opt.gravity
    np.testing.assert_allclose(data.qacc[:3], centre + np.cross(expected, -np.asarray(shift)), rtol=1e-9, atol=1e-12)
    env.close()
