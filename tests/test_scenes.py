"""A scene is one declaration: the task read off the MJCF, settings from its scales, one path for
built-in scenes and user files alike — and a regression test for each bug the duplication bred."""

import json
import subprocess
import sys
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import pytest
from helpers import assert_same_rotation, hinge_quaternion

from fvin_mpc.control.mpc import COLD_STARTS, MPCSettings, RTIOptions
from fvin_mpc.control.scene import (
    DEFAULT_TERMINAL_ENERGY_WEIGHT,
    MAX_DEFAULT_HORIZON,
    REFERENCE_SCALES,
    RESTART_SPEED_FRACTION,
    default_mpc_settings,
    scene_env,
    scene_mpc_settings,
    scene_scales,
)
from fvin_mpc.core.goals import HOVER, UPRIGHT
from fvin_mpc.core.space import S3
from fvin_mpc.envs import SCENES, RigidBodyEnv
from fvin_mpc.envs.scenes import SCENE_DIR, resolve_scene

WEAK_PENDULUM = Path(__file__).resolve().parent / "data" / "weak_pendulum.xml"


# ---------------------------------------------------------------------- the task, read off the potential
@pytest.mark.parametrize("scene", sorted(SCENES))
def test_built_in_tasks_are_the_potentials_extrema(scene):
    """Upright (rotation by π about y) is the maximum of U, hanging (identity) the minimum."""
    env = RigidBodyEnv(scene)
    assert_same_rotation(env.goal, np.array([0.0, 0.0, 1.0, 0.0]), 1e-15)
    assert_same_rotation(env.rest, np.array([1.0, 0.0, 0.0, 0.0]), 1e-15)
    np.testing.assert_allclose(env.reset()[0], [1, 0, 0, 0, 0, 0, 0], atol=1e-15)


def test_a_pendulum_written_upright_at_qpos_zero_gets_its_task_from_the_potential():
    """Regression: such an MJCF used to get goal = rest = identity and start upright."""
    env = RigidBodyEnv(str(WEAK_PENDULUM))
    assert env.scene_spec.name == "weak_pendulum"
    assert_same_rotation(env.goal, np.array([1.0, 0.0, 0.0, 0.0]), 1e-15)  # qpos = 0 is upright
    assert_same_rotation(env.rest, hinge_quaternion(np.pi), 1e-15)
    observation, info = env.reset()
    assert_same_rotation(observation[:4], hinge_quaternion(np.pi), 1e-15)  # episodes start hanging
    assert info["angle_from_goal"] == pytest.approx(np.pi)
    assert info["energy"] == pytest.approx(-5.0)  # the potential's minimum: m g z = 10 · (−0.5)
    assert env.physics.joint_damping  # what the file simulates, without a declaration
    # Its period follows its speed scale (√60 rad/s, the pendulum's): 0.05 s × √60 / ω_s rounded to the
    # file's 20 ms timestep, so 40 ms (the same turn per step as the pendulum scene's 50 ms).
    assert env.speed_scale == pytest.approx(60.0**0.5) and env.dt == pytest.approx(0.04)


def test_the_task_of_a_ball_joint_puts_the_centre_of_mass_above_and_below_the_pivot():
    env = RigidBodyEnv("spherical_pendulum")
    for orientation, sign in ((env.goal, 1.0), (env.rest, -1.0)):
        env.set_state(orientation, np.zeros(3))
        reach = env.data.xipos[env.model.body(env.body_name).id] - env.data.xanchor[0]
        np.testing.assert_allclose(reach / np.linalg.norm(reach), [0.0, 0.0, sign], atol=1e-12)


def test_a_scene_without_gravity_has_no_task_to_read_off(tmp_path):
    xml = tmp_path / "floating.xml"
    xml.write_text(WEAK_PENDULUM.read_text().replace('gravity="0 0 -10"', 'gravity="0 0 0"'))
    with pytest.raises(ValueError, match="declare goal and rest"):
        RigidBodyEnv(str(xml))


