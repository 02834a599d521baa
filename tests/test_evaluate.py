"""Closed-loop evaluation CLI/library and the multi-start MPC."""

import json
from dataclasses import replace

import numpy as np
import pytest
from helpers import hinge

from fvin_mpc import evaluate as evaluate_cli
from fvin_mpc.core import s3
from fvin_mpc.studies import evaluation as ev


# ---------------------------------------------------------------------- evaluate
def test_episode_starts_rest_then_seeded_random():
    starts = ev.episode_starts(ev.EvaluationConfig(episodes=4, seed=10, max_omega=1.5))
    assert starts[0].reset_options is None and starts[0].seed == 10
    assert [s.seed for s in starts[1:]] == [11, 12, 13]
    assert all(s.reset_options == {"random": True, "max_omega": 1.5} for s in starts[1:])


def test_signed_angle_from_goal_on_the_hinge():
    goal, axis = np.array([0.0, 0.0, 1.0, 0.0]), np.array([0.0, 1.0, 0.0])
    for theta, expected in [(np.pi, 0.0), (np.pi - 0.3, -0.3), (np.pi + 0.3, 0.3), (0.0, np.pi), (0.2, 0.2 - np.pi)]:
        q, _ = hinge(theta)
        for sign in (1, -1):  # q and −q are the same rotation
            angle = float(ev.signed_angle_from_goal(sign * q, goal, axis))
            assert np.isclose(np.cos(angle), np.cos(expected)) and np.isclose(np.sin(angle), np.sin(expected)), theta


@pytest.mark.parametrize("kwargs", [{"episodes": 0}, {"duration_s": 0.0}, {"controllers": ("mpc-magic",)},
                                    {"controllers": ()}, {"max_omega": -1.0}, {"mpc": (("horizon", 0),)},
                                    {"mpc": (("terminal_energy_weight", -1.0),)}, {"mpc": (("magic", 1),)}])
def test_config_is_validated(kwargs):
    with pytest.raises(ValueError):
        ev.EvaluationConfig(**kwargs)


def test_evaluate_energy_and_zero_serial_equals_parallel():
    config = ev.EvaluationConfig(episodes=3, duration_s=5.0, controllers=("energy-true", "zero"), seed=3)
    serial = ev.evaluate(config, workers=1, progress=False)
    parallel = ev.evaluate(config, workers=2, progress=False)
    assert serial.summary["zero"]["success_rate"] == 0.0  # hanging or swinging, never upright
    assert serial.summary["energy-true"]["success_rate"] == 1.0  # incl. the swing-up from rest
    for name in ("energy-true", "zero"):
        for a, b in zip(serial.episodes, parallel.episodes):
            assert a["seed"] == b["seed"]
            ma, mb = a["results"][name], b["results"][name]
            assert ma["time_to_upright_s"] == mb["time_to_upright_s"]
            assert ma["accumulated_cost"] == pytest.approx(mb["accumulated_cost"], rel=1e-12)
    # The rest start is the hard one: it must pump, so it takes longer than a second.
    assert serial.episodes[0]["results"]["energy-true"]["time_to_upright_s"] > 1.0


def test_missing_default_checkpoint_skips_learned_controllers(monkeypatch, tmp_path):
    import fvin_mpc.core.checkpoint

    monkeypatch.setattr(fvin_mpc.core.checkpoint, "CHECKPOINT_DIR", tmp_path)
    config = ev.EvaluationConfig(episodes=1, duration_s=0.5, controllers=("energy-learned", "zero"))
    messages = []
    result = ev.evaluate(config, progress=False, log=messages.append)
    assert list(result.summary) == ["zero"]
    assert "not shipped" in result.skipped["energy-learned"] and messages


def test_missing_explicit_checkpoint_is_an_error():
    config = ev.EvaluationConfig(episodes=1, duration_s=0.5, controllers=("energy-learned",), checkpoint="nope/missing")
    with pytest.raises(FileNotFoundError, match="missing"):
        ev.evaluate(config, progress=False)


def test_cli_writes_report_and_skips_energy_shaping_on_a_ball_joint(tmp_path, capsys):
    code = evaluate_cli.main(["--scene", "spherical_pendulum", "--episodes", "2", "--duration", "0.5", "--controllers",
                    "energy-true,zero", "--out-dir", str(tmp_path), "--quiet", "--json", str(tmp_path / "copy.json")])
    assert code == 0
    captured = capsys.readouterr()
    assert "skipping energy-true" in captured.err and "hinge" in captured.err
    report = json.loads((tmp_path / "evaluation.json").read_text())
    assert list(report["summary"]) == ["zero"] and "energy-true" in report["skipped"]
    assert (tmp_path / "evaluation.md").read_text().count("| zero |") == 1
    assert (tmp_path / "time_to_upright.png").exists() and not (tmp_path / "phase_portraits.png").exists()
    assert json.loads((tmp_path / "copy.json").read_text())["summary"] == report["summary"]


