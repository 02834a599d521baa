"""3-D model quality: held-out rollouts and the recovered inertia, ``python -m fvin_mpc.inertia``.

The command line of :mod:`fvin_mpc.studies.inertia`, whose docstring (the method) is this command's ``--help``.
"""

from __future__ import annotations
import argparse
import json
from pathlib import Path
import fvin_mpc.studies.inertia as inertia_module
from fvin_mpc._cli import run_command
from fvin_mpc.envs.scenes import resolve_scene
from fvin_mpc.core.data import load_data
from fvin_mpc.studies.inertia import report


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.inertia", description=inertia_module.__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", nargs="+", default=[resolve_scene("spherical_pendulum").default_checkpoint],
                        help="one or more shipped names or paths (default: %(default)s)")
    parser.add_argument("--data", type=Path, default=Path("data/spherical_pendulum_heldout.npz"),
                        help="held-out trajectories (default: %(default)s)")
    parser.add_argument("--horizon", type=int, default=20, help="rollout steps (default: %(default)s = 1 s at h = 0.05)")
    parser.add_argument("--samples", type=int, default=512, help="orientations for the component comparison")
    parser.add_argument("--energy-steps", type=int, default=400)
    parser.add_argument("--seed", type=int, default=0, help="seeds the sampled orientations and energy states")
    parser.add_argument("--json", type=Path, default=None, help="write the reports (a list) as JSON")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    data = load_data(args.data)
    reports = []
    for name in args.checkpoint:
        result = report(name, data, args.horizon, args.samples, args.energy_steps, args.seed)
        for part in result["rollout"].values():
            part.pop("angle_error_per_step_mean", None)
        reports.append(result)
    text = json.dumps(reports if len(reports) > 1 else reports[0], indent=2)
    print(text)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(reports, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
