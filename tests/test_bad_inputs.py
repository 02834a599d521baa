"""The bad-input suite: every command, given what a new user gets wrong, refuses it at its edge
in one line — exit status 2, exactly one line on stderr, ``error: …``, no traceback — before any work, and
leaves every file in its folder as it was.

Two halves:

* :data:`CASES`, a table of named cases (the command, its argv, the broken files it is given, a fragment of
  the line it must print), run in-process through the command's ``main`` and ``run_command`` (what
  ``python -m`` runs) in a fresh folder that is the working directory. ``docs/bad-inputs.md`` is this
  table with the line each case gets; regenerate it with ``python tests/test_bad_inputs.py``.
* Hypothesis over broken MJCFs (physics a body cannot have), data files (NaN, non-unit quaternions, cut
  or foreign bytes, bad metadata), checkpoint sidecars and option values: a few examples each in the
  default suite, many under ``-m slow``.

Ctrl-C is checked twice: in-process (one line, status 130) and on a real ``python -m`` run interrupted
mid-episode (nothing half written).
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

ROOT = Path(__file__).resolve().parents[1]
CHECKPOINTS = ROOT / "checkpoints"
PENDULUM_XML = (ROOT / "envs" / "scenes" / "pendulum.xml").read_text()
QUADROTOR_XML = (ROOT / "envs" / "scenes" / "quadrotor.xml").read_text()
MOTOR = '<motor name="torque" joint="hinge" gear="1" ctrlrange="-2 2" ctrllimited="true"/>'
ROD_INERTIA = 'mass="1" diaginertia="0.083333333333 0.083333333333 1e-6"'
#: What the commands need to stop printing progress and plots where the case does not test them.
QUIET = ("--quiet",)
NO_PLOT = ("--plot", "")

Setup = Callable[[Path], None]


# ---------------------------------------------------------------------- what a case is given
def text_file(name: str, text: str) -> Setup:
    def setup(folder: Path) -> None:
        path = folder / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return setup


def byte_file(name: str, data: bytes) -> Setup:
    def setup(folder: Path) -> None:
        (folder / name).write_bytes(data)
    return setup


def a_folder(name: str) -> Setup:
    def setup(folder: Path) -> None:
        (folder / name).mkdir(parents=True, exist_ok=True)
    return setup


def pendulum(*replacements: tuple[str, str]) -> str:
    """The built-in pendulum's MJCF with ``(old, new)`` replacements (each must apply)."""
    text = PENDULUM_XML
    for old, new in replacements:
        assert old in text, old
        text = text.replace(old, new)
    return text


def craft(*replacements: tuple[str, str]) -> str:
    text = QUADROTOR_XML
    for old, new in replacements:
        assert old in text, old
        text = text.replace(old, new)
    return text


def scene(name: str, *replacements: tuple[str, str]) -> Setup:
    return text_file(f"{name}.xml", pendulum(*replacements))


def craft_scene(name: str, *replacements: tuple[str, str]) -> Setup:
    return text_file(f"{name}.xml", craft(*replacements))


_BASE_DATA: dict[str, Any] = {}


def base_data() -> Any:
    """A small real data set of the pendulum (4 trajectories of 8 steps at its 50 ms), collected once."""
    if "pendulum" not in _BASE_DATA:
        from fvin_mpc.learning.collection import collect

        _BASE_DATA["pendulum"] = collect("pendulum", trajectories=4, steps=8, seed=0, progress=False)
    return _BASE_DATA["pendulum"]


def data_file(name: str, edit: Callable[[np.ndarray, np.ndarray, dict], tuple] | None = None) -> Setup:
    """The base data, edited (``edit(state, u, metadata) -> (state, u, metadata)`` on copies), written
    with NumPy directly (as a user's own script would; the package's writer checks nothing)."""
    def setup(folder: Path) -> None:
        data = base_data()
        state, u, metadata = data.state.copy(), data.u.copy(), dict(data.metadata)
        if edit is not None:
            state, u, metadata = edit(state, u, metadata)
        np.savez_compressed(folder / name, state=state, u=u, metadata=json.dumps(metadata))
    return setup


def checkpoint_copy(stem: str, shipped: str = "pendulum_sign-invariant",
                    edit: Callable[[dict], None] | None = None) -> Setup:
    """A shipped checkpoint's pair copied as ``stem.{json,safetensors}``, its sidecar edited."""
    def setup(folder: Path) -> None:
        shutil.copy(CHECKPOINTS / f"{shipped}.safetensors", folder / f"{stem}.safetensors")
        sidecar = json.loads((CHECKPOINTS / f"{shipped}.json").read_text())
        if edit is not None:
            edit(sidecar)
        (folder / f"{stem}.json").write_text(json.dumps(sidecar))
    return setup


def _set(path: tuple[str, ...], value: Any) -> Callable[[dict], None]:
    def edit(sidecar: dict) -> None:
        target = sidecar
        for key in path[:-1]:
            target = target[key]
        target[path[-1]] = value
    return edit


# ---------------------------------------------------------------------- the cases
@dataclass(frozen=True)
class Case:
    """One bad input: ``python -m fvin_mpc.<command> <argv>`` in a folder prepared by ``setup``; the one line
    it prints must contain ``message`` (``loose``: any one line — an option ``train`` validates, whose
    words are its own)."""

    name: str
    command: str
    argv: tuple[str, ...]
    message: str
    setup: tuple[Setup, ...] = ()
    loose: bool = False
    without_torch: bool = False


def case(name: str, command: str, argv: str | tuple[str, ...], message: str, *setup: Setup, loose: bool = False,
         without_torch: bool = False) -> Case:
    args = tuple(argv.split()) if isinstance(argv, str) else argv
    return Case(name, command, args, message, setup, loose, without_torch)


def _nan_state(state, u, metadata):
    state[1, 3, 5] = np.nan
    return state, u, metadata


def _inf_control(state, u, metadata):
    u[2, 1, 0] = np.inf
    return state, u, metadata


def _long_quaternions(state, u, metadata):
    state[..., :4] *= 2.0
    return state, u, metadata


def _wide_controls(state, u, metadata):
    return state, np.concatenate([u, u], axis=2), metadata


def _one_trajectory(state, u, metadata):
    return state[:1], u[:1], metadata


def _other_period(state, u, metadata):
    return state, u, {**metadata, "control_period": 0.02}


def _no_period(state, u, metadata):
    return state, u, {key: value for key, value in metadata.items() if key != "control_period"}


def _zero_period(state, u, metadata):
    return state, u, {**metadata, "control_period": 0.0}


def _unknown_space(state, u, metadata):
    return state, u, {**metadata, "configuration_space": "S7"}


def _no_steps(state, u, metadata):
    return state[:, :1], u[:, :0], metadata


def _bad_shapes(state, u, metadata):
    return state[:, :, :5], u, metadata


PIVOT = ("--true-model", *QUIET, *NO_PLOT)  # swingup on the closed form: the scene is all that is judged
EXISTING_NPZ = data_file("existing.npz")
PENDULUM_DATA = data_file("pendulum.npz")