@pytest.mark.parametrize("argv, message", [(["--controllers", "bogus"], "unknown controllers"),
                                           (["--episodes", "0"], "episodes"), (["--workers", "0"], "workers"),
                                           (["--scene", "no_such_scene"], "unknown scene")])
def test_cli_bad_input_is_a_one_line_error(argv, message, capsys, tmp_path):
    assert evaluate_cli.main([*argv, "--out-dir", str(tmp_path), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and message in err and "\n" not in err


def test_cli_help(capsys):
    with pytest.raises(SystemExit) as exit_info:
        evaluate_cli.main(["--help"])
    assert exit_info.value.code == 0 and "--workers" in capsys.readouterr().out


# ---------------------------------------------------------------------- multi-start MPC
def test_multistart_catches_a_nearly_upright_pendulum_that_the_single_guess_lets_fall():
    """Near upright every constant-torque first guess falls; IPOPT then returns a full-turn plan.
    The "goal" guess lies in the basin of catching it; the multi-start keeps the cheaper plan."""
    from fvin_mpc.control import model_export as export
    from fvin_mpc.control.mpc import COLD_STARTS, MPC, IpoptOptions, MPCSettings
    from fvin_mpc.core.rigid_body import PENDULUM

    model = export.from_rigid_body(PENDULUM, 0.05, 2, name="test_multistart")
    settings = MPCSettings(compile="none", ipopt=IpoptOptions(max_iter=300))
    goal = (0.0, 0.0, 1.0, 0.0)
    q, omega = hinge(np.pi + 0.07, 0.9)
    _, single = MPC(model, settings, goal, [-2.0], [2.0])(np.r_[q, omega])
    multi_controller = MPC(model, replace(settings, cold_starts=COLD_STARTS), goal, [-2.0], [2.0])
    _, multi = multi_controller(np.r_[q, omega])
    assert multi["success"] and set(multi["cold_costs"]) == {"rollout+", "rollout-", "goal"}
    assert multi["cost"] == pytest.approx(np.nanmin(list(multi["cold_costs"].values())))
    # The single guess's plan passes through hanging; the multi-start's never leaves the top.
    def worst_angle(states):
        return float(s3.geodesic_angles(np.asarray(states)[:, :4], goal).max())
    assert worst_angle(single["states"]) > 2.0
    assert worst_angle(multi["states"]) < 0.5
    assert multi["cost"] < 0.1 * single["cost"]
    # Warm calls afterwards are single solves again.
    _, warm = multi_controller(np.r_[hinge(np.pi + 0.1, 0.5)])
    assert "cold_costs" not in warm


def test_multistart_rejects_unknown_guesses():
    from fvin_mpc.control.mpc import MPCSettings

    with pytest.raises(ValueError, match="cold_starts"):
        MPCSettings(cold_starts=("magic",))
    with pytest.raises(ValueError, match="cold_starts"):
        MPCSettings(cold_starts=())


def test_evaluation_mpc_settings_follow_the_scene_and_the_overrides():
    from fvin_mpc.control.mpc import COLD_STARTS
    from fvin_mpc.control.scene import scene_env, scene_mpc_settings

    default = ev.mpc_settings(ev.EvaluationConfig())
    assert default == scene_mpc_settings(scene_env("pendulum"))
    assert default.cold_starts == COLD_STARTS  # multi-start is the evaluated MPC unless --single-start
    override = ev.mpc_settings(ev.EvaluationConfig(mpc=(("horizon", 40), ("terminal_energy_weight", 0.0))))
    assert (override.horizon, override.terminal_energy_weight) == (40, 0.0)


@pytest.mark.slow
def test_evaluate_judges_a_free_body_as_fly_does(tmp_path):
    """A craft with no checkpoint: the closed form's recoveries and figure-eight, fly's report (a CasADi build)."""
    import json as json_module

    from fvin_mpc.envs.flyer_family import write_flyers
    from fvin_mpc.evaluate import main as evaluate_main

    (scene,) = write_flyers([7000], tmp_path)
    assert evaluate_main(["--scene", str(scene), "--episodes", "1", "--quiet", "--out-dir", str(tmp_path / "out")]) == 0
    report = json_module.loads((tmp_path / "out" / "quadrotor.json").read_text())
    assert list(report["models"]) == ["closed-form"]
    assert report["models"]["closed-form"]["summary"]["recovered_count"] == 1
