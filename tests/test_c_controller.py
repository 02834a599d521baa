"""The real-time controller's one loop, its generated C library (:mod:`fvin_mpc.control.c_controller`), driven by
:class:`~fvin_mpc.control.rti.RealTimeMPC` through ``ctypes``.

Its controls are judged against reference episodes of the loop recorded before the Python copy of it was deleted
(``tests/data/loop_reference``, ``python -m benchmarks.loop_replay record`` at 1aecd33): the recorded observations
replayed call by call give the recorded controls to 1e-9 (the plant taken out), and the whole episode run again
has the recorded outcome. The recordings' wall-clock budgets did not bind (the iteration counts alone bound the
loop), so the replays lift them too. The default suite replays the closed-form pendulum's loop; the others are
``slow``.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from benchmarks.loop_replay import CONTROL_TOLERANCE, LOOPS, loop_setup, outcome, paired_difference
from fvin_mpc.control.c_controller import ControllerNotExportable, write_controller
from fvin_mpc.control.closed_loop import episode_metrics, run_episode
from fvin_mpc.control.model_export import CompileCount
from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings

COMPILER = os.environ.get("CC", "cc")
pytestmark = pytest.mark.skipif(shutil.which(COMPILER) is None,
                                reason=f"no C compiler {COMPILER!r} on PATH: the C controller cannot be built")
REFERENCE = Path(__file__).parent / "data" / "loop_reference"
#: Wall-clock budgets that never bind (s): the iteration counts alone bound the loop.
UNBOUNDED = {"cold_budget_s": 600.0, "budget_s": 600.0}


def replay(name: str) -> None:
    """``name``'s recording replayed call by call, then its whole episode run again."""
    recording = np.load(REFERENCE / f"{name}.npz")
    recorded = json.loads((REFERENCE / f"{name}.json").read_text())
    env, controller, (duration, options, seed) = loop_setup(name)
    difference, colds = paired_difference(controller, recording)
    assert difference <= CONTROL_TOLERANCE
    assert colds == [str(c) for c in recording["cold_start"]]
    episode, _ = run_episode(env, controller, duration, options, seed=seed)
    now = outcome(episode)
    assert now["success"] == recorded["success"]
    assert now["time_to_upright_s"] == pytest.approx(recorded["time_to_upright_s"], abs=env.unwrapped.dt + 1e-9)
    assert now["accumulated_cost"] == pytest.approx(recorded["accumulated_cost"], rel=0.01)


def test_the_loop_gives_the_recorded_controls_on_the_closed_form_pendulum():
    replay("pendulum-closed-form")


@pytest.mark.slow
@pytest.mark.parametrize("name", [name for name in LOOPS if name != "pendulum-closed-form"])
def test_the_loop_gives_the_recorded_controls(name):
    replay(name)


def test_every_built_in_scene_has_a_recorded_loop():
    from fvin_mpc.envs.scenes import SCENES

    assert {scene for scene, *_ in LOOPS.values()} == {*SCENES, "quadrotor"}
    assert all((REFERENCE / f"{name}.npz").is_file() and (REFERENCE / f"{name}.json").is_file() for name in LOOPS)


@pytest.fixture(scope="module")
def closed_form_pendulum():
    env = scene_env("pendulum", true_model=True)
    model = scene_model(env, true_model=True)
    return env, scene_mpc(env, model, scene_mpc_settings(env, solver="rti").updated(rti=UNBOUNDED))


def test_skipped_observations_reach_the_loop_as_a_jump_of_its_clock(closed_form_pendulum):
    """A latency over the period: the controller is busy at the next instant, that observation is lost, and the
    clock jump drops the one-step prediction from the disturbance estimate: the episode stays deterministic."""
    env, controller = closed_form_pendulum
    first, _ = run_episode(env, controller, 2.0, latency=0.06, seed=5)
    second, _ = run_episode(env, controller, 2.0, latency=0.06, seed=5)
    assert first.skipped > 0
    np.testing.assert_array_equal(first.u, second.u)
    counters = controller.counters()
    assert counters["calls"] >= counters["cold_calls"] > 0