SWINGUP = [
    case("horizon 0", "swingup", "--horizon 0", "argument --horizon: must be >= 1"),
    case("horizon without bound", "swingup", "--horizon 100000", "argument --horizon: must be <= 1000"),
    case("horizon not a number", "swingup", "--horizon ten", "argument --horizon: expected a whole number"),
    case("max-iter 0", "swingup", "--max-iter 0", "argument --max-iter: must be >= 1"),
    case("cold-max-iter negative", "swingup", "--cold-max-iter -1", "argument --cold-max-iter: must be >= 1"),
    case("torque reserve 2", "swingup", "--torque-reserve 2", "argument --torque-reserve: must be < 1"),
    case("torque reserve negative", "swingup", "--torque-reserve -0.1", "argument --torque-reserve: must be >= 0"),
    case("negative energy weight", "swingup", "--energy-weight -1", "argument --energy-weight: must be >= 0"),
    case("NaN omega weight", "swingup", "--omega-weight nan", "argument --omega-weight: must be a finite number"),
    case("infinite control weight", "swingup", "--control-weight inf", "must be a finite number"),
    case("negative terminal weight", "swingup", "--terminal-omega-weight -2", "must be >= 0"),
    case("goal of zeros", "swingup", "--goal 0 0 0 0", "--goal must be a nonzero quaternion"),
    case("goal with NaN", "swingup", "--goal nan 0 0 1", "argument --goal: must be a finite number"),
    case("goal of three numbers", "swingup", "--goal 1 0 0", "argument --goal: expected 4 arguments"),
    case("init NaN", "swingup", ("--init", "nan,0", *PIVOT), "--init: every number must be finite"),
    case("init not numbers", "swingup", ("--init", "abc", *PIVOT), "--init: expected rest, random"),
    case("init of another joint", "swingup", ("--init", "0.1,0.2,0.3", *PIVOT), "1 qpos and 1 qvel"),
    case("newton-iters negative", "swingup", "--newton-iters -3", "argument --newton-iters: must be >= 1"),
    case("newton-iters 0 is no default", "swingup", "--newton-iters 0", "argument --newton-iters: must be >= 1"),
    case("newton-iters without bound", "swingup", "--newton-iters 1000", "argument --newton-iters: must be <= 20"),
    case("duration 0", "swingup", "--duration 0", "argument --duration: must be > 0"),
    case("duration without bound", "swingup", "--duration 1e12", "argument --duration: must be <= 3600"),
    case("duration NaN", "swingup", "--duration nan", "argument --duration: must be > 0"),
    case("seed negative", "swingup", "--seed -1", "argument --seed: must be >= 0"),
    case("control period 0", "swingup", "--control-period 0", "argument --control-period: must be > 0"),
    case("control period NaN", "swingup", "--control-period nan", "argument --control-period: must be > 0"),
    case("control period off the timestep", "swingup", ("--control-period", "0.0123", *PIVOT),
         "must be a whole multiple of the MJCF timestep"),
    case("control period past the step's reach", "swingup", ("--control-period", "0.2", *PIVOT),
         "past the 1 rad a model's step can take"),
    case("latency negative", "swingup", "--latency -1", "a fixed latency must be finite seconds >= 0"),
    case("latency infinite", "swingup", "--latency inf", "a fixed latency must be finite seconds >= 0"),
    case("latency a word", "swingup", "--latency soon", "expected none, measured or seconds"),
    case("unknown solver", "swingup", "--solver newton", "argument --solver: invalid choice"),
    case("unknown option", "swingup", "--horizn 30", "unrecognized arguments: --horizn 30"),
    case("plot without a suffix", "swingup", "--plot out", "--plot out: expected a file ending in .png"),
    case("plot a folder", "swingup", "--plot plots", "--plot plots is a folder", a_folder("plots")),
    case("plot under a file", "swingup", "--plot notes.txt/run.png", "notes.txt is a file, not a folder",
         text_file("notes.txt", "mine\n")),
    case("video not a video", "swingup", "--video run.gif", "--video run.gif: expected a file ending in .mp4"),
    case("json a folder", "swingup", "--json out", "--json out is a folder", a_folder("out")),
    case("scene file missing", "swingup", "--scene nope.xml", "scene file does not exist: 'nope.xml'"),
    case("scene name unknown", "swingup", "--scene nope", "unknown scene 'nope'"),
    case("free body for swing-up", "swingup", "--scene quadrotor", "free body and swingup needs a body on a pivot"),
    case("checkpoint missing", "swingup", "--checkpoint no-such-model", "checkpoint file not found"),
    case("checkpoint of another space", "swingup", "--checkpoint quadrotor_fixed-inertia", "model on R3xS3"),
    case("body missing", "swingup", ("--body", "arm", *PIVOT), "no body named 'arm'"),
]

MJCF = [  # the MJCF reader: physics a body cannot have, refused before any work (swingup on the closed form)
    case("gear 0", "swingup", ("--scene", "gear0.xml", *PIVOT), "has gear 0", scene("gear0", ('gear="1"', 'gear="0"'))),
    case("gear NaN", "swingup", ("--scene", "gearnan.xml", *PIVOT), "holds a NaN where a number belongs",
         scene("gearnan", ('gear="1"', 'gear="nan"'))),
    case("gear 1e12", "swingup", ("--scene", "gearbig.xml", *PIVOT), "does not resolve the body's speed scale",
         scene("gearbig", ('gear="1"', 'gear="1e12"'))),
    case("ctrlrange missing", "swingup", ("--scene", "noctrl.xml", *PIVOT), "has no control bounds",
         scene("noctrl", (' ctrlrange="-2 2" ctrllimited="true"', ""))),
    case("ctrlrange infinite", "swingup", ("--scene", "infctrl.xml", *PIVOT), "a bound must be finite",
         scene("infctrl", ('ctrlrange="-2 2"', 'ctrlrange="-inf inf"'))),
    case("clamping switched off", "swingup", ("--scene", "clampoff.xml", *PIVOT), "control clamping is switched off",
         scene("clampoff", ('<flag contact="disable"/>', '<flag contact="disable" clampctrl="disable"/>'))),
    case("timestep 0", "swingup", ("--scene", "ts0.xml", *PIVOT), "timestep must be a finite number of seconds > 0",
         scene("ts0", ('timestep="0.005"', 'timestep="0"'))),
    case("timestep negative", "swingup", ("--scene", "tsneg.xml", *PIVOT), "got -0.005",
         scene("tsneg", ('timestep="0.005"', 'timestep="-0.005"'))),
    case("timestep 1 s", "swingup", ("--scene", "ts1.xml", *PIVOT), "the timestep 1 s does not resolve",
         scene("ts1", ('timestep="0.005"', 'timestep="1"'))),
    case("body of 1e-9 kg", "swingup", ("--scene", "light.xml", *PIVOT), "does not resolve the body's speed scale",
         scene("light", (ROD_INERTIA, 'mass="1e-9" diaginertia="8e-11 8e-11 1e-15"'))),
    case("body of 1e30 kg", "swingup", ("--scene", "heavy.xml", *PIVOT), "the motor cannot move the body",
         scene("heavy", (ROD_INERTIA, 'mass="1e30" diaginertia="8e28 8e28 1e24"'))),
    case("position servo", "swingup", ("--scene", "servo.xml", *PIVOT), "has a bias (a <position> or <velocity> servo",
         scene("servo", (MOTOR, '<position name="torque" joint="hinge" kp="10" ctrlrange="-2 2"/>'))),
    case("velocity servo", "swingup", ("--scene", "velservo.xml", *PIVOT), "has a bias",
         scene("velservo", (MOTOR, '<velocity name="torque" joint="hinge" kv="3" ctrlrange="-2 2"/>'))),
    case("motor with a gain", "swingup", ("--scene", "gain.xml", *PIVOT), "has gain 5",
         scene("gain", (MOTOR, '<general name="torque" joint="hinge" gainprm="5" ctrlrange="-2 2"/>'))),
    case("actuator with dynamics", "swingup", ("--scene", "filter.xml", *PIVOT), "has dynamics (dyntype mjDYN_FILTER)",
         scene("filter", (MOTOR, '<general name="torque" joint="hinge" dyntype="filter" dynprm="0.1" '
                                 'ctrlrange="-2 2"/>'))),
    case("no actuator", "swingup", ("--scene", "noact.xml", *PIVOT), "its joint is not actuated",
         scene("noact", (MOTOR, ""))),
    case("slide joint", "swingup", ("--scene", "slide.xml", *PIVOT), "its joint must be a hinge or a ball",
         scene("slide", ('type="hinge" axis="0 1 0"', 'type="slide" axis="0 1 0"'))),
    case("joint limits", "swingup", ("--scene", "limited.xml", *PIVOT), "joint limits",
         scene("limited", ('armature="0"/>', 'armature="0" range="-1 1" limited="true"/>'))),
    case("no gravity, no task", "swingup", ("--scene", "nograv.xml", *PIVOT), "the potential has no maximum",
         scene("nograv", ('gravity="0 0 -10"', 'gravity="0 0 0"'))),
    case("gravity NaN", "swingup", ("--scene", "gravnan.xml", *PIVOT), "holds a NaN",
         scene("gravnan", ('gravity="0 0 -10"', 'gravity="0 0 nan"'))),
    case("mass NaN", "swingup", ("--scene", "massnan.xml", *PIVOT), "could not compile MJCF",
         scene("massnan", ('mass="1"', 'mass="nan"'))),
    case("reversed ctrlrange", "swingup", ("--scene", "ctrlrev.xml", *PIVOT), "invalid control range",
         scene("ctrlrev", ('ctrlrange="-2 2"', 'ctrlrange="2 -2"'))),
    case("not an MJCF", "swingup", ("--scene", "notes.xml", *PIVOT), "could not compile MJCF 'notes.xml'",
         text_file("notes.xml", "my notes, not an MJCF\n")),
    case("empty MJCF", "swingup", ("--scene", "empty.xml", *PIVOT), "empty file", text_file("empty.xml", "")),
]

