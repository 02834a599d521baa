"""The C controller (``python -m fvin_mpc.export --controller``, :mod:`fvin_mpc.control.c_controller`)
computes the Python :class:`~fvin_mpc.control.rti.RealTimeMPC`'s controls: whole closed-loop episodes in
MuJoCo, the library built with the system compiler and driven through ``ctypes``, the controls equal to
1e-9 in the waiting mode and with a fixed latency (deterministic; a measured latency differs by the
loops' timings, which is the point of the C loop).

The Python loop's wall-clock budgets (``RTIOptions.cold_budget_s``, ``budget_s``) are set so that they do
not bind: the C loop is bounded by iteration counts only, and the two agree where the Python loop
finishes its counts — on a loaded machine its budgets would otherwise cut it short at random. Every
other setting is the scene's default: multi-start cold starts, the disturbance estimate, implicit
dynamics on the pendulum, three iterations per period on the ball joint.

The default suite builds one small case (the closed-form pendulum); the others are ``slow``.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess

import numpy as np
import pytest

from fvin_mpc.control.c_controller import ControllerNotExportable, CRealTimeMPC
from fvin_mpc.control.closed_loop import episode_metrics, run_episode
from fvin_mpc.control.model_export import CompileCount
from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings

COMPILER = os.environ.get("CC", "cc")
pytestmark = pytest.mark.skipif(shutil.which(COMPILER) is None,
                                reason=f"no C compiler {COMPILER!r} on PATH: the C controller cannot be built")

#: Wall-clock budgets that never bind (s): the C loop is bounded by counts, so is the Python loop then.
UNBOUNDED = {"cold_budget_s": 600.0, "budget_s": 600.0}


def pendulum_pair(scene: str, true_model: bool, **overrides):
    env = scene_env(scene, true_model=true_model)
    model = scene_model(env, true_model=true_model)
    python = scene_mpc(env, model, scene_mpc_settings(env, solver="rti", **overrides).updated(rti=UNBOUNDED))
    return env, python, CRealTimeMPC(python)


def quadrotor_pair(true_model: bool):
    from fvin_mpc.control.flight import quadrotor_model, quadrotor_mpc, quadrotor_mpc_settings
    from fvin_mpc.envs import QuadrotorEnv
    from fvin_mpc.envs.scenes import resolve_scene

    env = QuadrotorEnv(resolve_scene("quadrotor"))
    settings = quadrotor_mpc_settings().updated(rti=UNBOUNDED)
    python = quadrotor_mpc(env, quadrotor_model(env, true_model=true_model), settings)
    return env, python, CRealTimeMPC(python)


def assert_same_closed_loops(env, python, c_loop, duration_s: float, latency, **episode):
    """Both loops over one episode: controls to 1e-9, the same fallbacks, the same outcome and cost."""
    python_episode, _ = run_episode(env, python, duration_s, latency=latency, **episode)
    c_episode, _ = run_episode(env, c_loop, duration_s, latency=latency, **episode)
    assert c_episode.u.shape == python_episode.u.shape
    np.testing.assert_allclose(c_episode.u, python_episode.u, rtol=0.0, atol=1e-9)
    assert c_episode.fallback == python_episode.fallback
    assert [i.get("cold_start") for i in c_episode.controller_info] == \
        [i.get("cold_start") for i in python_episode.controller_info]
    python_metrics, c_metrics = episode_metrics(python_episode), episode_metrics(c_episode)
    assert c_metrics["success"] == python_metrics["success"]
    assert c_metrics["accumulated_cost"] == pytest.approx(python_metrics["accumulated_cost"], rel=1e-6)
    return python_episode, c_episode


@pytest.fixture(scope="module")
def closed_form_pendulum():
    return pendulum_pair("pendulum", true_model=True)


def test_closed_form_pendulum_c_loop_equals_python_loop(closed_form_pendulum):
    env, python, c_loop = closed_form_pendulum
    _, c_episode = assert_same_closed_loops(env, python, c_loop, 4.0, "none", seed=0)
    assert episode_metrics(c_episode)["success"], "the swing-up must reach the top: the comparison covers the catch"
    # the estimate was active near the top, so the comparison covers it too
    disturbances = np.array([i["disturbance"] for i in c_episode.controller_info])
    assert np.abs(disturbances).max() > 0.0
    assert_same_closed_loops(env, python, c_loop, 2.0, 0.012, seed=3)
    counters = c_loop.counters()
    assert counters["cold_calls"] == 2 and counters["calls"] == counters["prepares"] > 100


def test_skipped_observations_reach_the_c_loop_as_a_jump_of_its_clock(closed_form_pendulum):
    """A latency over the period: the controller is busy at the next instant, that observation is lost,
    and the clock jump drops the one-step prediction from the disturbance estimate in both loops."""
    env, python, c_loop = closed_form_pendulum
    python_episode, _ = assert_same_closed_loops(env, python, c_loop, 2.0, 0.06, seed=5)
    assert python_episode.skipped > 0


def test_the_c_loop_refuses_a_state_that_is_not_one(closed_form_pendulum):
    _, _, c_loop = closed_form_pendulum
    with pytest.raises(ValueError, match="bad-state"):
        c_loop.feedback(np.array([2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]))
    assert c_loop.counters()["bad_states"] == 1


class ChangesParameters:
    """A controller told new model parameters after its ``at``-th call, between the control and the
    preparation — where an online adaptation would (docs/adaptation.md)."""

    def __init__(self, controller, at: int, **blocks):
        self.controller, self.at, self.blocks = controller, at, blocks
        self.defaults = controller.parameters

    def reset(self):
        self.calls = 0
        self.controller.set_parameters(self.defaults)
        self.controller.reset()

    def __call__(self, x):
        result = self.controller(x)
        self.calls += 1
        if self.calls == self.at:
            self.controller.set_parameters(**self.blocks)
        return result

    def prepare(self):
        self.controller.prepare()

    def set_time(self, t):
        self.controller.set_time(t)


def test_default_model_parameters_leave_the_controls_as_they_were(closed_form_pendulum):
    """The parameters as an input of the compiled functions (the default) against the constants baked in
    (before they were inputs): the same controls to rounding over a whole swing-up."""
    env, python, _ = closed_form_pendulum
    constants = scene_mpc(env, python.model, python.settings.updated(rti={"model_parameters": False}))
    baked, _ = run_episode(env, constants, 4.0, seed=0)
    inputs, _ = run_episode(env, python, 4.0, seed=0)
    np.testing.assert_allclose(inputs.u, baked.u, rtol=0.0, atol=1e-12)
    with pytest.raises(ValueError, match="baked in"):
        constants.set_parameters(gain_scale=[0.5])


def test_changed_model_parameters_reach_both_loops_without_recompiling(closed_form_pendulum):
    """New gains and physical values mid-episode: the Python and the C loop agree to 1e-9, the controls
    differ from the unchanged model's from the change on, and nothing is compiled."""
    env, python, c_loop = closed_form_pendulum
    unchanged, _ = run_episode(env, python, 3.0, seed=2)
    compilations = (CompileCount.calls, CompileCount.compiler_runs)
    blocks = {"gain_scale": [0.7], "mass_gravity": 9.0}
    python_episode, c_episode = assert_same_closed_loops(env, ChangesParameters(python, 10, **blocks),
                                                         ChangesParameters(c_loop, 10, **blocks), 3.0, "none", seed=2)
    assert (CompileCount.calls, CompileCount.compiler_runs) == compilations
    np.testing.assert_array_equal(python_episode.u[:10], unchanged.u[:10])  # the change acts from the next call
    assert np.max(np.abs(python_episode.u[10:] - unchanged.u[10:])) > 1e-3
    np.testing.assert_array_equal(c_loop.parameters, python.parameters)
    assert python.parameters[python.parameter_names.index("mass_gravity")] == 9.0
    # the prediction is the model's with the gain scale: ∂ω⁺/∂u scales with it
    x = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.3, 0.0])
    slope = python._predict(x, np.zeros(1))[1]
    python.set_parameters(gain_scale=[0.35])
    np.testing.assert_allclose(python._predict(x, np.zeros(1))[1], 0.5 * slope, rtol=1e-12, atol=1e-15)
    # a non-finite value is refused by the library itself, and nothing changes
    before = c_loop.parameters
    refused = np.ascontiguousarray(np.where(np.arange(before.size) == 0, np.inf, before))
    assert c_loop._lib.fvc_set_parameters(c_loop._handle, refused.ctypes.data_as(ctypes.POINTER(ctypes.c_double))) == -3
    np.testing.assert_array_equal(c_loop.parameters, before)
    for controller in (python, c_loop):
        controller.set_parameters(python.model.model_parameters.defaults)