def test_the_loop_refuses_a_state_that_is_not_one(closed_form_pendulum):
    _, controller = closed_form_pendulum
    bad_states = controller.counters()["bad_states"]
    with pytest.raises(ValueError, match="bad-state"):
        controller.feedback(np.array([2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]))
    assert controller.counters()["bad_states"] == bad_states + 1


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
    env, python = closed_form_pendulum
    constants = scene_mpc(env, python.model, python.settings.updated(rti={"model_parameters": False}))
    baked, _ = run_episode(env, constants, 4.0, seed=0)
    inputs, _ = run_episode(env, python, 4.0, seed=0)
    np.testing.assert_allclose(inputs.u, baked.u, rtol=0.0, atol=1e-12)
    with pytest.raises(ValueError, match="baked in"):
        constants.set_parameters(gain_scale=[0.5])


def test_changed_model_parameters_reach_the_loop_without_recompiling(closed_form_pendulum):
    """New gains and physical values mid-episode: the controls differ from the unchanged model's from the change
    on, nothing is compiled, and the library's prediction is the model's with the new gain."""
    env, controller = closed_form_pendulum
    unchanged, _ = run_episode(env, controller, 3.0, seed=2)
    compilations = (CompileCount.calls, CompileCount.compiler_runs)
    changed, _ = run_episode(env, ChangesParameters(controller, 10, gain_scale=[0.7], mass_gravity=9.0), 3.0, seed=2)
    assert (CompileCount.calls, CompileCount.compiler_runs) == compilations
    np.testing.assert_array_equal(changed.u[:10], unchanged.u[:10])  # the change acts from the next call
    assert np.max(np.abs(changed.u[10:] - unchanged.u[10:])) > 1e-3
    assert controller.parameters[controller.parameter_names.index("mass_gravity")] == 9.0
    np.testing.assert_array_equal(controller.library.parameters(), controller.parameters)
    # the prediction is the model's with the gain scale: ∂ω⁺/∂u scales with it
    x = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.3, 0.0])
    slope = controller._predict(x, np.zeros(1))[1]
    controller.set_parameters(gain_scale=[0.35])
    np.testing.assert_allclose(controller._predict(x, np.zeros(1))[1], 0.5 * slope, rtol=1e-12, atol=1e-15)
    # a non-finite value is refused by the library itself, and nothing changes
    before = controller.parameters
    with pytest.raises(ValueError, match="bad-parameters"):
        controller.library.set_parameters(np.where(np.arange(before.size) == 0, np.inf, before))
    np.testing.assert_array_equal(controller.library.parameters(), before)
    controller.set_parameters(controller.model.model_parameters.defaults)


def test_the_prepared_feedback_swings_up_as_the_qp_does(closed_form_pendulum):
    """``RTIOptions.feedback="prepared"``: the QP solved in the preparation, its gains applied in the call; the
    episode's outcome that of the full QP per call."""
    env, controller = closed_form_pendulum
    prepared = scene_mpc(env, controller.model, controller.settings.updated(rti={"feedback": "prepared"}))
    prepared_episode, _ = run_episode(env, prepared, 4.0, seed=0)
    qp_episode, _ = run_episode(env, controller, 4.0, seed=0)
    assert episode_metrics(prepared_episode)["success"] and episode_metrics(qp_episode)["success"]
    assert episode_metrics(prepared_episode)["accumulated_cost"] == pytest.approx(
        episode_metrics(qp_episode)["accumulated_cost"], rel=0.01)
    with pytest.raises(ValueError, match="needs max_iter=1"):
        controller.settings.updated(rti={"feedback": "prepared", "max_iter": 3})


def test_an_ipopt_cold_start_enters_the_loop_and_is_refused_for_a_standalone_folder(tmp_path):
    """``rti.cold_solver="ipopt"``: Python solves the cold call with IPOPT and hands the plan to the library, which
    improves it by one iteration; the folder a robot builds cannot hold IPOPT, and says so."""
    env = scene_env("pendulum", true_model=True)
    model = scene_model(env, true_model=True)
    controller = scene_mpc(env, model, scene_mpc_settings(env, solver="rti", rti={"cold_solver": "ipopt"}))
    x0, _ = env.reset(seed=0)
    _, first = controller(x0)
    assert first["cold_solver"] == "ipopt" and first["cold_ipopt_success"] and first["iterations"] == 1
    controller.prepare()
    _, second = controller(x0)
    assert "cold_solver" not in second and second["status"] in ("rti", "budget")
    episode, _ = run_episode(env, controller, 4.0, seed=0)
    assert episode_metrics(episode)["success"] and controller.counters()["cold_calls"] == 2  # since it was made
    with pytest.raises(ControllerNotExportable, match="IPOPT cannot be generated as C"):
        write_controller(controller, tmp_path / "controller")