COLLECT = [
    case("trajectories 0 is no default", "collect", "--trajectories 0", "argument --trajectories: must be >= 1"),
    case("steps 0 is no default", "collect", "--steps 0", "argument --steps: must be >= 1"),
    case("steps negative", "collect", "--steps -1", "argument --steps: must be >= 1"),
    case("hold-steps 0", "collect", "--hold-steps 0", "argument --hold-steps: must be >= 1"),
    case("max-omega negative", "collect", "--max-omega -1", "argument --max-omega: must be >= 0"),
    case("near-goal angle past a half turn", "collect", "--near-goal-angle 4",
         "argument --near-goal-angle: must be <="),
    case("max-speed 0", "collect", "--max-speed 0", "argument --max-speed: must be > 0"),
    case("control period 0", "collect", "--control-period 0", "argument --control-period: must be > 0"),
    case("seed negative", "collect", "--seed -1", "argument --seed: must be >= 0"),
    case("existing data without --force", "collect", "--out existing.npz --quiet",
         "--out existing.npz exists; pass --force", EXISTING_NPZ),
    case("default output exists", "collect", "--quiet", "--out data/pendulum.npz exists; pass --force",
         text_file("data/pendulum.npz", "an earlier data set")),
    case("output a folder", "collect", "--out runs --quiet", "--out runs is a folder", a_folder("runs")),
    case("output not .npz", "collect", "--out data.txt --quiet", "expected a file ending in .npz"),
    case("collector of the other kind", "collect", "--collector bursts --out d.npz --quiet",
         "--collector bursts does not record a pivoted scene"),
    case("random-only option with swings", "collect", "--max-omega 3 --out d.npz --quiet",
         "--max-omega applies to --collector random only"),
    case("scene with gear 0", "collect", "--scene gear0.xml --out d.npz --quiet", "has gear 0",
         scene("gear0", ('gear="1"', 'gear="0"'))),
    case("scene of 1e30 kg", "collect", "--scene heavy.xml --out d.npz --quiet", "the motor cannot move the body",
         scene("heavy", (ROD_INERTIA, 'mass="1e30" diaginertia="8e28 8e28 1e24"'))),
    case("scene with a servo", "collect", "--scene servo.xml --out d.npz --quiet", "has a bias",
         scene("servo", (MOTOR, '<position name="torque" joint="hinge" kp="10" ctrlrange="-2 2"/>'))),
    case("scene with timestep 1 s", "collect", "--scene ts1.xml --out d.npz --quiet", "does not resolve",
         scene("ts1", ('timestep="0.005"', 'timestep="1"'))),
    case("craft below its weight", "collect", "--scene weak.xml --out d.npz --quiet", "the craft cannot hover",
         craft_scene("weak", ('ctrlrange="0 2.5"', 'ctrlrange="0 1"'))),
    case("craft of 1e-9 kg", "collect", "--scene feather.xml --out d.npz --quiet", "does not resolve the craft's rates",
         craft_scene("feather", ('mass="0.5" diaginertia="0.0023 0.0029 0.0046"',
                                 'mass="1e-9" diaginertia="2.3e-12 2.9e-12 4.6e-12"'))),
    case("craft without thrust bounds", "collect", "--scene free.xml --out d.npz --quiet", "has no control bounds",
         craft_scene("free", (' ctrlrange="0 2.5" ctrllimited="true"', ""))),
]

TRAIN = [  # the data files are the package's loader's; train's own options are loose (their words are train's)
    case("data missing", "train", "--data absent.npz --out m --quiet", "data file not found: absent.npz"),
    case("data an empty file", "train", "--data empty.npz --out m --quiet", "empty.npz: the file is empty",
         byte_file("empty.npz", b"")),
    case("data a text file", "train", "--data notes.npz --out m --quiet", "not a NumPy archive of trajectories",
         text_file("notes.npz", "some notes\n")),
    case("data a folder", "train", "--data runs --out m --quiet", "runs: a folder, not a data file", a_folder("runs")),
    case("data a checkpoint", "train", "--data model.safetensors --out m --quiet", "a checkpoint's file, not data",
         checkpoint_copy("model")),
    case("data with NaN states", "train", "--data nan.npz --out m --quiet", "state[1, 3, 5] is nan",
         data_file("nan.npz", _nan_state)),
    case("data with infinite controls", "train", "--data inf.npz --out m --quiet", "u[2, 1, 0] is inf",
         data_file("inf.npz", _inf_control)),
    case("data with non-unit quaternions", "train", "--data long.npz --out m --quiet", "has norm 2",
         data_file("long.npz", _long_quaternions)),
    case("data of the wrong control width", "train", "--data wide.npz --out m --quiet",
         "the data have 2 controls per step, and their scene 'pendulum' has 1 actuators",
         data_file("wide.npz", _wide_controls)),
    case("data of one trajectory", "train", "--data one.npz --out m --quiet", "training holds at least one out",
         data_file("one.npz", _one_trajectory)),
    case("data without a control period", "train", "--data noperiod.npz --out m --quiet",
         "control_period must be finite seconds > 0", data_file("noperiod.npz", _no_period)),
    case("data of an unknown space", "train", "--data s7.npz --out m --quiet", "unknown configuration space 'S7'",
         data_file("s7.npz", _unknown_space)),
    case("data without steps", "train", "--data nosteps.npz --out m --quiet", "no transitions",
         data_file("nosteps.npz", _no_steps)),
    case("data of the wrong state width", "train", "--data narrow.npz --out m --quiet",
         "inconsistent trajectory shapes",
         data_file("narrow.npz", _bad_shapes)),
    case("train variant unknown", "train", "--data pendulum.npz --variant bogus --out m --quiet", "", PENDULUM_DATA,
         loose=True),
    case("train existing default output", "train", "--data pendulum.npz --quiet", "--force", PENDULUM_DATA,
         text_file("checkpoints/pendulum_sign-invariant.json", "{}"), loose=True),
]

