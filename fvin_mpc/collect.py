"""Collect trajectories from a scene: ``python -m fvin_mpc.collect``.

Pivoted scenes, by default (``--collector swings``): data that excite what a swing-up needs,
sized from the scene's own scales (energy span, speed scale, actuator bounds, control period):
starts spread over the energies from hanging to 1.4× the swing-up's span (upright and fast
included), near the goal and uniform, driven by energy-pumping bursts — every actuator at its
bound along the motion — with random switching to braking, random levels and coasting, plus some
random piecewise-constant controls; trajectories of two natural periods, about 8,000 transitions
(``fvin_mpc.learning.excitation``; docs/excitation.md). The metadata record the energies reached
and the share of saturated controls.

``--collector random`` is the former collector (the shipped pendulum checkpoints' data).
Initial states are drawn uniformly (angle(s) over the whole circle/sphere, angular
velocity up to ``--max-omega``), controls are either constant over a trajectory (as in
the paper's experiments) or random piecewise constant (a new level every
``--hold-steps`` control periods), drawn uniformly inside the actuators' range. Half
of the trajectories use each mode. Everything is seeded.

Free-body scenes (``--scene quadrotor`` or any MJCF of one body on a free joint) are recorded from the
MJCF alone (``--collector bursts``, the default): short bursts of random piecewise-constant controls
around hover from random states (attitudes uniform on S³, tumbling at up to ``--max-omega``, default
10 rad/s there, or near level), sized from the craft; defaults 750 bursts of 20 periods (15,000
transitions). ``--collector stabilized-flight`` flies instead a closed-form stabilizing controller
towards random waypoints (300 episodes of 50 periods), for crafts the closed form represents.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from fvin_mpc._cli import (
    check_output_file,
    nonnegative_float,
    number_in,
    positive_float,
    positive_int,
    run_command,
    seed_value,
)
from fvin_mpc.core.data import save_data
from fvin_mpc.core.errors import UsageError
from fvin_mpc.envs.scenes import existing_scene
from fvin_mpc.learning.collection import collect, collect_quadrotor
from fvin_mpc.learning.excitation import collect_swings
from fvin_mpc.learning.free_body_excitation import collect_excitation

#: Options of the former random collector only (``--collector random``).
RANDOM_ONLY = ("max_omega", "hold_steps", "near_goal_trajectories", "near_goal_angle", "near_goal_omega", "max_speed")
#: Options a free body's collectors do not take (they record the craft at its own period, from its MJCF).
PIVOT_ONLY = ("body", "control_period", "hold_steps", "near_goal_trajectories", "near_goal_angle", "near_goal_omega",
              "max_speed")
#: ``--collector`` choices per kind of scene, the first the default.
PIVOT_COLLECTORS = ("swings", "random")
FREE_BODY_COLLECTORS = ("bursts", "stabilized-flight")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.collect", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default="pendulum", help="built-in scene name or MJCF path (default: %(default)s)")
    parser.add_argument("--body", default=None, help="body to observe (default: the scene's)")
    parser.add_argument("--collector", choices=PIVOT_COLLECTORS + FREE_BODY_COLLECTORS, default=None,
                        help="pivoted scenes: swings (energy-pumping bursts sized from the scene's scales; default) or "
                             "random (the former uniform states and random constant/piecewise controls); free bodies: "
                             "bursts (random-excitation bursts from the MJCF alone; default) or stabilized-flight "
                             "(a closed-form pilot, for crafts the closed form represents)")
    parser.add_argument("--trajectories", type=positive_int, default=None,
                        help="default: swings ≈ 8,000 transitions / steps; random 320; bursts 750; "
                             "stabilized flight 300")
    parser.add_argument(
        "--steps", type=positive_int, default=None,
        help="control periods per trajectory (default: swings two natural periods, 20–200; random and bursts 20; "
             "stabilized flight 50)"
    )
    parser.add_argument(
        "--max-omega", type=nonnegative_float, default=None,
        help="largest initial |ω| (rad/s; default: 6; free body: 10)"
    )
    parser.add_argument("--hold-steps", type=positive_int, default=None,
                        help="random: periods per level of piecewise-constant controls (default: 4)")
    parser.add_argument("--control-period", type=positive_float, default=None,
                        help="seconds per step (default: the scene's; a whole multiple of its MJCF timestep)")
    parser.add_argument("--max-speed", type=positive_float, default=None,
                        help="keep only trajectories with every |ω_i| ≤ this (rad/s) at every step (default: keep all)")
    parser.add_argument("--near-goal-trajectories", type=number_in(int, 0), default=None,
                        help="random: this many more trajectories started near the goal (default: 0)")
    parser.add_argument("--near-goal-angle", type=number_in(float, 0.0, 3.141592653589793, low_open=True), default=None,
                        help="their largest initial angle from the goal (rad; default: 1)")
    parser.add_argument("--near-goal-omega", type=nonnegative_float, default=None,
                        help="their largest initial |ω_i| (rad/s; default: 2)")
    parser.add_argument("--seed", type=seed_value, default=0)
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output .npz (default: data/<scene name>.npz, the MJCF's stem for a path); an existing file is "
             "replaced only with --force",
    )
    parser.add_argument("--force", action="store_true", help="replace an existing output file")
    parser.add_argument("--quiet", action="store_true")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    spec = existing_scene(args.scene)
    allowed = PIVOT_COLLECTORS if spec.goal_set.attitude_at_rest else FREE_BODY_COLLECTORS
    collector = args.collector or allowed[0]
    if collector not in allowed:
        kind = "a pivoted" if spec.goal_set.attitude_at_rest else "a free-body"
        raise UsageError(f"--collector {collector} does not record {kind} scene; use one of {', '.join(allowed)}")
    # an option the collector would ignore is refused: a value given and silently not used is a wrong result
    ignored = (PIVOT_ONLY if not spec.goal_set.attitude_at_rest else RANDOM_ONLY if collector == "swings" else ())
    given = [name for name in ignored if getattr(args, name) is not None]
    if given:
        takes = "a pivoted scene only" if not spec.goal_set.attitude_at_rest else "--collector random only"
        raise UsageError(f"--{given[0].replace('_', '-')} applies to {takes}")
    out = check_output_file(args.out or Path("data") / f"{spec.name}.npz", "--out", (".npz",), force=args.force)
    if not spec.goal_set.attitude_at_rest:
        max_omega = 10.0 if args.max_omega is None else args.max_omega
        if collector == "bursts":
            free = collect_excitation(args.scene, trajectories=args.trajectories or 750, steps=args.steps or 20,
                                      seed=args.seed, max_omega=max_omega, progress=not args.quiet)
        else:
            free = collect_quadrotor(args.scene, trajectories=args.trajectories or 300, steps=args.steps or 50,
                                     seed=args.seed, max_omega=max_omega, progress=not args.quiet)
        save_data(out, free)
        print(json.dumps({"out": str(out), **{k: free.metadata[k] for k in ("scene", "trajectories", "transitions",
                                                                           "control_period", "coverage")}}))
        return 0
    if collector == "swings":
        data = collect_swings(args.scene, args.trajectories, args.steps, args.seed, args.body,
                              control_period=args.control_period, progress=not args.quiet)
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
    data = collect(args.scene, args.trajectories, args.steps, args.seed, args.max_omega,
                   4 if args.hold_steps is None else args.hold_steps,
                   args.body, progress=not args.quiet, control_period=args.control_period, max_speed=args.max_speed,
                   **near_goal)
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