# ---------------------------------------------------------------------- one declaration per scene
def test_a_path_to_a_built_in_mjcf_is_that_scene():
    """Regression: ``--scene envs/scenes/pendulum.xml`` silently got the default MPC settings."""
    for name, spec in SCENES.items():
        assert resolve_scene(SCENE_DIR / f"{name}.xml") is spec
        assert resolve_scene(str(SCENE_DIR / f"{name}.xml")) is spec
    by_path = scene_env(str(SCENE_DIR / "pendulum_damped.xml"), true_model=True)
    by_name = scene_env("pendulum_damped", true_model=True)
    assert scene_mpc_settings(by_path) == scene_mpc_settings(by_name)
    assert scene_mpc_settings(by_name).horizon == 50  # the scene's declared horizon


def test_a_user_mjcf_is_declared_by_its_path_alone():
    spec = resolve_scene(str(WEAK_PENDULUM))
    assert (spec.name, spec.xml_path, spec.default_checkpoint) == ("weak_pendulum", WEAK_PENDULUM,
                                                                   "weak_pendulum_sign-invariant")
    derived = ("name", "xml_path", "space", "goal_set")
    assert all(getattr(spec, f.name) in (None, {}) for f in fields(spec) if f.name not in derived)
    assert spec.space is S3 and spec.goal_set is UPRIGHT  # read off the file: a hinge, not a free joint
    with pytest.raises(ValueError, match="unknown scene"):
        resolve_scene("no_such_scene")


def test_a_scene_declares_its_goal_set_and_a_free_joint_hovers():
    """The goal's kind is the scene's (never a flag on the space): the built-in pivots hold upright, the
    quadrotor and any MJCF on a free joint hover, and a declaration may say otherwise."""
    assert all(resolve_scene(name).goal_set is UPRIGHT for name in SCENES)
    assert resolve_scene("quadrotor").goal_set is HOVER
    assert resolve_scene(str(resolve_scene("quadrotor").xml_path)).goal_set is HOVER
    spec = resolve_scene("pendulum")
    assert replace(spec, goal_set=HOVER).goal_set is HOVER


def test_the_control_period_follows_the_checkpoint_unless_given():
    """Regression: a checkpoint trained at 0.02 s on the pendulum stopped with 'differs from the
    scene's control period 0.05 s'; the env now steps at the checkpoint's period."""
    assert scene_env("pendulum", "pendulum-h0.02_sign-invariant").dt == pytest.approx(0.02)
    assert scene_env("pendulum", "pendulum_sign-invariant").dt == pytest.approx(0.05)
    assert scene_env("pendulum", "pendulum-h0.02_sign-invariant", control_period=0.05).dt == pytest.approx(0.05)
    assert scene_env("pendulum", true_model=True).dt == pytest.approx(0.05)


# ---------------------------------------------------------------------- defaults from the scene's scales
def test_the_reference_scales_give_the_tuned_numbers():
    """On the pendulum's scales the derived settings are MPCSettings' own numbers, plus the
    terminal energy cost and the multi-start the evaluation reports."""
    derived = default_mpc_settings(REFERENCE_SCALES)
    # and the real-time iteration's restart, which has no tuned number of its own: a fraction of ω_s
    assert derived.rti.restart_speed == pytest.approx(RESTART_SPEED_FRACTION * REFERENCE_SCALES.speed, rel=1e-9)
    assert replace(derived, rti=RTIOptions()) == replace(
        MPCSettings(), terminal_energy_weight=DEFAULT_TERMINAL_ENERGY_WEIGHT, cold_starts=COLD_STARTS)
    scales = scene_scales(RigidBodyEnv("pendulum"))
    assert (scales.energy_span, scales.speed**2, scales.torque, scales.step_size) == pytest.approx(
        (10.0, 60.0, 2.0, 0.05)
    )
    assert scene_mpc_settings(RigidBodyEnv("pendulum")) == derived