EVALUATE = [
    case("episodes 0", "evaluate", "--episodes 0", "episodes must be >= 1"),
    case("duration 0", "evaluate", "--duration 0", "argument --duration: must be > 0"),
    case("duration without bound", "evaluate", "--duration 1e12", "argument --duration: must be <= 3600"),
    case("controllers unknown", "evaluate", "--controllers bogus --quiet", "unknown controllers"),
    case("workers 0", "evaluate", "--workers 0 --quiet", "--workers must be >= 1"),
    case("ray address without ray", "evaluate", "--ray-address auto --quiet", "--ray-address needs --backend ray"),
    case("seed negative", "evaluate", "--seed -1", "argument --seed: must be >= 0"),
    case("max-omega negative", "evaluate", "--max-omega -1", "argument --max-omega: must be >= 0"),
    case("out-dir holds a report", "evaluate", "--out-dir study --quiet", "--out-dir study already holds evaluation.md",
         text_file("study/evaluation.md", "my study\n")),
    case("default out-dir holds a report", "evaluate", "--quiet", "--out-dir evaluation already holds evaluation.json",
         text_file("evaluation/evaluation.json", "{}\n")),
    case("out-dir a file", "evaluate", "--out-dir notes.txt --quiet", "--out-dir notes.txt is a file",
         text_file("notes.txt", "mine\n")),
    case("json a folder", "evaluate", "--json out --quiet", "--json out is a folder", a_folder("out")),
    case("scene timestep 1 s", "evaluate", "--scene ts1.xml --controllers mpc-true --quiet", "does not resolve",
         scene("ts1", ('timestep="0.005"', 'timestep="1"'))),
    case("checkpoint of another space", "evaluate", "--checkpoint quadrotor_fixed-inertia --controllers mpc-learned "
         "--quiet", "R3xS3"),
    case("horizon 0", "evaluate", "--horizon 0", "argument --horizon: must be >= 1"),
    case("latency negative", "evaluate", "--latency -0.1", "a fixed latency must be finite seconds >= 0"),
]


def _quadrotor_step(value: float) -> Setup:
    return checkpoint_copy("fast", "quadrotor_fixed-inertia", _set(("model", "step_size"), value))


FLY = [
    case("episodes 0", "fly", "--episodes 0", "--episodes must be >= 1"),
    case("seed negative", "fly", "--seed -1", "argument --seed: must be >= 0"),
    case("checkpoint of a pivot", "fly", "--checkpoint pendulum_sign-invariant --quiet", "R3xS3"),
    case("checkpoint of another period", "fly", "--checkpoint fast --episodes 1 --quiet",
         "steps at 0.01 s and scene 'quadrotor' is flown at 0.02 s", _quadrotor_step(0.01)),
    case("report with a checkpoint of another period", "fly", "--checkpoint fast --report study --quiet",
         "steps at 0.01 s", _quadrotor_step(0.01)),
    case("scene a pivot", "fly", "--scene pendulum --model closed-form --quiet", "is a body on a pivot"),
    case("craft below its weight", "fly", "--scene weak.xml --model closed-form --quiet", "the craft cannot hover",
         craft_scene("weak", ('ctrlrange="0 2.5"', 'ctrlrange="0 1"'))),
    case("craft of 1e30 kg", "fly", "--scene lead.xml --model closed-form --quiet", "the craft cannot hover",
         craft_scene("lead", ('mass="0.5" diaginertia="0.0023 0.0029 0.0046"',
                              'mass="1e30" diaginertia="2.3e27 2.9e27 4.6e27"'))),
    case("craft timestep 0.1 s", "fly", "--scene slow.xml --model closed-form --quiet", "does not resolve the craft's",
         craft_scene("slow", ('timestep="0.002"', 'timestep="0.1"'))),
    case("craft rotor gear NaN", "fly", "--scene nan.xml --model closed-form --quiet", "holds a NaN",
         craft_scene("nan", ('site="rotor0" gear="0 0 1 0 0 0.016"', 'site="rotor0" gear="0 0 nan 0 0 0.016"'))),
    case("plot without a suffix", "fly", "--plot flight --quiet", "--plot flight: expected a file ending in .png"),
    case("plot a folder", "fly", "--plot plots --quiet", "--plot plots is a folder", a_folder("plots")),
    case("video not a video", "fly", "--video run.png --quiet", "--video run.png: expected a file ending in .mp4"),
    case("still without a video", "fly", "--still strip.png --quiet", "--still is a strip of the video's frames"),
    case("report folder holds a report", "fly", "--report study --quiet", "--report study already holds quadrotor.md",
         text_file("study/quadrotor.md", "my study\n")),
    case("report a file", "fly", "--report notes.txt --quiet", "--report notes.txt is a file",
         text_file("notes.txt", "mine\n")),
    case("report with kept Jacobians", "fly", "--report study --rti-relinearize-every 2 --quiet",
         "leave out --rti-relinearize-every"),
    case("json a folder", "fly", "--json out --quiet", "--json out is a folder", a_folder("out")),
    case("relinearize every 0", "fly", "--rti-relinearize-every 0", "argument --rti-relinearize-every: must be >= 1"),
    case("latency NaN", "fly", "--latency nan", "a fixed latency must be finite seconds >= 0"),
    case("task unknown", "fly", "--task loop", "argument --task: invalid choice"),
]

EXPORT = [
    case("newton-iters 0", "export", "--newton-iters 0", "argument --newton-iters: must be >= 1"),
    case("newton-iters without bound", "export", "--newton-iters 100", "argument --newton-iters: must be <= 20"),
    case("checkpoint missing", "export", "--checkpoint no-such-model", "checkpoint file not found"),
    case("existing step without --force", "export", "--out step.casadi", "--out step.casadi exists; pass --force",
         text_file("step.casadi", "an earlier export")),
    case("step not .casadi", "export", "--out step.txt", "--out step.txt: expected a file ending in .casadi"),
    case("true model without --controller", "export", "--true-model", "--true-model and --build go with --controller"),
    case("controller folder holds a library", "export", "--controller lib --true-model",
         "--controller lib already holds Makefile", text_file("lib/Makefile", "all:\n")),
    case("controller a file", "export", "--controller notes.txt --true-model", "--controller notes.txt is a file",
         text_file("notes.txt", "mine\n")),
    case("controller of a broken scene", "export", "--controller lib --true-model --scene gear0.xml", "has gear 0",
         scene("gear0", ('gear="1"', 'gear="0"'))),
    case("controller of a craft checkpoint of another period", "export", "--controller lib --scene quadrotor "
         "--checkpoint fast", "steps at 0.01 s", _quadrotor_step(0.01)),
    case("seed negative", "export", "--seed -1", "argument --seed: must be >= 0"),
]