def test_the_prepared_feedback_is_the_same_in_both_loops_and_swings_up_as_the_qp_does(closed_form_pendulum):
    """``RTIOptions.feedback="prepared"``: the QP solved in the preparation, its gains applied in the call.
    Python and C equal to 1e-9, and the episode's outcome that of the full QP per call."""
    env, python, _ = closed_form_pendulum
    prepared = scene_mpc(env, python.model, python.settings.updated(rti={"feedback": "prepared"}))
    c_prepared = CRealTimeMPC(prepared)
    _, c_episode = assert_same_closed_loops(env, prepared, c_prepared, 4.0, "none", seed=0)
    assert_same_closed_loops(env, prepared, c_prepared, 2.0, 0.012, seed=3)
    qp_episode, _ = run_episode(env, python, 4.0, seed=0)
    assert episode_metrics(c_episode)["success"] and episode_metrics(qp_episode)["success"]
    assert episode_metrics(c_episode)["accumulated_cost"] == pytest.approx(
        episode_metrics(qp_episode)["accumulated_cost"], rel=0.01)
    with pytest.raises(ValueError, match="needs max_iter=1"):
        python.settings.updated(rti={"feedback": "prepared", "max_iter": 3})


def test_an_ipopt_cold_start_is_refused_with_the_reason():
    env = scene_env("pendulum", true_model=True)
    model = scene_model(env, true_model=True)
    python = scene_mpc(env, model, scene_mpc_settings(env, solver="rti", rti={"cold_solver": "ipopt"}, compile="none"))
    with pytest.raises(ControllerNotExportable, match="IPOPT cannot be generated as C"):
        CRealTimeMPC(python)


