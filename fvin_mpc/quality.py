"""Model quality of a checkpoint: ``python -m fvin_mpc.quality``.

The command line of :mod:`fvin_mpc.studies.quality`, whose docstring (the method) is this command's ``--help``.
"""

from __future__ import annotations
import argparse
import json
from pathlib import Path
import numpy as np
import fvin_mpc.studies.quality as quality_module
from fvin_mpc._cli import checked_scene_and_checkpoint, run_command
from fvin_mpc.envs.scenes import resolve_scene
from fvin_mpc.control.scene import scene_env
from fvin_mpc.core.checkpoint import CheckpointError, load_checkpoint
from fvin_mpc.core.rigid_body import from_mujoco
from fvin_mpc.core.data import load_data
from fvin_mpc.studies.quality import NP, compare_components, energy_behaviour, rollout_error


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.quality", description=quality_module.__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", default=resolve_scene("pendulum").default_checkpoint,
                        help="shipped name or path of a hinge scene's model (default: %(default)s)")
    parser.add_argument("--data", type=Path, default=None,
                        help="held-out trajectories (default: data/<scene>_heldout.npz, collected with seed 1 "
                             "— unseen by training, which uses seed 0 — if missing)")
    parser.add_argument("--horizon", type=int, default=40, help="rollout steps (default: %(default)s = 2 s at h = 0.05)")
    parser.add_argument("--energy-steps", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0, help="seeds the sampled states of the component comparison")
    parser.add_argument("--json", type=Path, default=None)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    recorded_scene = load_checkpoint(args.checkpoint).scene
    if recorded_scene is None:
        raise CheckpointError(f"checkpoint {args.checkpoint!r} records no scene; the report compares a model "
                              "with its scene's closed form")
    _, checkpoint = checked_scene_and_checkpoint(recorded_scene, args.checkpoint, command="quality")
    env = scene_env(checkpoint.scene, checkpoint)
    if env.joint_axis is None:
        parser.error(f"{args.checkpoint} models {checkpoint.scene!r}, a ball joint: this is the planar report; "
                     "use python -m fvin_mpc.inertia for 3-D model quality")
    # The scene's own closed-form body (read off its MJCF), not a planar rod assumed for every checkpoint.
    body, axis = from_mujoco(env.model, env.body_name), env.joint_axis
    angles = np.random.default_rng(args.seed).uniform(-np.pi, np.pi, 256)
    quaternions = np.concatenate([np.cos(angles / 2)[:, None], np.sin(angles / 2)[:, None] * axis], 1)
    data_path = args.data or Path("data") / f"{env.scene_spec.name}_heldout.npz"
    if not data_path.exists() and args.data is None:
        from fvin_mpc.learning.collection import collect
        from fvin_mpc.core.data import save_data

        save_data(data_path, collect(checkpoint.scene, trajectories=64, steps=args.horizon, seed=1))
    held_out = load_data(data_path)
    report = {
        "checkpoint": str(checkpoint.path), "variant": checkpoint.config.variant, "data": str(data_path),
        "rollout": rollout_error(checkpoint, held_out, args.horizon),
        # The closed-form body through the same integrator: the error the step size alone causes.
        "rollout_true_model": rollout_error(checkpoint, held_out, args.horizon, terms=body.terms(NP)),
        "components": compare_components(checkpoint, body, quaternions, axis, env.rest),
        "energy": energy_behaviour(checkpoint, body, np.array([0.5, 1.5, 2.5, 3.0]), args.energy_steps, axis,
                                   env.rest, env.goal),
        "energy_on_hinge": energy_behaviour(checkpoint, body, np.array([0.5, 1.5, 2.5, 3.0]), args.energy_steps, axis,
                                            env.rest, env.goal, on_axis=True),
    }
    report["rollout"].pop("angle_error_per_step_mean")
    report["rollout_true_model"].pop("angle_error_per_step_mean")
    report["energy"].pop("true_energy")
    report["energy_on_hinge"].pop("true_energy")
    text = json.dumps(report, indent=2)
    print(text)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