LEARN = [
    case("without torch", "learn", "--quiet", "learn trains models and needs torch", without_torch=True),
    case("budget 0", "learn", "--budget 0", "argument --budget: must be >= 1"),
    case("segment steps 0", "learn", "--segment-steps 0", "argument --segment-steps: must be >= 1"),
    case("exploration noise negative", "learn", "--exploration-noise -1", "argument --exploration-noise: must be >= 0"),
    case("cost tolerance below 1", "learn", "--cost-tolerance 0.5", "argument --cost-tolerance: a number >= 1"),
    case("cost tolerance NaN", "learn", "--cost-tolerance nan", "argument --cost-tolerance: a number >= 1"),
    case("evaluation duration 0", "learn", "--evaluation-duration 0", "argument --evaluation-duration: must be > 0"),
    case("max rounds negative", "learn", "--max-rounds -1", "argument --max-rounds: must be >= 0"),
    case("time limit 0", "learn", "--time-limit 0", "argument --time-limit: must be > 0"),
    case("seed negative", "learn", "--seed -1", "argument --seed: must be >= 0"),
    case("out-dir holds a loop", "learn", "--out-dir run --quiet", "--out-dir run already holds learn.json",
         text_file("run/learn.json", "{}\n")),
    case("default out-dir holds a loop", "learn", "--quiet", "--out-dir learn/pendulum already holds data.npz",
         text_file("learn/pendulum/data.npz", "earlier data")),
    case("out-dir a file", "learn", "--out-dir notes.txt --quiet", "--out-dir notes.txt is a file",
         text_file("notes.txt", "mine\n")),
    case("excitation larger than the budget", "learn", "--budget 100 --excitation-trajectories 50 --quiet",
         "is larger than the budget"),
    case("scene timestep 1 s", "learn", "--scene ts1.xml --quiet", "does not resolve",
         scene("ts1", ('timestep="0.005"', 'timestep="1"'))),
    case("craft below its weight", "learn", "--scene weak.xml --quiet", "the craft cannot hover",
         craft_scene("weak", ('ctrlrange="0 2.5"', 'ctrlrange="0 1"'))),
]

QUALITY = [
    case("horizon 0 is no default", "quality", "--horizon 0", "argument --horizon: must be >= 1"),
    case("energy steps 0", "quality", "--energy-steps 0", "argument --energy-steps: must be >= 1"),
    case("samples 0", "quality", "--samples 0", "argument --samples: must be >= 1"),
    case("seed negative", "quality", "--seed -1", "argument --seed: must be >= 0"),
    case("checkpoint of a free body", "quality", "--checkpoint quadrotor_fixed-inertia",
         "is a free body and quality needs a body on a pivot"),
    case("checkpoint missing", "quality", "--checkpoint no-such-model", "checkpoint file not found"),
    case("held-out data empty", "quality", "--data empty.npz", "the file is empty", byte_file("empty.npz", b"")),
    case("held-out data of another period", "quality", "--data fast.npz",
         "fast.npz was recorded every 0.02 s and the checkpoint steps at 0.05 s", data_file("fast.npz", _other_period)),
    case("held-out data of another width", "quality", "--data wide.npz", "wide.npz: 2 controls per step",
         data_file("wide.npz", _wide_controls)),
    case("held-out data with NaN", "quality", "--data nan.npz", "is nan", data_file("nan.npz", _nan_state)),
    case("held-out data a folder", "quality", "--data runs", "a folder, not a data file", a_folder("runs")),
    case("horizon past the data", "quality", "--data pendulum.npz --horizon 500",
         "--horizon 500 is longer than the held-out trajectories", PENDULUM_DATA),
    case("json a folder", "quality", "--json out", "--json out is a folder", a_folder("out")),
    case("checkpoint sidecar not JSON", "quality", "--checkpoint broken", "not valid JSON",
         checkpoint_copy("broken"), text_file("broken.json", "{not json")),
]

SWEEP = [
    case("width 0", "sweep", "--widths 0", "argument --widths: must be >= 1"),
    case("size of one trajectory", "sweep", "--sizes 1", "argument --sizes: must be >= 2"),
    case("seeds negative", "sweep", "--seeds -1", "argument --seeds: must be >= 0"),
    case("hidden layers 0", "sweep", "--hidden-layers 0", "argument --hidden-layers: must be >= 1"),
    case("iterations 0", "sweep", "--iterations 0", "argument --iterations: must be >= 1"),
    case("time limit 0", "sweep", "--time-limit 0", "argument --time-limit: must be > 0"),
    case("data missing", "sweep", "--data absent.npz --out-dir s --quiet", "data file not found: absent.npz"),
    case("data a text file", "sweep", "--data notes.npz --out-dir s --quiet", "not a NumPy archive",
         text_file("notes.npz", "some notes\n")),
    case("data of one trajectory", "sweep", "--data one.npz --out-dir s --quiet", "training holds at least one out",
         data_file("one.npz", _one_trajectory)),
    case("data of the wrong control width", "sweep", "--data wide.npz --out-dir s --quiet", "has 1 actuators",
         data_file("wide.npz", _wide_controls)),
    case("out-dir holds a sweep", "sweep", "--data pendulum.npz --out-dir s --quiet",
         "--out-dir s already holds sweep.md",
         PENDULUM_DATA, text_file("s/sweep.md", "my sweep\n")),
    case("variants unknown", "sweep", "--data pendulum.npz --variants bogus --out-dir s --quiet", "unknown variants",
         PENDULUM_DATA),
    case("workers 0", "sweep", "--data pendulum.npz --workers 0 --out-dir s --quiet", "--workers must be >= 1",
         PENDULUM_DATA),
]

CHECKPOINT_FILES = [  # a checkpoint's own files, given where a model goes
    case("sidecar of another format", "swingup", "--checkpoint ck --quiet", "not a fvin_mpc.checkpoint/1 sidecar",
         checkpoint_copy("ck", edit=_set(("format",), "other/2"))),
    case("sidecar without weights", "swingup", "--checkpoint lone --quiet",
         "checkpoint file not found: lone.safetensors",
         text_file("lone.json", "{}")),
    case("weights replaced", "swingup", "--checkpoint ck --quiet", "SHA-256 differs",
         checkpoint_copy("ck", edit=_set(("weights_sha256",), "0" * 64))),
    case("model config broken", "swingup", "--checkpoint ck --quiet", "invalid model config",
         checkpoint_copy("ck", edit=_set(("model", "control_dim"), "one"))),
]

CASES: list[Case] = [*SWINGUP, *MJCF, *COLLECT, *TRAIN, *EVALUATE, *FLY, *EXPORT, *LEARN, *QUALITY, *SWEEP,
                     *CHECKPOINT_FILES]


# ---------------------------------------------------------------------- running a case
def snapshot(folder: Path) -> dict[str, Any]:
    """Every file (its bytes' digest and mtime) and folder under ``folder``."""
    found: dict[str, Any] = {}
    for path in sorted(folder.rglob("*")):
        key = str(path.relative_to(folder))
        found[key] = ("dir" if path.is_dir() else
                      (hashlib.sha1(path.read_bytes()).hexdigest(), path.stat().st_mtime_ns))
    return found


@contextlib.contextmanager
def torch_hidden(hidden: bool) -> Iterator[None]:
    """``import torch`` fails inside (as on an install without the train extra)."""
    if not hidden:
        yield
        return
    saved = {name: module for name, module in sys.modules.items() if name == "torch" or name.startswith("torch.")}
    for name in saved:
        del sys.modules[name]
    sys.modules["torch"] = None  # type: ignore[assignment]
    try:
        yield
    finally:
        del sys.modules["torch"]
        sys.modules.update(saved)


@dataclass
class Outcome:
    status: Any
    stderr: str
    before: dict[str, Any]
    after: dict[str, Any]

    @property
    def lines(self) -> list[str]:
        return [line for line in self.stderr.splitlines() if line.strip()]