@pytest.mark.slow
@pytest.mark.parametrize("latency", ["none", 0.02])
def test_learned_pendulum_c_loop_equals_python_loop(latency):
    env, python, c_loop = pendulum_pair("pendulum", true_model=False)
    for seed in (0, 1):
        assert_same_closed_loops(env, python, c_loop, 8.0, latency, seed=seed, reset_options={"random": True})


@pytest.mark.slow
@pytest.mark.parametrize("true_model", [True, False], ids=["closed-form", "learned"])
def test_ball_joint_c_loop_equals_python_loop(true_model):
    env, python, c_loop = pendulum_pair("spherical_pendulum", true_model=true_model)
    assert python.settings.rti.max_iter == 3  # the preset's three iterations per period
    assert_same_closed_loops(env, python, c_loop, 6.0, "none", seed=0, reset_options={"random": True})
    assert_same_closed_loops(env, python, c_loop, 4.0, 0.01, seed=1, reset_options={"random": True})


@pytest.mark.slow
@pytest.mark.parametrize("true_model", [True, False], ids=["closed-form", "learned"])
def test_quadrotor_c_loop_equals_python_loop(true_model):
    from fvin_mpc.control.flight import recovery_starts

    env, python, c_loop = quadrotor_pair(true_model)
    starts = recovery_starts(env.unwrapped.goal_state[:3], count=3)
    for (options, seed), latency in zip(starts, ["none", 0.004, "none"]):
        assert_same_closed_loops(env, python, c_loop, 3.0, latency, seed=seed, reset_options=options)


