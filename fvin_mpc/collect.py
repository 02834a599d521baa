"""Collect trajectories from a scene: ``python -m fvin_mpc.collect``.

Pivoted scenes, by default (``--excitation swings``): data that excite what a swing-up needs,
sized from the scene's own scales (energy span, speed scale, actuator bounds, control period):
starts spread over the energies from hanging to 1.4× the swing-up's span (upright and fast
included), near the goal and uniform, driven by energy-pumping bursts — every actuator at its
bound along the motion — with random switching to braking, random levels and coasting, plus some
random piecewise-constant controls; trajectories of two natural periods, about 8,000 transitions
(``fvin_mpc.learning.excitation``; docs/excitation.md). The metadata record the energies reached
and the share of saturated controls.

``--excitation random`` is the former collector (the shipped pendulum checkpoints' data).
Initial states are drawn uniformly (angle(s) over the whole circle/sphere, angular
velocity up to ``--max-omega``), controls are either constant over a trajectory (as in
the paper's experiments) or random piecewise constant (a new level every
``--hold-steps`` control periods), drawn uniformly inside the actuators' range. Half
of the trajectories use each mode. Everything is seeded.

Free-body scenes (``--scene quadrotor``) are flown instead by a closed-form stabilizing controller
towards random waypoints, with random thrust perturbations, half of the episodes starting in a
tumble (upside down included, ``|ω|`` up to ``--max-omega``, default 10 rad/s there); defaults
300 episodes of 50 periods (15,000 transitions).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from fvin_mpc._cli import run_command
from fvin_mpc.core.data import save_data
from fvin_mpc.core.errors import UsageError
from fvin_mpc.envs.scenes import existing_scene
from fvin_mpc.learning.collection import collect, collect_quadrotor
from fvin_mpc.learning.excitation import collect_swings

#: Options of the former random collector only (``--excitation random``).
RANDOM_ONLY = ("max_omega", "near_goal_trajectories", "near_goal_angle", "near_goal_omega", "max_speed")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.collect", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default="pendulum", help="built-in scene name or MJCF path (default: %(default)s)")
    parser.add_argument("--body", default=None, help="body to observe (default: the scene's)")
    parser.add_argument("--excitation", choices=("swings", "random"), default="swings",
                        help="pivoted scenes: swings (energy-pumping bursts sized from the scene's scales) or random "
                             "(the former uniform states and random constant/piecewise controls); default: %(default)s")
    parser.add_argument("--trajectories", type=int, default=None,
                        help="default: swings ≈ 8,000 transitions / steps; random 320; free body 300")
    parser.add_argument(
        "--steps", type=int, default=None,
        help="control periods per trajectory (default: swings two natural periods, 20–200; random 20; free body 50)"
    )
    parser.add_argument(
        "--max-omega", type=float, default=None, help="largest initial |ω| (rad/s; default: 6; free body: 10)"
    )
    parser.add_argument("--hold-steps", type=int, default=4,
                        help="random: periods per level of piecewise-constant controls (default: %(default)s)")
    parser.add_argument("--control-period", type=float, default=None,
                        help="seconds per step (default: the scene's; a whole multiple of its MJCF timestep)")
    parser.add_argument("--max-speed", type=float, default=None,
                        help="keep only trajectories with every |ω_i| ≤ this (rad/s) at every step (default: keep all)")
    parser.add_argument("--near-goal-trajectories", type=int, default=None,
                        help="random: this many more trajectories started near the goal (default: 0)")
    parser.add_argument("--near-goal-angle", type=float, default=None,
                        help="their largest initial angle from the goal (rad; default: 1)")
    parser.add_argument("--near-goal-omega", type=float, default=None,
                        help="their largest initial |ω_i| (rad/s; default: 2)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output .npz (default: data/<scene name>.npz, the MJCF's stem for a path)",
    )
    parser.add_argument("--quiet", action="store_true")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    spec = existing_scene(args.scene)
    if not spec.space.pivoted:
        free = collect_quadrotor(args.scene, trajectories=args.trajectories or 300, steps=args.steps or 50,
                                 seed=args.seed, max_omega=10.0 if args.max_omega is None else args.max_omega,
                                 progress=not args.quiet)
        out = args.out or Path("data") / f"{spec.name}.npz"
        save_data(out, free)
        print(json.dumps({"out": str(out), **{k: free.metadata[k] for k in ("scene", "trajectories", "transitions",
                                                                           "control_period", "coverage")}}))
        return 0
    if args.excitation == "swings":
        given = [name for name in RANDOM_ONLY if getattr(args, name) not in (None, 0)]
        if given:
            raise UsageError(f"--{given[0].replace('_', '-')} applies to --excitation random only")
        data = collect_swings(args.scene, args.trajectories, args.steps, args.seed, args.body,
                              control_period=args.control_period, progress=not args.quiet)
        out = args.out or Path("data") / f"{spec.name}.npz"
        save_data(out, data)
        print(json.dumps({"out": str(out), **{k: data.metadata[k] for k in (
            "scene", "collector", "trajectories", "steps", "transitions", "control_period", "saturated_share",
            "energy_coverage")}}))
        return 0
    args.trajectories = args.trajectories or 320
    args.steps = args.steps or 20
    args.max_omega = 6.0 if args.max_omega is None else args.max_omega
    near_goal = {"near_goal_trajectories": args.near_goal_trajectories or 0,
                 "near_goal_angle": 1.0 if args.near_goal_angle is None else args.near_goal_angle,
                 "near_goal_omega": 2.0 if args.near_goal_omega is None else args.near_goal_omega}
    data = collect(args.scene, args.trajectories, args.steps, args.seed, args.max_omega, args.hold_steps,
                   args.body, progress=not args.quiet, control_period=args.control_period, max_speed=args.max_speed,
                   **near_goal)
    out = args.out or Path("data") / f"{spec.name}.npz"
    save_data(out, data)
    print(
        json.dumps(
            {
                "out": str(out),
                **{k: data.metadata[k] for k in ("scene", "trajectories", "transitions", "control_period")},
            }
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
