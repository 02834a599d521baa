"""Model quality of checkpoints: ``python -m fvin_mpc.quality``.

The command line of :mod:`fvin_mpc.studies.model_quality`, whose docstring (the method) is this command's
``--help``. A hinge checkpoint gets the planar report; ball-joint checkpoints (one or several, compared
side by side) the 3-D report with the recovered inertia.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import fvin_mpc.studies.model_quality as quality_module
from fvin_mpc._cli import (
    check_output_file,
    checked_scene_and_checkpoint,
    positive_int,
    run_command,
    seed_value,
)
from fvin_mpc.control.scene import scene_env
from fvin_mpc.core.checkpoint import CheckpointError, load_checkpoint
from fvin_mpc.core.data import load_data, save_data
from fvin_mpc.core.rigid_body import from_mujoco
from fvin_mpc.envs.scenes import resolve_scene
from fvin_mpc.learning.collection import collect
from fvin_mpc.studies.model_quality import (
    NP,
    check_held_out,
    compare_components,
    energy_behaviour,
    report,
    rollout_error,
)
from fvin_mpc.studies.report import json_text

#: Defaults that differ between the planar (hinge) and the 3-D (ball-joint) report: rollout steps
#: (2 s and 1 s at h = 0.05) and the unforced energy rollout's steps.
HINGE_DEFAULTS = {"horizon": 40, "energy_steps": 2000}
BALL_JOINT_DEFAULTS = {"horizon": 20, "energy_steps": 400}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.quality", description=quality_module.__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", nargs="+", default=[resolve_scene("pendulum").default_checkpoint],
                        help="shipped name or path of the model; several ball-joint checkpoints are reported side by "
                             "side (default: %(default)s)")
    parser.add_argument("--data", type=Path, default=None,
                        help="held-out trajectories (default: data/<scene>_heldout.npz; for a hinge collected with "
                             "seed 1 — unseen by training, which uses seed 0 — if missing)")
    parser.add_argument("--horizon", type=positive_int, default=None,
                        help=f"rollout steps (default: {HINGE_DEFAULTS['horizon']} on a hinge = 2 s at h = 0.05, "
                             f"{BALL_JOINT_DEFAULTS['horizon']} on a ball joint)")
    parser.add_argument("--energy-steps", type=positive_int, default=None,
                        help=f"steps of the unforced energy rollouts (default: {HINGE_DEFAULTS['energy_steps']} on a "
                             f"hinge, {BALL_JOINT_DEFAULTS['energy_steps']} on a ball joint)")
    parser.add_argument("--samples", type=positive_int, default=512,
                        help="ball joint: orientations for the component comparison (default: %(default)s)")
    parser.add_argument("--seed", type=seed_value, default=0,
                        help="seeds the sampled states of the component comparison")
    parser.add_argument("--json", type=Path, default=None,
                        help="write the report as JSON (ball joints: a list, one report per checkpoint)")
    return parser


def hinge_report(args: argparse.Namespace, name: str) -> str:
    """The planar report of one hinge checkpoint, as JSON text."""
    checkpoint = load_checkpoint(name)
    env = scene_env(checkpoint.scene, checkpoint)
    horizon = HINGE_DEFAULTS["horizon"] if args.horizon is None else args.horizon
    energy_steps = HINGE_DEFAULTS["energy_steps"] if args.energy_steps is None else args.energy_steps
    # The scene's own closed-form body (read off its MJCF), not a planar rod assumed for every checkpoint.
    body, axis = from_mujoco(env.model, env.body_name), env.joint_axis
    angles = np.random.default_rng(args.seed).uniform(-np.pi, np.pi, 256)
    quaternions = np.concatenate([np.cos(angles / 2)[:, None], np.sin(angles / 2)[:, None] * axis], 1)
    data_path = args.data or Path("data") / f"{env.scene_spec.name}_heldout.npz"
    if not data_path.exists() and args.data is None:

        save_data(data_path, collect(checkpoint.scene, trajectories=64, steps=horizon, seed=1))
    held_out = check_held_out(load_data(data_path), checkpoint, data_path, args.horizon)
    result = {
        "checkpoint": str(checkpoint.path), "variant": checkpoint.config.variant, "data": str(data_path),
        "rollout": rollout_error(checkpoint, held_out, horizon),
        # The closed-form body through the same integrator: the error the step size alone causes.
        "rollout_true_model": rollout_error(checkpoint, held_out, horizon, terms=body.terms(NP)),
        "components": compare_components(checkpoint, body, quaternions, axis, env.rest),
        "energy": energy_behaviour(checkpoint, body, np.array([0.5, 1.5, 2.5, 3.0]), energy_steps, axis,
                                   env.rest, env.goal),
        "energy_on_hinge": energy_behaviour(checkpoint, body, np.array([0.5, 1.5, 2.5, 3.0]), energy_steps, axis,
                                            env.rest, env.goal, on_axis=True),
    }
    result["rollout"].pop("angle_error_per_step_mean")
    result["rollout_true_model"].pop("angle_error_per_step_mean")
    result["energy"].pop("true_energy")
    result["energy_on_hinge"].pop("true_energy")
    return json_text(result, indent=2)


def ball_joint_reports(args: argparse.Namespace, names: list[str], scene: str) -> list[dict]:
    """The 3-D report of each ball-joint checkpoint."""
    path = args.data or Path("data") / f"{scene}_heldout.npz"
    data = load_data(path)
    horizon = BALL_JOINT_DEFAULTS["horizon"] if args.horizon is None else args.horizon
    for name in names:  # each report checks the data against its model; an explicit horizon is checked here
        if args.horizon is not None:
            check_held_out(data, load_checkpoint(name), path, args.horizon)
    reports = []
    for name in names:
        result = report(name, data, horizon, args.samples,
                        BALL_JOINT_DEFAULTS["energy_steps"] if args.energy_steps is None else args.energy_steps,
                        args.seed)
        for part in result["rollout"].values():
            part.pop("angle_error_per_step_mean", None)
        reports.append(result)
    return reports


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    json_path = check_output_file(args.json, "--json")
    scenes = []
    for name in args.checkpoint:
        recorded_scene = load_checkpoint(name).scene
        if recorded_scene is None:
            raise CheckpointError(f"checkpoint {name!r} records no scene; the report compares a model "
                                  "with its scene's closed form")
        checked_scene_and_checkpoint(recorded_scene, name, command="quality")  # a body on a pivot, of its scene
        scenes.append(recorded_scene)
    # A ball joint has no one axis. The env of each checkpoint (its step), not of the scene's default
    # checkpoint, which a scene a user brings need not have.
    hinges = [scene_env(scene, load_checkpoint(name)).joint_axis is not None
              for scene, name in zip(scenes, args.checkpoint)]
    if any(hinges):
        if len(args.checkpoint) > 1:
            parser.error("the planar (hinge) report takes one --checkpoint; several are compared on ball joints only")
        text = hinge_report(args, args.checkpoint[0])
        print(text)
        if json_path is not None:
            json_path.parent.mkdir(parents=True, exist_ok=True)
            json_path.write_text(text + "\n")
        return 0
    if len(set(scenes)) > 1:
        parser.error(f"the ball-joint checkpoints model different scenes {sorted(set(scenes))}: one held-out set "
                     "serves them all")
    reports = ball_joint_reports(args, args.checkpoint, scenes[0])
    print(json_text(reports if len(reports) > 1 else reports[0], indent=2))
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json_text(reports, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