def test_a_free_body_runs_its_kernels_in_both_loops_and_in_the_exported_folder(tmp_path):
    """The closed-form quadrotor's feedback calls the hand-written Riccati stage (``riccati_stage="auto"``, a free
    body) and its linearization the lane kernels of its dynamics and cost (``stage_lanes="auto"``): both loops
    agree over a recovery (1e-9); the exported folder's ``fvc_model.c`` is the very source the Python loop
    compiled, and the folder builds the three kernels in one unit with ``make`` and runs (``--rti-riccati-stage``
    and ``--rti-stage-lanes`` reach the settings)."""
    from fvin_mpc._cli import mpc_overrides
    from fvin_mpc.control.c_controller import write_controller
    from fvin_mpc.control.flight import recovery_starts
    from fvin_mpc.evaluate import build_parser

    assert mpc_overrides(build_parser().parse_args(["--solver", "rti", "--rti-riccati-stage", "generated"]))["rti"] \
        == {"riccati_stage": "generated"}
    assert mpc_overrides(build_parser().parse_args(["--solver", "rti", "--rti-stage-lanes", "off"]))["rti"] \
        == {"stage_lanes": "off"}
    env, python, c_loop = quadrotor_pair(true_model=True)
    kernels = ["fvin_lanes_rti_dynamics_30", "fvin_lanes_rti_stage_cost_30", "fvin_riccati_sweep_12_4_30"]
    assert [kernel.name for kernel in python.loop_kernels] == kernels
    options, seed = recovery_starts(env.unwrapped.goal_state[:3], count=3)[0]
    assert_same_closed_loops(env, python, c_loop, 1.0, "none", seed=seed, reset_options=options)
    if shutil.which("make") is None:
        pytest.skip("no make on PATH")
    directory = write_controller(python, tmp_path / "quadrotor")
    assert all(kernel in (directory / "fvc_kernels.c").read_text() for kernel in kernels)
    source = (directory / "fvc_model.c").read_bytes()
    assert hashlib.sha256(source).hexdigest() == python.compile_report.source_sha256
    subprocess.run(["make", "-s"], cwd=directory, capture_output=True, text=True, check=True)
    run = subprocess.run([str(directory / "example"), "5"], capture_output=True, text=True, check=True)
    assert "calls=5 cold=1 fallbacks=0" in run.stdout


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["spherical_pendulum", "quadrotor"])
def test_changed_model_parameters_agree_between_the_loops(scene):
    """The learned ball joint and quadrotor with changed gains and physical weights from the start and again
    mid-episode: the Python and the C loop to 1e-9 (the parametrized R³ × S³ and ball-joint terms in C)."""
    if scene == "quadrotor":
        from fvin_mpc.control.flight import recovery_starts

        env, python, c_loop = quadrotor_pair(true_model=False)
        options, seed = recovery_starts(env.unwrapped.goal_state[:3], count=1)[0]
        parameters = python.model.model_parameters
        linear = parameters.defaults[parameters.slice("potential_linear")]
        start = {"gain_scale": [0.9, 1.1, 1.0, 0.95], "potential_linear": 1.1 * linear}
        later = {"gain_scale": [1.0, 0.9, 1.05, 1.0]}
        duration = 2.0
    else:
        env, python, c_loop = pendulum_pair(scene, true_model=False)
        options, seed = {"random": True}, 4
        weights = python.model.model_parameters.defaults[python.model.model_parameters.slice("potential_w2")]
        start = {"gain_scale": [0.8, 1.2, 1.0], "potential_w2": 1.1 * weights}
        later = {"gain_scale": [1.0, 1.0, 0.9]}
        duration = 4.0
    for controller in (python, c_loop):
        controller.set_parameters(**start)
    # ChangesParameters.reset() returns to `start`, the values at its construction
    python_run, c_run = ChangesParameters(python, 15, **later), ChangesParameters(c_loop, 15, **later)
    assert_same_closed_loops(env, python_run, c_run, duration, "none", seed=seed, reset_options=options)
    np.testing.assert_array_equal(c_loop.parameters, python.parameters)


@pytest.mark.slow
def test_the_prepared_feedback_is_the_same_in_both_loops_on_the_learned_models():
    from fvin_mpc.control.flight import quadrotor_model, quadrotor_mpc, quadrotor_mpc_settings, recovery_starts
    from fvin_mpc.envs import QuadrotorEnv
    from fvin_mpc.envs.scenes import resolve_scene

    env, python, c_loop = pendulum_pair("pendulum", true_model=False, rti={"feedback": "prepared"})
    assert_same_closed_loops(env, python, c_loop, 8.0, "none", seed=1, reset_options={"random": True})
    env = QuadrotorEnv(resolve_scene("quadrotor"))
    settings = quadrotor_mpc_settings().updated(rti={**UNBOUNDED, "feedback": "prepared"})
    python = quadrotor_mpc(env, quadrotor_model(env), settings)
    options, seed = recovery_starts(env.unwrapped.goal_state[:3], count=3)[2]
    assert_same_closed_loops(env, python, CRealTimeMPC(python), 3.0, "none", seed=seed, reset_options=options)


