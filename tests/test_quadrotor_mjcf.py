"""Any free-flying craft from its MJCF (docs/flyers.md): the env observes the centre of mass, the closed
form reads any rotor layout or wrench actuators off the model (checked against ``mj_forward`` on
generated crafts), and data come from the MJCF alone (random-excitation bursts)."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from fvin_mpc.core.quadrotor import GeometricController, from_mujoco
from fvin_mpc.envs import QuadrotorEnv
from fvin_mpc.envs.flyer_family import FLYER_RANGES, flyer_scene, write_flyers
from fvin_mpc.learning.free_body_excitation import EXCITATION, collect_excitation

SEEDS = range(12)


def _accelerations(model: mujoco.MjModel, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """MuJoCo's centre-of-mass acceleration (world) and ``ω̇`` (body), and the closed form's, at a random
    tumbling, moving state under random controls within the bounds (fluid drag switched off: the closed
    form says it leaves it out)."""
    rng = np.random.default_rng(seed)
    model.opt.density = model.opt.viscosity = 0.0
    craft = from_mujoco(model, mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, 1))
    data = mujoco.MjData(model)
    quaternion = rng.normal(size=4)
    data.qpos[:] = np.concatenate([rng.normal(size=3), quaternion / np.linalg.norm(quaternion)])
    data.qvel[:] = rng.normal(size=6) * np.array([1, 1, 1, 5, 5, 5])
    data.ctrl[:] = rng.uniform(*model.actuator_ctrlrange.T)
    mujoco.mj_forward(model, data)
    centre, omega, rotation = model.body_ipos[1], data.qvel[3:], data.xmat[1].reshape(3, 3)
    # the free joint's qacc is the body origin's; the centre of mass adds ω̇ × c + ω × (ω × c)
    com = data.qacc[:3] + rotation @ (np.cross(data.qacc[3:], centre) + np.cross(omega, np.cross(omega, centre)))
    inertia, u = np.array(craft.inertia), data.ctrl.copy()
    closed_com = rotation @ np.array(craft.force_map) @ u / craft.mass - np.array([0.0, 0.0, craft.gravity])
    closed_omega = np.linalg.solve(inertia, np.array(craft.torque_map) @ u - np.cross(omega, inertia @ omega))
    return com, data.qacc[3:].copy(), closed_com, closed_omega


@pytest.mark.parametrize("seed", SEEDS)
def test_the_closed_form_accelerates_as_mujoco_on_generated_crafts(seed):
    model = mujoco.MjModel.from_xml_string(flyer_scene(seed)[0])
    com, omega_dot, closed_com, closed_omega = _accelerations(model, seed)
    np.testing.assert_allclose(closed_com, com, atol=1e-9 * (1.0 + np.abs(com).max()))
    np.testing.assert_allclose(closed_omega, omega_dot, atol=1e-9 * (1.0 + np.abs(omega_dot).max()))


def test_the_family_spans_its_ranges():
    facts = [flyer_scene(seed)[1] for seed in range(60)]
    low, high = FLYER_RANGES["mass_kg"]
    assert all(low <= f["mass_kg"] <= high * 1.001 for f in facts)
    assert {f["rotors"] for f in facts if f["actuation"] == "rotors"} == {4, 6, 8}
    assert {f["actuation"] for f in facts} == {"rotors", "wrench"}
    assert {f["fluid_drag"] for f in facts} == {True, False}
    assert all(f["com_offset_arm_fraction"] <= 1.0 / 3.0 + 1e-9 for f in facts)
    assert max(f["com_offset_arm_fraction"] for f in facts) > 0.2
    assert max(f["inertial_frame_rotation_deg"] for f in facts) > 10.0
    assert all(1e-3 <= f["timestep_s"] <= 1e-2 for f in facts)
    assert flyer_scene(3) == flyer_scene(3)


def test_what_the_closed_form_leaves_out_is_said():
    mjcf = next(flyer_scene(seed)[0] for seed in range(40) if flyer_scene(seed)[1]["fluid_drag"])
    model = mujoco.MjModel.from_xml_string(mjcf)
    assert any("fluid drag" in item for item in from_mujoco(model, "flyer").unmodelled)
    model.opt.density = model.opt.viscosity = 0.0
    assert from_mujoco(model, "flyer").unmodelled == ()


@pytest.fixture(scope="module")
def crafts(tmp_path_factory):
    """A rotor craft with its centre of mass off the body origin and a wrench-actuated one, as files."""
    folder = tmp_path_factory.mktemp("flyers")
    facts = {seed: flyer_scene(seed)[1] for seed in range(40)}

    def hovers(seed: int) -> bool:  # level hover within the thrust bounds (the closed form's least squares)
        model = mujoco.MjModel.from_xml_string(flyer_scene(seed)[0])
        return bool(np.all(np.array(from_mujoco(model, "flyer").hover_controls) >= 0.0))

    rotors = next(s for s, f in facts.items() if f["actuation"] == "rotors" and f["com_offset_arm_fraction"] > 0.2
                  and f["max_tilt_deg"] > 1.0 and hovers(s))
    wrench = next(s for s, f in facts.items() if f["actuation"] == "wrench")
    return write_flyers([rotors, wrench], folder)


def test_the_env_observes_the_centre_of_mass(crafts):
    for path in crafts:
        env = QuadrotorEnv(path)
        state = env.reset(seed=0)[0]
        qpos, qvel = env.joint_state(state)
        np.testing.assert_allclose(qpos, env.data.qpos, atol=1e-12)
        np.testing.assert_allclose(qvel, env.data.qvel, atol=1e-12)
        # v is the derivative of x: a finite difference over one MuJoCo step without controls
        h = env.model.opt.timestep
        before = env.state()
        env.step(np.zeros(env.model.nu), substeps=1)
        after = env.state()
        np.testing.assert_allclose((after[:3] - before[:3]) / h, 0.5 * (before[7:10] + after[7:10]),
                                   atol=0.05 * (1.0 + np.abs(before[7:10]).max()))
        # the hover controls hold the level craft still at the hover point
        env.reset(options={"hover": True})
        for _ in range(10):
            state = env.step(env.hover_thrust)[0]
        np.testing.assert_allclose(state[:3], env.hover_point, atol=1e-9)
        np.testing.assert_allclose(state[7:], 0.0, atol=1e-9)
        np.testing.assert_allclose(env.hover_thrust, from_mujoco(env.model, env.body_name).hover_controls, atol=1e-9)


def test_the_control_period_follows_the_craft(crafts):
    for path in crafts:
        env = QuadrotorEnv(path)
        scales = env.scales
        assert env.dt <= 0.3 * scales.attitude_time + 1e-12
        assert env.dt > 0.3 * scales.attitude_time - env.model.opt.timestep or env.frame_skip == 1
    assert QuadrotorEnv("quadrotor").dt == 0.02


def test_excitation_data_need_only_the_mjcf(crafts):
    for path in crafts:
        data = collect_excitation(str(path), trajectories=20, steps=10, seed=3, progress=False)
        assert data.metadata["collector"] == EXCITATION and data.metadata["transitions"] == 200
        assert data.state.shape == (20, 11, 13) and np.all(np.isfinite(data.state))
        again = collect_excitation(str(path), trajectories=20, steps=10, seed=3, progress=False)
        np.testing.assert_array_equal(again.state, data.state)
        coverage = data.metadata["coverage"]
        assert coverage["max_tilt_deg"] > 120.0 and coverage["max_abs_omega"] > 5.0


def test_the_geometric_controller_allocates_any_layout(crafts):
    """Its least-squares allocation gives the commanded thrust and roll/pitch torque when nothing saturates."""
    for path in crafts:
        env = QuadrotorEnv(path)
        craft = from_mujoco(env.model, env.body_name)
        controller = GeometricController(craft)
        u = controller(env.goal_state, env.hover_point)
        np.testing.assert_allclose(controller.allocation() @ u,
                                   [craft.mass * craft.gravity, 0.0, 0.0, 0.0], atol=1e-6 * craft.mass * 10)


def test_the_tuned_craft_keeps_its_control_weight_and_recovery_time():
    from fvin_mpc.control.flight import (
        TUNED_ANGULAR_CONTROL,
        TUNED_ATTITUDE_TIME,
        TUNED_CONTROL_WEIGHT,
        TUNED_LINEAR_CONTROL,
        TUNED_RECOVERY_S,
        TUNED_YAW_TIME,
        recovery_duration,
        scaled_control_weight,
    )

    scales = QuadrotorEnv("quadrotor").scales
    assert scales.angular_control == pytest.approx(TUNED_ANGULAR_CONTROL, rel=1e-12)
    assert scales.linear_control == pytest.approx(TUNED_LINEAR_CONTROL, rel=1e-12)
    assert scales.attitude_time == pytest.approx(TUNED_ATTITUDE_TIME, rel=1e-12)
    assert scales.yaw_time == pytest.approx(TUNED_YAW_TIME, rel=1e-7)
    assert not any(scales.moment_actuators)
    assert scaled_control_weight(scales) == pytest.approx(TUNED_CONTROL_WEIGHT, rel=1e-12)
    assert recovery_duration(scales) == TUNED_RECOVERY_S


def test_a_wrench_craft_weighs_its_thrust_and_moments_apart(crafts):
    """One weight for a thrust in N and moments in N·m froze the thrust at hover (module docstring)."""
    from fvin_mpc.control.flight import TUNED_CONTROL_WEIGHT, TUNED_LINEAR_CONTROL, scaled_control_weight

    scales = QuadrotorEnv(crafts[1]).scales
    assert scales.moment_actuators == (False, True, True, True)
    # the thrust: the same cost per m/s² as the tuned craft's, about ``m`` newtons of thrust per m/s² (plus
    # the moments that cancel its lever about the centre of mass off the thrust site)
    weights = scaled_control_weight(scales)
    assert scales.linear_control == pytest.approx(scales.mass, rel=0.01)
    assert weights[0] == pytest.approx(TUNED_CONTROL_WEIGHT * (TUNED_LINEAR_CONTROL / scales.linear_control) ** 2,
                                       rel=1e-12)
    assert min(weights[1:]) > 100.0 * weights[0]
    assert isinstance(scaled_control_weight(QuadrotorEnv(crafts[0]).scales), float)


def test_a_slow_yawing_craft_gets_a_longer_recovery(crafts):
    from fvin_mpc.control.flight import TUNED_RECOVERY_S, TUNED_YAW_TIME, recovery_duration

    for path in crafts:
        scales = QuadrotorEnv(path).scales
        assert recovery_duration(scales) >= TUNED_RECOVERY_S
        assert recovery_duration(scales) == pytest.approx(
            max(TUNED_RECOVERY_S, TUNED_RECOVERY_S * scales.yaw_time / TUNED_YAW_TIME,
                TUNED_RECOVERY_S * scales.attitude_time / 0.06946194659107466), abs=0.05)


def test_the_figure_eight_scales_with_the_craft(crafts):
    from fvin_mpc.studies.flight_report import figure_eight, make_env

    built_in = figure_eight(make_env())
    assert (built_in.amplitude, built_in.period, built_in.ramp_s) == (0.5, 3.0, 1.0)  # the tuned task, unchanged
    for path in crafts:
        env = make_env(scene=path)
        loop = figure_eight(env)
        scales = env.unwrapped.scales
        assert loop.amplitude == pytest.approx(0.5 / 0.17 * scales.arm, rel=0.05)
        _, _, acceleration = loop.trajectory(np.linspace(loop.ramp_s, loop.ramp_s + loop.period, 400))
        lateral = 9.81 * np.sqrt(scales.thrust_to_weight**2 - 1.0)
        assert 0.2 < np.linalg.norm(acceleration, axis=1).max() / lateral < 0.35


@pytest.mark.slow
def test_fly_takes_a_generated_craft(crafts, tmp_path):
    """``fly --scene X.xml`` end to end with the closed form (a CasADi build: slow)."""
    import json

    from fvin_mpc.fly import main

    out = tmp_path / "fly.json"
    assert main(["--scene", str(crafts[0]), "--model", "closed-form", "--episodes", "2", "--latency", "none",
                 "--quiet", "--json", str(out)]) == 0
    summary = json.loads(out.read_text())["summary"]
    assert summary["recovered_count"] == 2 and summary["failures"] == 0


def test_collect_records_a_craft_by_path_without_the_closed_form(crafts, tmp_path, monkeypatch):
    """``collect --scene X.xml`` on a free body: random-excitation bursts, the closed form never read."""
    import fvin_mpc.core.quadrotor as closed_form
    from fvin_mpc import collect
    from fvin_mpc.core.data import load_data
    from fvin_mpc.learning import collection

    def refuse(*args, **kwargs):
        raise AssertionError("collection read the closed form")

    monkeypatch.setattr(closed_form, "from_mujoco", refuse)
    monkeypatch.setattr(collection, "from_mujoco", refuse)  # the stabilized-flight pilot's own import
    out = tmp_path / "craft.npz"
    assert collect.main(["--scene", str(crafts[1]), "--trajectories", "4", "--steps", "5", "--out", str(out),
                         "--quiet"]) == 0
    data = load_data(out)
    assert data.metadata["collector"] == EXCITATION and data.state.shape == (4, 6, 13)


def test_a_craft_whose_roll_and_yaw_move_together_is_refused_with_the_reason(crafts, tmp_path):
    """Adjacent rotors spinning alike (Menagerie's skydio_x2 before its pull request #220): roll and yaw
    come from one combination of the thrusts; the env says so in one line instead of flying it."""
    from fvin_mpc.core.errors import SceneError

    square = """<mujoco><option timestep="0.005"/><worldbody><body name="craft" pos="0 0 1"><freejoint/>
      <geom type="box" size="0.1 0.1 0.02" mass="1"/>
      <site name="a" pos="-0.15 -0.15 0"/><site name="b" pos="-0.15 0.15 0"/>
      <site name="c" pos="0.15 0.15 0"/><site name="d" pos="0.15 -0.15 0"/></body></worldbody>
      <actuator><motor site="a" gear="0 0 1 0 0 -0.02" ctrlrange="0 10"/>
      <motor site="b" gear="0 0 1 0 0 {b}" ctrlrange="0 10"/><motor site="c" gear="0 0 1 0 0 {c}" ctrlrange="0 10"/>
      <motor site="d" gear="0 0 1 0 0 {d}" ctrlrange="0 10"/>
      </actuator></mujoco>"""
    tied = tmp_path / "tied.xml"
    tied.write_text(square.format(b="0.02", c="0.02", d="-0.02"))
    with pytest.raises(SceneError, match="torque about body x and the torque about body z move together"):
        QuadrotorEnv(tied)
    crossed = tmp_path / "crossed.xml"
    crossed.write_text(square.format(b="0.02", c="-0.02", d="0.02"))
    assert QuadrotorEnv(crossed).scales.thrust_to_weight > 1.0