def test_a_non_finite_disturbance_estimate_never_reaches_the_torque(closed_form_pendulum):
    """A NaN ``d̂`` (set before the preparation: the shifted plan's last node is then NaN) is clipped away by the
    QP's bounds and the trust region: the control stays finite and inside the torque range."""
    env, controller = closed_form_pendulum
    x0, _ = env.reset(options={"qpos": np.array([2.0]), "qvel": np.array([1.0])})
    controller.reset()
    controller(x0)
    previous = controller.plan.controls.copy()
    controller.set_disturbance(np.nan)
    controller.prepare()
    assert not np.all(np.isfinite(controller.plan.states))
    u, info = controller(controller.model(x0, previous[0])[0])
    assert np.all(np.isfinite(u)) and np.all(env.unwrapped.torque_low <= u) and np.all(u <= env.unwrapped.torque_high)
    controller.reset()


def test_a_spent_cold_budget_still_scores_every_first_guess(closed_form_pendulum):
    """A cold budget spent inside the first guess ("goal", whose gaps are still open) still leaves every other
    guess scored, un-iterated, so that half-iterated plan is not kept for want of time: a rollout, a plan of the
    model with no gaps, beats the un-converged goal path. The budget is the library's (the monotonic clock)."""
    env, controller = closed_form_pendulum
    hurried = scene_mpc(env, controller.model, controller.settings.updated(rti={"cold_budget_s": 1e-12}))
    _, info = hurried(env.reset()[0])
    assert set(info["cold_costs"]) == set(hurried.settings.cold_starts)
    assert info["cold_start"] == min(info["cold_costs"], key=info["cold_costs"].get) != "goal"
    assert info["status"] == "budget"


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


def test_a_free_body_runs_its_kernels_in_the_loop_and_in_the_exported_folder(tmp_path):
    """The closed-form quadrotor's feedback calls the hand-written Riccati stage (``riccati_stage="auto"``, a free
    body) and its linearization the lane kernels of its dynamics and cost (``stage_lanes="auto"``); the exported
    folder's ``fvc_model.c`` is the very source the controller's library holds, and the folder builds the three
    kernels in one unit with ``make`` and runs (``--rti-riccati-stage`` and ``--rti-stage-lanes`` reach the
    settings)."""
    from fvin_mpc._cli import mpc_overrides
    from fvin_mpc.evaluate import build_parser

    assert mpc_overrides(build_parser().parse_args(["--solver", "rti", "--rti-riccati-stage", "generated"]))["rti"] \
        == {"riccati_stage": "generated"}
    assert mpc_overrides(build_parser().parse_args(["--solver", "rti", "--rti-stage-lanes", "off"]))["rti"] \
        == {"stage_lanes": "off"}
    env, controller, (duration, options, seed) = loop_setup("quadrotor-closed-form")
    kernels = ["fvin_lanes_rti_dynamics_30", "fvin_lanes_rti_stage_cost_30", "fvin_riccati_sweep_12_4_30"]
    assert [kernel.name for kernel in controller.loop_kernels] == kernels
    episode, _ = run_episode(env, controller, 1.0, options, seed=seed)
    assert episode.controller_success.all()
    if shutil.which("make") is None:
        pytest.skip("no make on PATH")
    directory = write_controller(controller, tmp_path / "quadrotor")
    assert all(kernel in (directory / "fvc_kernels.c").read_text() for kernel in kernels)
    source = (directory / "fvc_model.c").read_bytes()
    assert hashlib.sha256(source).hexdigest() == controller.compile_report.source_sha256
    subprocess.run(["make", "-s"], cwd=directory, capture_output=True, text=True, check=True)
    run = subprocess.run([str(directory / "example"), "5"], capture_output=True, text=True, check=True)
    assert "calls=5 cold=1 fallbacks=0" in run.stdout