def run(command: str, argv: tuple[str, ...], folder: Path, setup: tuple[Setup, ...] = (),
        without_torch: bool = False) -> Outcome:
    """``python -m fvin_mpc.<command> argv`` in-process, in ``folder`` (prepared by ``setup``)."""
    from fvin_mpc.core.errors import run_command

    for prepare in setup:
        prepare(folder)
    main = importlib.import_module(f"fvin_mpc.{command}").main
    before = snapshot(folder)
    err = io.StringIO()
    with contextlib.chdir(folder), contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()), \
            torch_hidden(without_torch):
        try:
            status = run_command(main, list(argv))
        except SystemExit as exit_info:  # a parse error that escaped the wrapper
            status = ("SystemExit", exit_info.code)
    return Outcome(status, err.getvalue(), before, snapshot(folder))


def check_refused(outcome: Outcome, message: str = "") -> str:
    """The outcome is a refusal: status 2, one line ``error: …`` containing ``message``, nothing changed."""
    assert "Traceback" not in outcome.stderr, outcome.stderr
    assert outcome.status == 2, (outcome.status, outcome.stderr)
    assert len(outcome.lines) == 1 and outcome.lines[0].startswith("error: "), outcome.stderr
    assert message in outcome.lines[0], (message, outcome.lines[0])
    assert outcome.after == outcome.before, "the refused command changed the folder"
    return outcome.lines[0]


def test_the_table_covers_every_command_with_at_least_100_cases():
    commands = {path.stem for path in (ROOT / "fvin_mpc").glob("[!_]*.py")}
    assert len(CASES) >= 100 and {c.command for c in CASES} == commands
    assert len({(c.command, c.name) for c in CASES}) == len(CASES), "case names repeat within a command"


@pytest.mark.parametrize("bad", CASES, ids=lambda c: f"{c.command}: {c.name}")
def test_a_bad_input_is_refused_in_one_line_before_any_work(bad: Case, tmp_path):
    check_refused(run(bad.command, bad.argv, tmp_path, bad.setup, bad.without_torch), "" if bad.loose else bad.message)


def test_the_documented_table_lists_every_case():
    """``docs/bad-inputs.md`` is this table (regenerate: ``python tests/test_bad_inputs.py``)."""
    document = (ROOT / "docs" / "bad-inputs.md").read_text()
    missing = [f"{c.command}: {c.name}" for c in CASES if f"| {c.command} | {c.name} |" not in document]
    assert not missing, f"docs/bad-inputs.md is stale (python tests/test_bad_inputs.py): {missing[:5]}"


def test_the_check_can_fail(tmp_path):
    """A command that runs on (here: ``--help``) or a message that is not there is caught."""
    with pytest.raises(AssertionError):
        check_refused(run("swingup", ("--horizon", "0"), tmp_path), "no such words")
    with pytest.raises(AssertionError):
        check_refused(run("collect", ("--help",), tmp_path))


# ---------------------------------------------------------------------- Ctrl-C
def test_ctrl_c_is_one_line_and_status_130(capsys):
    from fvin_mpc.core.errors import INTERRUPTED_STATUS, run_command

    def main(argv):
        raise KeyboardInterrupt

    assert run_command(main, []) == INTERRUPTED_STATUS == 130
    assert capsys.readouterr().err == "error: interrupted (Ctrl-C)\n"