def test_settings_scale_with_the_step_speed_and_torque():
    """Half the step: twice the stages at half the weight each, the same horizon in seconds; a
    weaker motor: control weight ∝ 1/u_max²; a slower body: |ω|² weights ∝ 1/ω_s², longer horizon."""
    base = default_mpc_settings(REFERENCE_SCALES)
    fine = default_mpc_settings(replace(REFERENCE_SCALES, step_size=0.025))
    assert fine.horizon == 2 * base.horizon
    assert fine.orientation_weight == pytest.approx(base.orientation_weight / 2)
    assert fine.omega_weight == pytest.approx(base.omega_weight / 2)
    assert fine.terminal_omega_weight == base.terminal_omega_weight
    weak = default_mpc_settings(replace(REFERENCE_SCALES, torque=1.0))
    assert weak.control_weight == pytest.approx(4 * base.control_weight)
    slow = default_mpc_settings(replace(REFERENCE_SCALES, speed=REFERENCE_SCALES.speed / 2))
    assert slow.omega_weight == pytest.approx(4 * base.omega_weight)
    # A forced fine period does not explode the horizon: past MAX_DEFAULT_HORIZON steps the terminal
    # energy term does the look-ahead.
    assert default_mpc_settings(replace(REFERENCE_SCALES, step_size=0.005)).horizon == MAX_DEFAULT_HORIZON
    assert slow.horizon == 2 * base.horizon


def test_the_weak_pendulums_settings_and_cli_overrides():
    env = scene_env(str(WEAK_PENDULUM), true_model=True)
    scales = scene_scales(env)
    assert (scales.energy_span, scales.torque, scales.step_size) == pytest.approx((10.0, 1.0, 0.04))
    settings = scene_mpc_settings(env)
    assert settings.horizon == 37 and settings.terminal_energy_weight == DEFAULT_TERMINAL_ENERGY_WEIGHT
    assert scene_mpc_settings(env, omega_weight=1e-4, horizon=None).omega_weight == 1e-4
    with pytest.raises(ValueError, match="unknown MPC settings"):
        scene_mpc_settings(env, omega_wieght=1.0)


def test_the_weak_pendulum_swings_up_with_default_settings(tmp_path):
    """The closed-form model of a pendulum written the other way round, with damping and a motor a
    fifth of the gravity torque (several pumps), swings up and holds with no tuning at all — within
    the episode length swingup derives from the scene (no --duration either)."""
    from fvin_mpc import swingup

    out = tmp_path / "weak.json"
    assert swingup.main(["--scene", str(WEAK_PENDULUM), "--true-model", "--plot", "", "--quiet",
                         "--json", str(out)]) == 0
    summary = json.loads(out.read_text())
    assert summary["swung_up"], summary
    derived = swingup.default_duration(scene_scales(RigidBodyEnv(str(WEAK_PENDULUM))))
    assert derived > 10.0 and summary["duration_s"] == pytest.approx(derived, abs=0.02)
    assert summary["control_period_s"] == pytest.approx(0.04) and summary["horizon"] == 37
    assert summary["max_abs_torque"] <= 1.0


# ---------------------------------------------------------------------- regressions
def test_evaluate_accepts_an_explicit_checkpoint_whose_name_has_dots(tmp_path):
    """Regression: ``Path.with_suffix`` cut 'pendulum-h0.02_x' to 'pendulum-h0' and refused it."""
    from fvin_mpc.core.checkpoint import load_checkpoint, save_checkpoint
    from fvin_mpc.studies import evaluation

    shipped = load_checkpoint("pendulum-h0.02_sign-invariant")
    stem = save_checkpoint(tmp_path / "pendulum-h0.02_copy", shipped.config, shipped.weights, scene="pendulum")
    config = evaluation.EvaluationConfig(checkpoint=str(stem), controllers=("mpc-learned",), episodes=1)
    evaluation._check_checkpoint(config)  # no FileNotFoundError
    assert evaluation.make_env(config).unwrapped.dt == pytest.approx(0.02)