@pytest.mark.slow
def test_the_quadrotor_figure_eight_reference_reaches_the_loop_each_period():
    """A time-varying reference: sampled in Python, pushed to the library every period; the craft follows it."""
    from fvin_mpc.control.flight import FigureEight

    env, controller, _ = loop_setup("quadrotor-closed-form")
    reference = FigureEight(center=tuple(env.unwrapped.hover_point), amplitude=0.5, period=3.0, ramp_s=1.0)
    controller.set_reference(reference)
    episode, _ = run_episode(env, controller, 3.0, {"hover": True})
    assert np.abs(episode.states[:, :3] - episode.states[0, :3]).max() > 0.2
    assert episode.controller_success.all()


def test_export_options_that_need_a_controller_are_refused_without_one(capsys):
    from fvin_mpc.core.errors import run_command
    from fvin_mpc.export import main

    assert run_command(main, ["--build"]) == 2
    assert "go with --controller DIR" in capsys.readouterr().err


def test_the_commands_have_one_loop(capsys):
    """``--loop`` is gone: the real-time MPC of every command is the generated library."""
    from fvin_mpc.swingup import build_parser

    with pytest.raises(SystemExit):
        build_parser().parse_args(["--loop", "c"])
    assert "unrecognized arguments: --loop" in capsys.readouterr().err


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


def test_a_knock_restarts_the_loop_and_the_damped_pendulum_swings_back_up():
    # The scene's default restart_speed (0.13 ω_s ≈ 1.0 rad/s) against a 2 rad/s knock once held for 1 s.
    env, controller, (duration, options, seed) = loop_setup("pendulum_damped-knocked")
    assert 0.5 < controller.settings.rti.restart_speed < 2.0
    episode, _ = run_episode(env, controller, 10.0, options, seed=seed)
    restarts = [k for k, info in enumerate(episode.controller_info) if info.get("restarted")]
    assert restarts, "the knock did not restart the plan"
    assert all(episode.controller_info[k].get("cold_start") for k in restarts)  # each a cold call
    assert episode_metrics(episode)["success"]


def test_kept_jacobians_swing_up(closed_form_pendulum):
    """``rti.relinearize_every``: the loop keeps and renews Jacobians — shifted at each preparation, renewed
    whole after a cold call — and a closed-form swing-up with them succeeds."""
    env, controller = closed_form_pendulum
    kept = scene_mpc(env, controller.model,
                     controller.settings.updated(rti={"relinearize_every": 3, "relinearize_head": 2}))
    assert kept.kept_jacobians[3].sum() < kept.kept_jacobians[0]
    episode, _ = run_episode(env, kept, 5.0, {"random": True}, seed=2, latency=0.01)
    assert episode_metrics(episode)["success"]


def test_the_mehrotra_qp_swings_up():
    """``rti.qp_method="mehrotra"`` (``--rti-qp-method``): the generated QP's predictor–corrector in the loop."""
    from fvin_mpc._cli import mpc_overrides
    from fvin_mpc.evaluate import build_parser

    assert mpc_overrides(build_parser().parse_args(["--solver", "rti", "--rti-qp-method", "mehrotra"]))["rti"] == {
        "qp_method": "mehrotra"}
    env = scene_env("pendulum", true_model=True)
    controller = scene_mpc(env, scene_model(env, true_model=True), scene_mpc_settings(
        env, solver="rti", rti={**UNBOUNDED, "qp_method": "mehrotra", "qp_iterations": 5}))
    episode, _ = run_episode(env, controller, 4.0)
    assert episode_metrics(episode)["success"]


def test_the_library_is_built_for_this_cpu_and_keyed_by_it(closed_form_pendulum, monkeypatch, tmp_path):
    """The library is compiled with the host's target flags (``-march=native`` where the compiler takes it) and
    its cache entry names the CPU: another CPU sharing the cache builds its own."""
    from fvin_mpc.control import c_controller
    from fvin_mpc.control.model_export import generated_code_flags

    _, controller = closed_form_pendulum
    target = generated_code_flags(COMPILER)
    assert c_controller.library_flags(COMPILER) == (*c_controller.LIBRARY_FLAGS, *target)
    if not target:
        pytest.skip("the compiler does not take -march=native: nothing CPU-specific to key")
    monkeypatch.setenv("FVIN_MPC_CACHE", str(tmp_path))
    here, _ = c_controller.cached_library(controller)
    monkeypatch.setattr(c_controller, "host_cpu", lambda: "another CPU")
    elsewhere, cached = c_controller.cached_library(controller)
    assert here != elsewhere and here.is_file() and elsewhere.is_file() and not cached
