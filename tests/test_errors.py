"""User-facing errors (``fvin_mpc.core.errors``): one hierarchy, one line on stderr and exit status 2
from every command, and nonsensical input refused before any work (no MPC is built, nothing is
trained in this file: each refusal must come first)."""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fvin_mpc._cli import checked_scene_and_checkpoint, run_command
from fvin_mpc.core.checkpoint import CheckpointError
from fvin_mpc.core.errors import FvinMpcError, SceneError, UsageError

ROOT = Path(__file__).resolve().parents[1]
WEAK_PENDULUM = ROOT / "tests" / "data" / "weak_pendulum.xml"
#: The package's commands and the research studies' (``benchmarks/``: the dispatcher and the two with their own parser).
COMMAND_MODULES = sorted([*(ROOT / "fvin_mpc").glob("[!_]*.py"), *(ROOT / "benchmarks").glob("*_report.py"),
                          ROOT / "benchmarks" / "__main__.py"])


def one_error_line(stderr: str) -> str:
    """The single line a refused command printed; fails on a traceback or several lines."""
    assert "Traceback" not in stderr, stderr
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), stderr
    return lines[0]


def refused(main, argv, capsys) -> str:
    """Run a command's ``main`` as ``python -m`` does; it must exit 2 with one error line."""
    capsys.readouterr()
    assert run_command(main, argv) == 2
    return one_error_line(capsys.readouterr().err)


def refused_by_argparse(main, argv, capsys) -> str:
    """An option's value refused while parsing: through run_command, the same one line and exit 2 as any
    refusal (argparse's usage block left out), naming the option."""
    return refused(main, argv, capsys)


# ---------------------------------------------------------------------- the hierarchy and the wrapper
def test_the_user_facing_errors_share_one_root_and_stay_value_errors():
    for error in (CheckpointError, SceneError, UsageError):
        assert issubclass(error, FvinMpcError) and issubclass(error, ValueError)


def test_the_errors_module_imports_nothing_of_the_package():
    tree = ast.parse((ROOT / "fvin_mpc" / "core" / "errors.py").read_text())
    imported = [alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names]
    imported += [node.module or "" for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)]
    assert not [name for name in imported if name.startswith("fvin_mpc") or name == ""], imported


def test_run_command_prints_a_user_error_as_one_line_and_returns_2(capsys):
    def main(argv):
        raise SceneError("first line\n  second line")

    assert run_command(main, []) == 2
    assert capsys.readouterr().err == "error: first line second line\n"


def test_run_command_lets_a_bug_keep_its_traceback():
    def main(argv):
        raise KeyError("a bug")

    with pytest.raises(KeyError):
        run_command(main, [])


def test_run_command_passes_the_exit_status_through():
    assert run_command(lambda argv: 0, []) == 0
    assert run_command(lambda argv: 1, []) == 1