def test_a_real_run_interrupted_mid_episode_leaves_nothing_behind(tmp_path):
    """``python -m fvin_mpc.swingup`` stopped by SIGINT while it runs its episode: status 130, one error line
    (the progress it printed before is not an error), no traceback, and none of its outputs written."""
    process = subprocess.Popen(
        [sys.executable, "-m", "fvin_mpc.swingup", "--true-model", "--duration", "600", "--quiet",
         "--plot", "out/run.png", "--json", "out/run.json"],
        cwd=tmp_path, stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"})
    try:
        first = process.stderr.readline()  # "model …, solver built in …": the episode starts after it
        assert first.startswith("model "), first
        time.sleep(1.0)
        process.send_signal(signal.SIGINT)
        _, rest = process.communicate(timeout=60)
    finally:
        process.kill()
    errors = [line for line in rest.splitlines() if line.strip()]
    assert process.returncode == 130 and "Traceback" not in rest, rest
    assert errors == ["error: interrupted (Ctrl-C)"], rest
    assert not (tmp_path / "out").exists() and not list(tmp_path.iterdir())


def test_learn_without_torch_in_a_fresh_process_refuses_before_any_work(tmp_path):
    """As on an install without the train extra (torch blocked before anything imports it): one line that
    names the extra, and no folder left behind (it ran the closed form and left an empty one before)."""
    probe = ("import sys; sys.modules['torch'] = None\n"
             "from fvin_mpc.core.errors import run_command\n"
             "import fvin_mpc.learn as learn\n"
             "raise SystemExit(run_command(learn.main, ['--quiet']))\n")
    result = subprocess.run([sys.executable, "-c", probe], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                            env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert result.stderr.strip().splitlines() == [
        'error: learn trains models and needs torch, which is not installed: pip install torch==2.13.0 && '
        'pip install -e ".[train]"']
    assert not list(tmp_path.iterdir())


# ---------------------------------------------------------------------- generated bad inputs (Hypothesis)
#: Examples per property: a handful in the default suite, many under ``-m slow``.
FEW, MANY = 6, 150
_HYPOTHESIS = dict(deadline=None, derandomize=True, database=None,
                   suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


def _fresh(root: Path) -> Path:
    """A new, empty folder under ``root`` for one example."""
    folder = root / f"example_{len(list(root.iterdir()))}"
    folder.mkdir()
    return folder


# Physics no body can be simulated or modelled with: each value is past the bound its check names.
_BROKEN_PIVOT = st.one_of(
    st.tuples(st.just("gear"), st.sampled_from(["0", "nan", "inf", "-inf"])),
    st.tuples(st.just("gear"), st.floats(1e6, 1e15).map(lambda g: f"{g:.6g}")),
    st.tuples(st.just("timestep"), st.sampled_from(["0", "-0.001", "nan"])),
    st.tuples(st.just("timestep"), st.floats(0.07, 10.0).map(lambda h: f"{h:.6g}")),
    st.tuples(st.just("mass"), st.floats(1e-12, 1e-7).map(lambda m: f"{m:.6g}")),
    st.tuples(st.just("mass"), st.floats(1e20, 1e35).map(lambda m: f"{m:.6g}")),
    st.tuples(st.just("ctrlrange"), st.sampled_from(["-inf inf", "-2 inf", "missing"])),
    st.tuples(st.just("actuator"), st.sampled_from(["position", "velocity", "gain", "filter"])),
)


def broken_pendulum(kind: str, value: str) -> str:
    if kind == "gear":
        return pendulum(('gear="1"', f'gear="{value}"'))
    if kind == "timestep":
        return pendulum(('timestep="0.005"', f'timestep="{value}"'))
    if kind == "mass":  # the rod's shape kept: inertia scales with the mass
        m = float(value)
        return pendulum((ROD_INERTIA, f'mass="{m:.6g}" diaginertia="{m / 12:.6g} {m / 12:.6g} {m * 1e-6:.6g}"'))
    if kind == "ctrlrange":
        return pendulum((' ctrlrange="-2 2" ctrllimited="true"', "" if value == "missing" else f' ctrlrange="{value}"'))
    actuator = {"position": '<position name="torque" joint="hinge" kp="10" ctrlrange="-2 2"/>',
                "velocity": '<velocity name="torque" joint="hinge" kv="2" ctrlrange="-2 2"/>',
                "gain": '<general name="torque" joint="hinge" gainprm="3" ctrlrange="-2 2"/>',
                "filter": '<general name="torque" joint="hinge" dyntype="filter" dynprm="0.1" ctrlrange="-2 2"/>'}
    return pendulum((MOTOR, actuator[value]))


_BROKEN_CRAFT = st.one_of(
    st.tuples(st.just("thrust"), st.floats(0.05, 0.73).map(lambda t: f"{t:.4g}")),  # t/w < 1.2 (4 rotors, 4.905 N)
    st.tuples(st.just("mass"), st.floats(1e-12, 1e-6).map(lambda m: f"{m:.6g}")),
    st.tuples(st.just("mass"), st.floats(5.0, 1e30).map(lambda m: f"{m:.6g}")),
    st.tuples(st.just("timestep"), st.floats(0.06, 5.0).map(lambda h: f"{h:.6g}")),
)


def broken_craft(kind: str, value: str) -> str:
    if kind == "thrust":
        return QUADROTOR_XML.replace('ctrlrange="0 2.5"', f'ctrlrange="0 {value}"')
    if kind == "timestep":
        return craft(('timestep="0.002"', f'timestep="{value}"'))
    m = float(value)  # the inertia scaled with the mass: the same shape
    return craft(('mass="0.5" diaginertia="0.0023 0.0029 0.0046"',
                  f'mass="{m:.6g}" diaginertia="{0.0046 * m:.6g} {0.0058 * m:.6g} {0.0092 * m:.6g}"'))


def _pivot_property(tmp_path: Path, broken: tuple[str, str]) -> None:
    folder = _fresh(tmp_path)
    outcome = run("swingup", ("--scene", "broken.xml", *PIVOT), folder,
                  (text_file("broken.xml", broken_pendulum(*broken)),))
    check_refused(outcome)


def _craft_property(tmp_path: Path, broken: tuple[str, str], command: str) -> None:
    folder = _fresh(tmp_path)
    argv = ("--scene", "broken.xml", "--model", "closed-form", "--quiet") if command == "fly" else \
        ("--scene", "broken.xml", "--out", "d.npz", "--quiet")
    check_refused(run(command, argv, folder, (text_file("broken.xml", broken_craft(*broken)),)))


@settings(max_examples=FEW, **_HYPOTHESIS)
@given(broken=_BROKEN_PIVOT)
def test_generated_broken_pendulums_are_refused(tmp_path, broken):
    _pivot_property(tmp_path, broken)


@settings(max_examples=FEW, **_HYPOTHESIS)
@given(broken=_BROKEN_CRAFT, command=st.sampled_from(["fly", "collect"]))
def test_generated_broken_crafts_are_refused(tmp_path, broken, command):
    _craft_property(tmp_path, broken, command)


def _break_data(kind: str, draw: Any) -> Setup:
    """A data file broken one way (``draw``: that kind's value)."""
    def edit(state, u, metadata):
        if kind == "nan_state":
            index = tuple(int(i) % n for i, n in zip(draw, state.shape))
            state[index] = [np.nan, np.inf, -np.inf][draw[0] % 3]
        elif kind == "nan_control":
            index = tuple(int(i) % n for i, n in zip(draw, u.shape))
            u[index] = [np.nan, np.inf, -np.inf][draw[0] % 3]
        elif kind == "quaternion_scale":
            index = (draw[0] % state.shape[0], draw[1] % state.shape[1])
            state[index][:4] *= draw[2]
        elif kind == "period":
            metadata["control_period"] = draw
        elif kind == "space":
            metadata["configuration_space"] = draw
        return state, u, metadata

    if kind == "bytes":
        return byte_file("d.npz", draw)
    if kind == "cut":
        def cut(folder: Path) -> None:
            data_file("whole.npz")(folder)
            whole = (folder / "whole.npz").read_bytes()
            (folder / "d.npz").write_bytes(whole[: draw % max(1, len(whole) - 1)])
            (folder / "whole.npz").unlink()
        return cut
    return data_file("d.npz", edit)


_BROKEN_DATA = st.one_of(
    st.tuples(st.just("nan_state"), st.tuples(*[st.integers(0, 99)] * 3)),
    st.tuples(st.just("nan_control"), st.tuples(*[st.integers(0, 99)] * 3)),
    st.tuples(st.just("quaternion_scale"), st.tuples(st.integers(0, 99), st.integers(0, 99),
                                                     st.one_of(st.floats(0.0, 0.999), st.floats(1.001, 1e6)))),
    st.tuples(st.just("period"), st.one_of(st.sampled_from([0.0, -0.05, None, "fast", [0.05]]),
                                           st.floats(-1e3, 0.0), st.just(float("nan")), st.just(float("inf")))),
    st.tuples(st.just("space"), st.text(min_size=1, max_size=8).filter(lambda s: s not in ("S3", "R3xS3", "SO3"))),
    st.tuples(st.just("bytes"), st.binary(min_size=1, max_size=200)),
    st.tuples(st.just("cut"), st.integers(0, 10**6)),
)


def _data_property(tmp_path: Path, broken: tuple[str, Any], command: str) -> None:
    folder = _fresh(tmp_path)
    argv = ("--data", "d.npz") if command == "quality" else ("--data", "d.npz", "--out-dir", "s", "--quiet")
    check_refused(run(command, argv, folder, (_break_data(*broken),)))


@settings(max_examples=2 * FEW, **_HYPOTHESIS)
@given(broken=_BROKEN_DATA, command=st.sampled_from(["quality", "sweep"]))
def test_generated_broken_data_files_are_refused(tmp_path, broken, command):
    _data_property(tmp_path, broken, command)


_SIDECAR_EDITS = st.one_of(
    st.tuples(st.just(("model", "step_size")), st.sampled_from([0.0, -0.05, None, "fast", float("nan"), float("inf")])),
    st.tuples(st.just(("model", "control_dim")), st.sampled_from([0, -1, 2, 3, None, "one", 1.5])),
    st.tuples(st.just(("model", "hidden_width")), st.sampled_from([0, -4, 7, None, "wide"])),
    st.tuples(st.just(("model", "newton_iters")), st.sampled_from([0, -1, None, "two", 1.5, 10**6])),
    st.tuples(st.just(("model", "variant")), st.text(max_size=12).filter(
        lambda s: s not in ("sign-invariant", "fixed-inertia", "plain"))),
    st.tuples(st.just(("configuration_space",)), st.sampled_from(["R3xS3", "S7", "", 3])),
    st.tuples(st.just(("format",)), st.sampled_from(["", "fvin_mpc.checkpoint/2", None])),
    st.tuples(st.just(("weights_sha256",)), st.text(alphabet="0123456789abcdef", min_size=64, max_size=64)),
)


def _sidecar_property(tmp_path: Path, edit: tuple[tuple[str, ...], Any], command: str) -> None:
    folder = _fresh(tmp_path)
    argv = {"swingup": ("--checkpoint", "ck", *QUIET, *NO_PLOT), "quality": ("--checkpoint", "ck"),
            "export": ("--checkpoint", "ck")}[command]
    check_refused(run(command, argv, folder, (checkpoint_copy("ck", edit=_set(*edit)),)))


@settings(max_examples=2 * FEW, **_HYPOTHESIS)
@given(edit=_SIDECAR_EDITS, command=st.sampled_from(["swingup", "quality", "export"]))
def test_generated_broken_checkpoint_sidecars_are_refused(tmp_path, edit, command):
    _sidecar_property(tmp_path, edit, command)


def _not_finite_or(strategy: st.SearchStrategy) -> st.SearchStrategy[str]:
    return st.one_of(strategy.map(lambda v: f"{v:.6g}" if isinstance(v, float) else str(v)),
                     st.sampled_from(["nan", "inf", "-inf", "", "ten"]))


#: (command, option, values the option must refuse): each drawn value is outside what the option takes.
_BAD_OPTIONS = [
    ("swingup", "--horizon", _not_finite_or(st.one_of(st.integers(max_value=0), st.integers(1001, 10**9)))),
    ("swingup", "--duration", _not_finite_or(st.one_of(st.floats(-1e12, 0.0), st.floats(3600.5, 1e300)))),
    ("swingup", "--newton-iters", _not_finite_or(st.one_of(st.integers(max_value=0), st.integers(21, 10**9)))),
    ("swingup", "--torque-reserve", _not_finite_or(st.one_of(st.floats(-1e9, -1e-9), st.floats(1.0, 1e9)))),
    ("swingup", "--omega-weight", _not_finite_or(st.floats(-1e12, -1e-12))),
    ("swingup", "--seed", _not_finite_or(st.integers(max_value=-1))),
    ("swingup", "--latency", _not_finite_or(st.floats(-1e9, -1e-9))),
    ("collect", "--trajectories", _not_finite_or(st.integers(max_value=0))),
    ("collect", "--steps", _not_finite_or(st.integers(max_value=0))),
    ("evaluate", "--max-omega", _not_finite_or(st.floats(-1e9, -1e-9))),
    ("fly", "--seed", _not_finite_or(st.integers(max_value=-1))),
    ("learn", "--budget", _not_finite_or(st.integers(max_value=0))),
    ("quality", "--horizon", _not_finite_or(st.integers(max_value=0))),
    ("sweep", "--widths", _not_finite_or(st.integers(max_value=0))),
    ("export", "--newton-iters", _not_finite_or(st.one_of(st.integers(max_value=0), st.integers(21, 10**6)))),
]


def _option_property(tmp_path: Path, index: int, data: st.DataObject) -> None:
    command, option, values = _BAD_OPTIONS[index]
    value = data.draw(values)
    check_refused(run(command, (f"{option}={value}",), _fresh(tmp_path)), option)


@settings(max_examples=4 * FEW, **_HYPOTHESIS)
@given(index=st.integers(0, len(_BAD_OPTIONS) - 1), data=st.data())
def test_generated_bad_option_values_are_refused_while_parsing(tmp_path, index, data):
    _option_property(tmp_path, index, data)


# the same properties, thoroughly
@pytest.mark.slow
@settings(max_examples=MANY, **_HYPOTHESIS)
@given(broken=_BROKEN_PIVOT)
def test_generated_broken_pendulums_are_refused_thoroughly(tmp_path, broken):
    _pivot_property(tmp_path, broken)


@pytest.mark.slow
@settings(max_examples=MANY, **_HYPOTHESIS)
@given(broken=_BROKEN_CRAFT, command=st.sampled_from(["fly", "collect"]))
def test_generated_broken_crafts_are_refused_thoroughly(tmp_path, broken, command):
    _craft_property(tmp_path, broken, command)


@pytest.mark.slow
@settings(max_examples=MANY, **_HYPOTHESIS)
@given(broken=_BROKEN_DATA, command=st.sampled_from(["quality", "sweep"]))
def test_generated_broken_data_files_are_refused_thoroughly(tmp_path, broken, command):
    _data_property(tmp_path, broken, command)


@pytest.mark.slow
@settings(max_examples=MANY, **_HYPOTHESIS)
@given(edit=_SIDECAR_EDITS, command=st.sampled_from(["swingup", "quality", "export"]))
def test_generated_broken_checkpoint_sidecars_are_refused_thoroughly(tmp_path, edit, command):
    _sidecar_property(tmp_path, edit, command)


@pytest.mark.slow
@settings(max_examples=4 * MANY, **_HYPOTHESIS)
@given(index=st.integers(0, len(_BAD_OPTIONS) - 1), data=st.data())
def test_generated_bad_option_values_are_refused_thoroughly(tmp_path, index, data):
    _option_property(tmp_path, index, data)


# ---------------------------------------------------------------------- docs/bad-inputs.md
def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("`", "'").replace("<", "&lt;").replace(">", "&gt;")


def write_document(path: Path = ROOT / "docs" / "bad-inputs.md") -> None:
    """Run every case and write the table with the line each one got (the argv in code, the line as text:
    it may quote a command line, which tests/test_documented_commands.py would otherwise parse)."""
    import tempfile

    rows = []
    for bad in CASES:
        with tempfile.TemporaryDirectory() as folder:
            outcome = run(bad.command, bad.argv, Path(folder), bad.setup, bad.without_torch)
            line = outcome.lines[-1] if outcome.lines else f"(no error: status {outcome.status})"
            line = line.replace(os.path.realpath(folder) + os.sep, "").replace(folder + os.sep, "")
        rows.append(f"| {bad.command} | {bad.name} | `{' '.join(bad.argv) or '(none)'}` | {_cell(line)} |")
    commands = sorted({bad.command for bad in CASES})
    text = f"""# Bad inputs: what each command refuses, in one line

Every command validates at its edge, before any work: the option values while parsing, the scene's physics
when it reads the MJCF (envs/scenes.py `check_physics`, the envs' scale checks), data files when it loads
them (fvin_mpc/core/data.py `load_data`), checkpoints, and every output path (it must be creatable, of a
kind the writer knows, and nothing is replaced without `--force`). A refusal is one line on stderr,
`error: …`, and exit status 2; Ctrl-C is one line and status 130. A 0 is a value or an error, never "the
default"; no command writes into the package's own `docs/` unless told to.

The table is tests/test_bad_inputs.py's named cases: {len(CASES)} of them, over {len(commands)} commands
({", ".join(commands)}), each run in a fresh folder with the broken files it names, and the line it got. The
test asserts status 2, that one line and no traceback, and that no file in the folder changed; beside it,
Hypothesis draws broken MJCFs, data files, checkpoint sidecars and option values (a few examples in the
default suite, many with `-m slow`). Regenerate this page with `python tests/test_bad_inputs.py`.

The thresholds of the physics checks, and why (each constant's comment says more):

* a MuJoCo timestep turns the body at most 0.5 rad at its speed scale (the faster of the speed that
  carries it over its energy span and the speed its motor gives it over half a turn; for a craft, the
  faster of its attitude rate and a 10 rad/s tumble): data reach 1.2× that scale, and the variational
  step solves only while h|ω| ≲ 1 (DESIGN.md) — `MAX_STEP_ANGLE`;
* a control period turns it at most 1 rad at that scale (the step's solvable region; singular at π/2) —
  `MAX_PERIOD_ANGLE`;
* a motor gives at least 0.05 of the peak gravity torque (pumping gains about 2τ/τ_g rad per half swing:
  below it a swing-up takes more than 16 natural periods) — `MIN_MOTOR_SHARE`;
* a craft lifts at least 1.2 times its weight (what is left at hover is all it has to turn) —
  `MIN_THRUST_TO_WEIGHT`;
* a gear is finite and nonzero, a ctrlrange finite, an actuator a force or torque motor (no bias, no
  activation state, a fixed gain; a pivot's gain 1, since its torque is read as gear × control).

| command | case | arguments | the line it prints |
|---|---|---|---|
""" + "\n".join(rows) + "\n"
    path.write_text(text)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    write_document()
    print(f"wrote docs/bad-inputs.md ({len(CASES)} cases)")
