"""Export a model: a checkpoint's step ``F(x, u)`` as a CasADi file, or a scene's whole real-time
controller as a self-contained C library: ``python -m fvin_mpc.export``.

``--controller DIR`` writes the C library of the scene's real-time MPC
(:mod:`fvin_mpc.control.c_controller`: the generated functions, the C driver, a header, a Makefile and
an example ``main.c``) planning with ``--checkpoint`` or the closed form (``--true-model``); ``--build``
also compiles it (``make`` needs only a C compiler). Without ``--controller``: the step as a CasADi file
(the export itself and the compile cache are :mod:`fvin_mpc.control.model_export`).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
from pathlib import Path
from typing import Sequence

from fvin_mpc._cli import (
    MAX_NEWTON_ITERS,
    UsageError,
    check_craft_period,
    check_output_file,
    check_output_folder,
    checked_scene_and_checkpoint,
    newton_iters_type,
    run_command,
    seed_value,
)
from fvin_mpc.control.c_controller import write_controller
from fvin_mpc.control.flight import quadrotor_model, quadrotor_mpc, quadrotor_mpc_settings
from fvin_mpc.control.model_export import from_checkpoint, save_function
from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings
from fvin_mpc.envs import QuadrotorEnv
from fvin_mpc.envs.scenes import resolve_scene

#: What ``--controller DIR`` writes (:func:`~fvin_mpc.control.c_controller.write_controller`): replaced only
#: with ``--force``.
CONTROLLER_FILES = ("*.c", "*.h", "Makefile", "*.so", "example")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.export", description=__doc__,
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--scene", default="pendulum", help="built-in scene name or MJCF path")
    parser.add_argument("--checkpoint", default=None, help="shipped name or path (default: the scene's)")
    parser.add_argument("--newton-iters", type=newton_iters_type, default=None,
                        help=f"K unrolled, 1 … {MAX_NEWTON_ITERS} (default: the checkpoint's)")
    parser.add_argument("--out", type=Path, default=None,
                        help="the step's output file (default: <checkpoint>_K<K>.casadi)")
    parser.add_argument("--controller", type=Path, default=None, metavar="DIR",
                        help="write the scene's real-time controller as a C library into DIR instead")
    parser.add_argument("--true-model", action="store_true",
                        help="with --controller: plan with the closed-form body read off the scene's MJCF")
    parser.add_argument("--build", action="store_true", help="with --controller: run make in DIR")
    parser.add_argument("--force", action="store_true", help="replace an existing --out file or --controller files")
    parser.add_argument("--seed", type=seed_value, default=0,
                        help="unused (the export is deterministic); for CLI uniformity")
    return parser


def export_controller(args: argparse.Namespace) -> dict:
    """Write (and with ``--build`` compile) the scene's real-time controller as C."""
    check_output_folder(args.controller, "--controller", args.force, CONTROLLER_FILES)
    if args.build and shutil.which("make") is None:
        raise UsageError("--build needs make on PATH (or compile by hand: see the Makefile)")
    spec, checkpoint = checked_scene_and_checkpoint(args.scene, args.checkpoint, args.true_model)
    check_craft_period(spec, checkpoint)
    if spec.goal_set.attitude_at_rest:
        env = scene_env(spec, checkpoint, args.true_model)
        model = scene_model(env, checkpoint, args.true_model, args.newton_iters)
        # compile="none": the Python loop's own compiled copy is not needed to write the C one
        controller = scene_mpc(env, model, scene_mpc_settings(env, solver="rti", compile="none"))
    else:
        env = QuadrotorEnv(spec)
        model = quadrotor_model(env, checkpoint, args.true_model, args.newton_iters)
        controller = quadrotor_mpc(env, model, quadrotor_mpc_settings(compile="none"))
    directory = write_controller(controller, args.controller)
    summary = {"controller": str(directory), "scene": spec.name, "model": model.name,
               "horizon": controller.horizon, "files": sorted(path.name for path in directory.iterdir())}
    if args.build:
        process = subprocess.run(["make"], cwd=directory, capture_output=True, text=True)
        if process.returncode != 0:
            raise RuntimeError(f"make in {directory} failed: {process.stderr.strip()[-2000:]}")
        summary["built"] = ["libfvin_controller.so", "example"]
    return summary


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m fvin_mpc.export``: write a checkpoint's step as a CasADi file, or a controller as C."""
    args = build_parser().parse_args(argv)
    if args.controller is not None:
        print(json.dumps(export_controller(args)))
        return 0
    if args.true_model or args.build:
        raise UsageError("--true-model and --build go with --controller DIR")
    if args.out is not None:
        check_output_file(args.out, "--out", (".casadi",), force=args.force)
    model = from_checkpoint(args.checkpoint or resolve_scene(args.scene).default_checkpoint, args.newton_iters)
    out = check_output_file(args.out or Path(f"{model.name}_K{model.newton_iters}.casadi"), "--out", (".casadi",),
                            force=args.force)
    save_function(model.step, out)
    print(json.dumps({"out": str(out), "function": str(model.step), "newton_iters": model.newton_iters,
                      "step_size": model.step_size, "instructions": int(model.step.n_instructions())}))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