@pytest.mark.slow
def test_export_command_writes_a_library_that_builds_and_runs(tmp_path):
    from fvin_mpc.export import main

    if shutil.which("make") is None:
        pytest.skip("no make on PATH")
    directory = tmp_path / "controller"
    assert main(["--controller", str(directory), "--true-model", "--build"]) == 0
    for name in ("fvin_controller.h", "fvin_controller.c", "fvc_model.c", "fvc_config.h", "Makefile", "main.c"):
        assert (directory / name).is_file()
    run = subprocess.run([str(directory / "example"), "30"], capture_output=True, text=True, check=True)
    assert "calls=30 cold=1 fallbacks=0 prepares=30" in run.stdout
    # nothing of Python, CasADi or torch at run time: the example links libc and libm only
    linked = subprocess.run(["ldd", str(directory / "example")], capture_output=True, text=True).stdout
    assert "casadi" not in linked and "python" not in linked and "torch" not in linked


@pytest.mark.slow
def test_quadrotor_figure_eight_reference_reaches_the_c_loop_each_period():
    """A time-varying reference: sampled in Python, pushed to the library every period."""
    from fvin_mpc.control.flight import FigureEight

    env, python, c_loop = quadrotor_pair(true_model=True)
    reference = FigureEight(center=tuple(env.unwrapped.hover_point), amplitude=0.5, period=3.0, ramp_s=1.0)
    for controller in (python, c_loop):
        controller.set_reference(reference)
    _, c_episode = assert_same_closed_loops(env, python, c_loop, 3.0, "none", reset_options={"hover": True})
    # the craft left its hover point: the comparison covers a moving reference, not a constant one
    assert np.abs(c_episode.states[:, :3] - c_episode.states[0, :3]).max() > 0.2
    assert_same_closed_loops(env, python, c_loop, 2.0, 0.004, reset_options={"hover": True})


def test_export_options_that_need_a_controller_are_refused_without_one(capsys):
    from fvin_mpc.core.errors import run_command
    from fvin_mpc.export import main

    assert run_command(main, ["--build"]) == 2
    assert "go with --controller DIR" in capsys.readouterr().err