def test_a_corrupted_checkpoint_is_not_reported_missing(tmp_path):
    """Regression: the studies' checkpoint_or_none turned a corrupted file into 'not found'."""
    from benchmarks.common import checkpoint_or_none
    from fvin_mpc.core.checkpoint import CheckpointError, load_checkpoint, save_checkpoint

    shipped = load_checkpoint("pendulum_sign-invariant")
    stem = save_checkpoint(tmp_path / "model", shipped.config, shipped.weights)
    assert checkpoint_or_none(str(stem)) is not None
    assert checkpoint_or_none(str(tmp_path / "absent")) is None
    weights = stem.parent / (stem.name + ".safetensors")
    weights.write_bytes(weights.read_bytes()[:-8] + b"\x00" * 8)
    with pytest.raises(CheckpointError):
        checkpoint_or_none(str(stem))


def test_quality_gives_a_ball_joint_checkpoint_the_3d_report_not_the_planar_one(monkeypatch, tmp_path, capsys):
    """Regression: the planar report compared every checkpoint with the rod about y. ``quality`` (which
    absorbed the former ``inertia`` command) sends ball-joint checkpoints to the 3-D report."""
    from fvin_mpc import quality

    calls = []
    monkeypatch.setattr(quality, "load_data", lambda path: calls.append(("data", str(path))) or "held-out")
    monkeypatch.setattr(quality, "report", lambda name, data, horizon, samples, energy_steps, seed:
                        calls.append(("report", name, data, horizon, energy_steps)) or {"rollout": {}})
    monkeypatch.setattr(quality, "hinge_report", lambda *args: pytest.fail("the planar report ran"))
    assert quality.main(["--checkpoint", "spherical_pendulum_sign-invariant", "--json", str(tmp_path / "q.json")]) == 0
    assert calls == [("data", "data/spherical_pendulum_heldout.npz"),
                     ("report", "spherical_pendulum_sign-invariant", "held-out", 20, 400)]
    with pytest.raises(SystemExit) as exit_info:  # the planar report takes one checkpoint
        quality.main(["--checkpoint", "pendulum_sign-invariant", "pendulum_fixed-inertia"])
    assert exit_info.value.code == 2 and "one --checkpoint" in capsys.readouterr().err


def test_envs_installs_inside_the_package_not_as_a_top_level_envs(tmp_path):
    """Regression: ``pip install -e .`` installed a top-level package called ``envs``."""
    import importlib.metadata as metadata

    top_level = {name for name, dists in metadata.packages_distributions().items() if "fvin_mpc" in dists}
    assert top_level == {"fvin_mpc"}
    probe = "import importlib.util, sys; sys.exit(importlib.util.find_spec('envs') is not None)"
    assert subprocess.run([sys.executable, "-c", probe], cwd=tmp_path).returncode == 0
    import gymnasium

    assert gymnasium.spec("fvin_mpc/Pendulum-v0").entry_point.startswith("fvin_mpc.envs.")