@pytest.mark.parametrize("path", COMMAND_MODULES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_command_runs_through_the_wrapper(path):
    """``python -m fvin_mpc.<cmd>`` exits through run_command(main), so every command gets the one-line errors."""
    tree = ast.parse(path.read_text())
    guards = [node for node in tree.body if isinstance(node, ast.If) and "__main__" in ast.unparse(node.test)]
    assert len(guards) == 1, f"{path.name} has no `if __name__ == '__main__'` block"
    assert "SystemExit(run_command(main))" in ast.unparse(guards[0]), ast.unparse(guards[0])


def test_the_command_line_prints_one_line_and_exits_2(tmp_path):
    """The real ``python -m`` path: the scene is checked before the checkpoint its name would lead to."""
    result = subprocess.run([sys.executable, "-m", "fvin_mpc.swingup", "--scene", "nope.xml", "--quiet"],
                            capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert result.returncode == 2
    line = one_error_line(result.stderr)
    assert "scene file does not exist" in line and "nope.xml" in line and "'pendulum'" in line
    assert "checkpoint" not in line and result.stdout == ""


# ---------------------------------------------------------------------- nonsensical values, before any work
@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", "ten"])
@pytest.mark.parametrize("command, argv", [("fvin_mpc.swingup", []), ("fvin_mpc.evaluate", []),
                                           ("benchmarks.spherical_report", ["closed-loop"])])
def test_a_duration_that_is_not_positive_is_refused_while_parsing(command, argv, value, capsys):
    import importlib

    main = importlib.import_module(command).main
    line = refused_by_argparse(main, [*argv, "--duration", value], capsys)
    assert "--duration" in line and ("must be > 0" in line or "expected a number > 0" in line)


@pytest.mark.parametrize("scene, message", [("nope.xml", "scene file does not exist: 'nope.xml'"),
                                            ("nope", "unknown scene 'nope'")])
def test_swingup_refuses_an_unknown_scene_naming_the_known_ones(scene, message, capsys):
    from fvin_mpc import swingup

    line = refused(swingup.main, ["--scene", scene, "--quiet"], capsys)
    assert message in line and "spherical_pendulum" in line and "checkpoint" not in line


@pytest.mark.parametrize("command", ["collect", "evaluate"])
def test_other_scene_commands_refuse_an_unknown_scene(command, capsys, tmp_path):
    import importlib

    main = importlib.import_module(f"fvin_mpc.{command}").main
    line = refused(main, ["--scene", str(tmp_path / "nope.xml"), "--quiet"], capsys)
    assert "scene file does not exist" in line and "'pendulum'" in line
    assert not (tmp_path / "data").exists()


def test_swingup_refuses_a_free_body_scene(capsys):
    from fvin_mpc import swingup

    line = refused(swingup.main, ["--scene", "quadrotor", "--quiet"], capsys)
    assert "free body" in line and "fvin_mpc.fly" in line


def test_a_bad_init_is_refused_before_the_controller_is_built(capsys, monkeypatch):
    from fvin_mpc import swingup

    def no_build(*args, **kwargs):
        raise AssertionError("the MPC was built before --init was checked")

    monkeypatch.setattr(swingup, "scene_mpc", no_build)
    assert "--init" in refused(swingup.main, ["--init", "abc", "--quiet"], capsys)
    assert "1 qpos and 1 qvel" in refused(swingup.main, ["--init", "0.1,0.2,0.3", "--quiet"], capsys)


@pytest.mark.parametrize("command, argv, message", [
    ("fly", ["--episodes", "0"], "--episodes must be >= 1"),
    ("benchmarks", ["ops", "--repeats", "0"], "--repeats must be >= 1"),
])
def test_other_bad_counts_are_one_line_errors(command, argv, message, capsys):
    import importlib

    module = importlib.import_module("benchmarks.__main__" if command == "benchmarks" else f"fvin_mpc.{command}")
    assert message in refused(module.main, argv, capsys)



@pytest.mark.parametrize("module, argv, message", [
    ("benchmarks.adaptation_heldout", ["--windows", "0"], "must be >= 1"),
    ("benchmarks.payload_adaptation", ["--low-rank", "1"], "add --models learned"),
])
def test_the_adaptation_benchmarks_refuse_what_they_cannot_run(module, argv, message, capsys):
    import importlib

    assert message in refused(importlib.import_module(module).main, argv, capsys)


@pytest.mark.parametrize("scene, collector, allowed", [
    ("pendulum", "bursts", "swings, random"),
    ("quadrotor", "swings", "bursts, stabilized-flight"),
])
def test_collect_refuses_a_collector_of_the_other_kind_of_scene(scene, collector, allowed, capsys, tmp_path):
    from fvin_mpc import collect

    message = refused(collect.main, ["--scene", scene, "--collector", collector, "--out", str(tmp_path / "d.npz"),
                                     "--quiet"], capsys)
    assert f"--collector {collector}" in message and allowed in message
    assert not (tmp_path / "d.npz").exists()

# ---------------------------------------------------------------------- checkpoints for another space or scene
def test_a_checkpoint_of_another_configuration_space_is_refused(capsys):
    from fvin_mpc import evaluate, swingup

    line = refused(swingup.main, ["--scene", "pendulum", "--checkpoint", "quadrotor_fixed-inertia", "--quiet"], capsys)
    assert "model on R3xS3" in line and "is on S3 ((q, ω) states)" in line
    line = refused(evaluate.main, ["--checkpoint", "quadrotor_fixed-inertia", "--controllers", "mpc-learned",
                                   "--quiet"], capsys)
    assert "R3xS3" in line


@pytest.mark.parametrize(
    "command, argv, message",
    [
        (
            "fvin_mpc.quality",
            ["--checkpoint", "quadrotor_fixed-inertia"],
            "is a free body and quality needs a body on a pivot",
        ),
        (
            "benchmarks.pendulum_v1_report",
            ["--checkpoint", "quadrotor_fixed-inertia", "--episodes", "1"],
            "a model on R3xS3",
        ),
        (
            "benchmarks.pendulum_v1_report",
            ["--checkpoint", "spherical_pendulum_sign-invariant", "--episodes", "1"],
            "has 3 controls",
        ),
        ("fvin_mpc.export", ["--checkpoint", "no-such-model"], "checkpoint file not found"),
    ],
)
def test_checkpoint_commands_refuse_a_model_they_cannot_use(command, argv, message, capsys, tmp_path):
    import importlib

    main = importlib.import_module(command).main
    writes_a_report = command == "benchmarks.pendulum_v1_report"
    assert message in refused(main, [*argv, "--out" if writes_a_report else "--seed",
                                     str(tmp_path / "out.md") if writes_a_report else "0"], capsys)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("command", ["train", "quality", "sweep"])
def test_a_missing_data_file_is_a_one_line_error(command, capsys, tmp_path):
    import importlib

    from fvin_mpc.core.errors import DataFileNotFound

    assert issubclass(DataFileNotFound, FileNotFoundError)
    main = importlib.import_module(f"fvin_mpc.{command}").main
    assert "data file not found" in refused(main, ["--data", str(tmp_path / "absent.npz")], capsys)


def test_fly_refuses_a_pivoted_checkpoint_before_building_anything(capsys):
    from fvin_mpc import fly

    line = refused(fly.main, ["--checkpoint", "pendulum_sign-invariant", "--episodes", "1", "--quiet"], capsys)
    assert "pendulum_sign-invariant" in line and "R3xS3" in line


def test_a_default_checkpoint_of_another_scene_is_refused(tmp_path, capsys):
    """A user's own ``pendulum.xml`` is not the built-in pendulum: the shipped model its name leads to
    was trained on the built-in scene, and the user never chose it."""
    scene = tmp_path / "pendulum.xml"
    shutil.copy(WEAK_PENDULUM, scene)
    from fvin_mpc import swingup

    line = refused(swingup.main, ["--scene", str(scene), "--quiet"], capsys)
    assert "default checkpoint 'pendulum_sign-invariant'" in line and "--checkpoint" in line


def test_a_scene_without_a_model_says_how_to_get_one(tmp_path, capsys, monkeypatch):
    shutil.copy(WEAK_PENDULUM, tmp_path / "arm.xml")
    monkeypatch.chdir(tmp_path)
    from fvin_mpc import swingup

    line = refused(swingup.main, ["--scene", "arm.xml", "--quiet"], capsys)
    assert "no trained model" in line and "arm_sign-invariant" in line and "--true-model" in line


def test_an_explicit_checkpoint_of_another_scene_in_the_same_space_is_allowed(capsys):
    """A model of one pendulum tried on another is the user's choice: allowed, with a note."""
    spec, checkpoint = checked_scene_and_checkpoint(str(WEAK_PENDULUM), "pendulum_sign-invariant")
    assert spec.name == "weak_pendulum" and checkpoint.scene == "pendulum"
    assert "trained on scene 'pendulum'" in capsys.readouterr().err


def test_a_checkpoint_of_its_own_scene_passes_and_true_model_needs_none():
    spec, checkpoint = checked_scene_and_checkpoint("pendulum")
    assert spec.name == "pendulum" and checkpoint.scene == "pendulum"
    assert checked_scene_and_checkpoint(str(WEAK_PENDULUM), "no-such-checkpoint", true_model=True)[1] is None
    spec, checkpoint = checked_scene_and_checkpoint(str(WEAK_PENDULUM))  # shipped, recorded as a relative path
    assert checkpoint.scene == "tests/data/weak_pendulum.xml"


# ---------------------------------------------------------------------- train's default output
@pytest.fixture()
def pendulum_data(tmp_path):
    from helpers import synthetic_hinge_data

    from fvin_mpc.core.data import Trajectories, save_data
    from fvin_mpc.core.rigid_body import PENDULUM

    data = synthetic_hinge_data(PENDULUM, trajectories=4, steps=3)
    data = Trajectories(data.state, data.u, {**data.metadata, "scene": "pendulum"})
    return save_data(tmp_path / "pendulum.npz", data)


def test_train_refuses_to_overwrite_an_existing_checkpoint_by_default(pendulum_data, tmp_path, capsys, monkeypatch):
    from fvin_mpc import train

    monkeypatch.chdir(tmp_path)
    existing = tmp_path / "checkpoints" / "pendulum_sign-invariant.json"
    existing.parent.mkdir()
    existing.write_text("an earlier model\n")

    def no_training(*args, **kwargs):
        raise AssertionError("trained before checking the output name")

    monkeypatch.setattr(train, "train_model", no_training)
    line = refused(train.main, ["--data", str(pendulum_data), "--quiet"], capsys)
    assert "checkpoints/pendulum_sign-invariant" in line and "--force" in line and "--out" in line
    assert existing.read_text() == "an earlier model\n"
    with pytest.raises(AssertionError, match="trained before"):  # --force (or --out) goes on to train
        train.main(["--data", str(pendulum_data), "--quiet", "--force"])


def test_the_free_body_training_refuses_to_overwrite_too(tmp_path, capsys, monkeypatch):
    from fvin_mpc import train
    from fvin_mpc.core.data import save_data
    from fvin_mpc.learning.collection import collect_quadrotor

    monkeypatch.chdir(tmp_path)
    data = tmp_path / "quadrotor.npz"
    save_data(data, collect_quadrotor(trajectories=2, steps=3, seed=0, progress=False))
    existing = tmp_path / "checkpoints" / "quadrotor_fixed-inertia.safetensors"
    existing.parent.mkdir()
    existing.write_bytes(b"weights")
    monkeypatch.setattr(train, "train_model", lambda *a, **k: pytest.fail("trained before checking"))
    assert "--force" in refused(train.main, ["--data", str(data), "--quiet"], capsys)
    assert existing.read_bytes() == b"weights"


def test_the_default_output_follows_the_data_file_unless_it_is_named_after_the_scene(tmp_path):
    from fvin_mpc.core.data import Trajectories
    from fvin_mpc.learning.training import default_output_stem, refuse_to_overwrite

    data = Trajectories.from_parts(np.zeros((1, 2, 4)), np.zeros((1, 2, 3)), np.zeros((1, 1, 1)),
                                   {"control_period": 0.05, "scene": "/any/path/arm.xml"})
    assert default_output_stem(data, "data/arm.npz", "plain").as_posix() == "checkpoints/arm_plain"
    assert default_output_stem(data, "data/other.npz", "plain").as_posix() == "checkpoints/other_plain"
    refuse_to_overwrite(tmp_path / "absent", force=False)
    (tmp_path / "present.json").write_text("{}")
    refuse_to_overwrite(tmp_path / "present", force=True)
    with pytest.raises(UsageError, match="--force"):
        refuse_to_overwrite(tmp_path / "present", force=False)


# ---------------------------------------------------------------------- swingup's default duration
def test_the_default_duration_leaves_room_for_a_weak_motor_and_keeps_10_s_on_the_pendulum():
    from fvin_mpc.control.closed_loop import HOLD_WINDOW_S
    from fvin_mpc.control.scene import scene_scales
    from fvin_mpc.envs import RigidBodyEnv
    from fvin_mpc.swingup import build_parser, default_duration

    assert default_duration(scene_scales(RigidBodyEnv("pendulum"))) == 10.0
    weak = default_duration(scene_scales(RigidBodyEnv(str(WEAK_PENDULUM))))
    # docs/custom_scene.md: upright at 5.78 s after four pumps; the hold window must fit after that.
    assert weak > 5.78 + HOLD_WINDOW_S and weak == pytest.approx(6 * 4 * np.pi / np.sqrt(60) + 3, rel=1e-6)
    assert build_parser().parse_args([]).duration is None  # so main derives it from the scene
    assert "gravity torque / motor torque" in " ".join(build_parser().format_help().split())