def test_swingup_runs_on_the_c_loop_when_asked(tmp_path, capsys):
    """``--loop c``: the command's controller is the C library (whose closed loops the tests above compare
    with Python's); with a solver that is not the real-time iteration, a one-line error."""
    import json

    from fvin_mpc.core.errors import run_command
    from fvin_mpc.swingup import main

    out = tmp_path / "c.json"
    calls = CompileCount.calls
    assert main(["--true-model", "--solver", "rti", "--loop", "c", "--duration", "2", "--plot", "", "--quiet",
                 "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["loop"] == "c" and np.isfinite(result["accumulated_cost"])
    assert CompileCount.calls == calls + 2  # the Python loop's functions and the C library (both cached)
    capsys.readouterr()
    assert run_command(main, ["--true-model", "--solver", "ipopt", "--loop", "c", "--duration", "1", "--plot", "",
                              "--quiet"]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert error[-1].startswith("error: --loop c runs the real-time iteration's generated C library")


def test_evaluate_runs_its_mpc_on_the_c_loop_when_asked(tmp_path, capsys):
    from fvin_mpc.core.errors import run_command
    from fvin_mpc.evaluate import main

    common = ["--controllers", "mpc-true", "--episodes", "1", "--duration", "2", "--quiet", "--loop", "c",
              "--out-dir", str(tmp_path)]
    assert main([*common, "--solver", "rti"]) == 0
    assert "the C loop" in (tmp_path / "evaluation.md").read_text()
    capsys.readouterr()
    assert run_command(main, [*common, "--solver", "ipopt"]) == 2
    assert "add --solver rti" in capsys.readouterr().err


def test_the_prepared_feedback_option_sets_one_iteration_per_period():
    from fvin_mpc._cli import mpc_overrides
    from fvin_mpc.swingup import build_parser

    args = build_parser().parse_args(["--solver", "rti", "--rti-feedback", "prepared"])
    assert mpc_overrides(args)["rti"] == {"feedback": "prepared", "max_iter": 1}
    assert "rti" not in mpc_overrides(build_parser().parse_args(["--solver", "rti"]))


@pytest.mark.parametrize(("option", "field"), [("--rti-cold-iter", "cold_iter"),
                                               ("--rti-qp-iterations", "qp_iterations"),
                                               ("--rti-relinearize-every", "relinearize_every")])
def test_the_count_options_reach_the_settings_and_refuse_zero(capsys, option, field):
    from fvin_mpc._cli import mpc_overrides
    from fvin_mpc.control.scene import scene_env, scene_mpc_settings
    from fvin_mpc.evaluate import build_parser

    args = build_parser().parse_args(["--solver", "rti", option, "4"])
    assert mpc_overrides(args)["rti"] == {field: 4}
    settings = scene_mpc_settings(scene_env("pendulum", true_model=True), **mpc_overrides(args))
    assert getattr(settings.rti, field) == 4
    with pytest.raises(SystemExit):
        build_parser().parse_args([option, "0"])
    assert "must be >= 1" in capsys.readouterr().err


def test_a_two_motor_ball_with_a_free_axis_c_loop_equals_python_loop(tmp_path):
    # The free axis reaches the C loop twice: in the generated cost, and in its disturbance
    # estimate's region (the axis's direction, the speed without the spin about it).
    from fvin_mpc.envs.families import write_family

    (scene,) = write_family("ball", [9002], tmp_path)
    env, python, c_loop = pendulum_pair(str(scene), true_model=True)
    assert python.settings.free_axis is not None
    python_episode, _ = assert_same_closed_loops(env, python, c_loop, 8.0, "none", seed=2,
                                                 reset_options={"random": True, "max_omega": 2.0})
    assert np.any(python_episode.controller_info[-1]["disturbance"] != 0.0)  # the estimate ran near the goal


def test_a_knock_restarts_both_loops_alike_and_the_damped_pendulum_swings_back_up():
    # The scene's default restart_speed (0.13 ω_s ≈ 1.0 rad/s) against a 2 rad/s knock once held for 1 s.
    from dataclasses import replace

    from fvin_mpc.envs import RigidBodyEnv
    from fvin_mpc.envs.scenes import resolve_scene

    _, python, c_loop = pendulum_pair("pendulum_damped", true_model=True)
    assert 0.5 < python.settings.rti.restart_speed < 2.0
    spec = resolve_scene("pendulum_damped")
    knocked = RigidBodyEnv(scene=spec, physics=replace(spec.physics, impulse_delta_omega=2.0))
    python_episode, c_episode = assert_same_closed_loops(knocked, python, c_loop, 10.0, "none", seed=3,
                                                         reset_options={"random": True})
    restarts = [k for k, info in enumerate(python_episode.controller_info) if info.get("restarted")]
    assert restarts, "the knock did not restart the plan"
    assert restarts == [k for k, info in enumerate(c_episode.controller_info) if info.get("restarted")]
    assert all(python_episode.controller_info[k].get("cold_start") for k in restarts)  # each a cold call


@pytest.mark.parametrize("block", [1, 7])
def test_the_paired_timing_replays_the_same_plan_to_both_loops(closed_form_pendulum, block):
    """``benchmarks.c_loop``'s paired periods feed one episode's observations to both loops in turns (period by
    period, or in blocks); its speed-up figures mean something only if the loops stay on the same plan there
    (no timing asserted)."""
    from benchmarks.c_loop import LeanC, paired

    env, python, c_loop = closed_form_pendulum
    result = paired(env, python, LeanC(c_loop), 1.0, {"random": True}, 2, block=block)
    assert result["periods"] == 19 and result["block"] == block and result["control_difference_max"] <= 1e-9
    for key in ("python_us_median", "c_us_median", "generated_us_median", "speed-up", "speed-up bound"):
        assert np.isfinite(result[key]) and result[key] > 0.0
    with pytest.raises(ValueError, match="block"):
        paired(env, python, LeanC(c_loop), 1.0, {"random": True}, 2, block=0)


@pytest.mark.parametrize(("scene", "latency"), [("pendulum", "none"), ("pendulum_damped", 0.01)])
def test_kept_jacobians_are_the_same_in_both_loops(scene, latency):
    """``rti.relinearize_every``: both loops keep and renew the same Jacobians — shifted at each preparation,
    renewed whole after a cold call — on the implicit dynamics' node slopes (pendulum) and the unrolled stages
    (damped pendulum, with a measured-latency delay)."""
    env, python, c_loop = pendulum_pair(scene, True, rti={"relinearize_every": 3, "relinearize_head": 2})
    assert python.kept_jacobians[3].sum() < python.kept_jacobians[0]
    _, c_episode = assert_same_closed_loops(env, python, c_loop, 5.0, latency, seed=2,
                                            reset_options={"random": True})
    assert episode_metrics(c_episode)["success"]


def test_the_mehrotra_qp_is_the_same_in_both_loops_and_swings_up():
    """``rti.qp_method="mehrotra"`` (``--rti-qp-method``): the generated QP's predictor–corrector runs in both loops
    alike, and a closed-form swing-up with it succeeds."""
    from fvin_mpc._cli import mpc_overrides
    from fvin_mpc.evaluate import build_parser

    assert mpc_overrides(build_parser().parse_args(["--solver", "rti", "--rti-qp-method", "mehrotra"]))["rti"] == {
        "qp_method": "mehrotra"}
    env, python, c_loop = pendulum_pair("pendulum", True, rti={"qp_method": "mehrotra", "qp_iterations": 5})
    _, c_episode = assert_same_closed_loops(env, python, c_loop, 4.0, "none")
    assert episode_metrics(c_episode)["success"]


@pytest.mark.slow
def test_kept_jacobians_are_the_same_in_both_loops_on_the_learned_ball_joint_and_quadrotor():
    """``rti.relinearize_every`` on the learned models: the ball joint's three iterations per period (each
    further one keeps the last one's Jacobians where they stand) and the R³ × S³ stages."""
    from fvin_mpc.control.flight import quadrotor_model, quadrotor_mpc, quadrotor_mpc_settings, recovery_starts
    from fvin_mpc.envs import QuadrotorEnv
    from fvin_mpc.envs.scenes import resolve_scene

    kept = {"relinearize_every": 4}
    env, python, c_loop = pendulum_pair("spherical_pendulum", False, rti=kept)
    assert_same_closed_loops(env, python, c_loop, 6.0, "none", seed=0, reset_options={"random": True})
    env = QuadrotorEnv(resolve_scene("quadrotor"))
    python = quadrotor_mpc(env, quadrotor_model(env, true_model=False),
                           quadrotor_mpc_settings().updated(rti={**UNBOUNDED, **kept}))
    options, seed = recovery_starts(env.unwrapped.goal_state[:3], count=1)[0]
    assert_same_closed_loops(env, python, CRealTimeMPC(python), 3.0, 0.004, seed=seed, reset_options=options)


def test_the_library_is_built_for_this_cpu_and_keyed_by_it(closed_form_pendulum, monkeypatch, tmp_path):
    """The C loop's library is compiled with the Python loop's target flags (``-march=native`` where the compiler
    takes it), its driver without fused multiply–adds, and its cache entry names the CPU: another CPU sharing the
    cache builds its own."""
    from fvin_mpc.control import c_controller
    from fvin_mpc.control.model_export import generated_code_flags

    _, python, _ = closed_form_pendulum
    target = generated_code_flags(COMPILER)
    assert c_controller.library_flags(COMPILER) == (*c_controller.LIBRARY_FLAGS, *target)
    assert "-ffp-contract=off" in c_controller.DRIVER_FLAGS
    if not target:
        pytest.skip("the compiler does not take -march=native: nothing CPU-specific to key")
    monkeypatch.setenv("FVIN_MPC_CACHE", str(tmp_path))
    here = c_controller.cached_library(python)
    monkeypatch.setattr(c_controller, "host_cpu", lambda: "another CPU")
    elsewhere = c_controller.cached_library(python)
    assert here != elsewhere and here.is_file() and elsewhere.is_file()