# ---------------------------------------------------------------------- the whole pipeline, from the CLIs alone
def test_a_user_mjcf_goes_through_collect_train_swingup_with_default_settings(tmp_path, capsys):
    """A small, fast version of docs/custom_scene.md: nothing but the MJCF's physics is declared;
    collect, train and swingup agree on the control period, the task and the dissipation."""
    from fvin_mpc import collect, swingup, train
    from fvin_mpc.core.checkpoint import load_checkpoint
    from fvin_mpc.core.data import load_data

    data_path, stem, summary_path = tmp_path / "weak.npz", tmp_path / "weak_model", tmp_path / "run.json"
    assert collect.main(["--scene", str(WEAK_PENDULUM), "--trajectories", "12", "--steps", "8", "--out",
                         str(data_path), "--quiet"]) == 0
    data = load_data(data_path)
    assert data.control_period == pytest.approx(0.04)  # the scene's own period (its speed scale)
    assert train.main(["--data", str(data_path), "--out", str(stem), "--iterations", "2", "--quiet"]) == 0
    checkpoint = load_checkpoint(stem)
    assert checkpoint.config.step_size == pytest.approx(0.04)
    assert checkpoint.config.dissipation  # the scene's joint damping switched it on by default
    capsys.readouterr()
    assert swingup.main(["--scene", str(WEAK_PENDULUM), "--checkpoint", str(stem), "--duration", "0.1",
                         "--horizon", "5", "--plot", "", "--quiet", "--json", str(summary_path)]) == 0
    summary = json.loads(summary_path.read_text())
    assert summary["control_period_s"] == pytest.approx(0.04)
    assert summary["terminal_energy_weight"] == DEFAULT_TERMINAL_ENERGY_WEIGHT
    assert tuple(summary["cold_starts"]) == COLD_STARTS



@pytest.mark.slow
def test_the_shipped_weak_pendulum_model_swings_it_up(tmp_path):
    """docs/custom_scene.md's learned-model run: the checkpoint trained by the default pipeline
    (collect → train) swings the weak pendulum up from rest with default settings. A missing
    shipped checkpoint is a failure, not a skip."""
    from fvin_mpc import swingup

    out = tmp_path / "learned.json"
    assert swingup.main(["--scene", str(WEAK_PENDULUM), "--duration", "10", "--plot", "", "--quiet",
                         "--json", str(out)]) == 0
    summary = json.loads(out.read_text())
    assert summary["model"] == "weak_pendulum_sign-invariant"
    assert summary["swung_up"] and summary["time_to_upright_s"] < 8.0, summary


from fvin_mpc.core.errors import SceneError  # noqa: E402


def _fake_menagerie(monkeypatch, tmp_path, fetch_error=None):
    """A stand-in for the optional ``mujoco-menagerie`` package (it downloads each robot on first use)."""
    import types

    xml = tmp_path / "craft.xml"
    xml.write_text('<mujoco><worldbody><body name="craft" pos="0 0 1"><freejoint/><geom type="sphere" size="0.1"/>'
                   '</body></worldbody></mujoco>')

    class Robot:
        default_model = "craft"

        def xml(self, entry=None):
            if fetch_error is not None:
                raise fetch_error
            assert entry == "craft"  # the robot's own MJCF, not its scene with a floor
            return xml

    module = types.SimpleNamespace(names=lambda: ["some_drone"], get=lambda name: Robot())
    monkeypatch.setitem(sys.modules, "mujoco_menagerie", module)
    return xml


def test_a_menagerie_name_is_its_robot_s_mjcf(monkeypatch, tmp_path):
    from fvin_mpc.core.space import R3S3
    from fvin_mpc.envs.scenes import resolve_scene

    xml = _fake_menagerie(monkeypatch, tmp_path)
    spec = resolve_scene("some_drone")
    assert (spec.name, spec.xml_path, spec.space) == ("some_drone", xml, R3S3)
    with pytest.raises(SceneError, match="MuJoCo Menagerie robot"):
        resolve_scene("no_such_drone")


def test_a_menagerie_name_says_what_went_wrong_in_one_line(monkeypatch, tmp_path):
    from fvin_mpc.envs.scenes import resolve_scene

    _fake_menagerie(monkeypatch, tmp_path, fetch_error=OSError("no network\nsecond line"))
    with pytest.raises(SceneError, match=r"^Menagerie robot 'some_drone' could not be fetched: no network$"):
        resolve_scene("some_drone")
    monkeypatch.setitem(sys.modules, "mujoco_menagerie", None)  # not installed: import fails
    with pytest.raises(SceneError, match=r"fvin_mpc\[menagerie\]"):
        resolve_scene("some_drone")
