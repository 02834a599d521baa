"""The 3-D rigid body on a ball joint (scene ``spherical_pendulum``): ``python -m benchmarks.spherical_report``.

The command line of :mod:`benchmarks.spherical`, whose docstring (the method) is this command's ``--help``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import benchmarks.spherical as spherical_module
from benchmarks.spherical import SCENE, closed_loop_study, markdown_tables, merge_results
from fvin_mpc._cli import checked_scene_and_checkpoint, positive_float, run_command
from fvin_mpc.core.data import save_data
from fvin_mpc.learning.collection import collect


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.spherical_report", description=spherical_module.__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect", help="speed-bounded trajectory data of the spherical pendulum")
    c.add_argument("--trajectories", type=int, default=800)
    c.add_argument("--steps", type=int, default=20, help="control periods per trajectory")
    c.add_argument("--max-omega", type=float, default=6.0, help="largest initial |ω| (rad/s)")
    c.add_argument("--hold-steps", type=int, default=2, help="periods per level of piecewise-constant controls")
    c.add_argument(
        "--max-speed", type=float, default=15.0, help="redraw a trajectory once some |ω_i| exceeds this (rad/s)"
    )
    c.add_argument("--near-goal-trajectories", type=int, default=600,
                   help="more trajectories started within --near-goal-angle of upright (default: %(default)s)")
    c.add_argument("--near-goal-angle", type=float, default=1.0, help="rad (default: %(default)s)")
    c.add_argument(
        "--near-goal-omega",
        type=float,
        default=2.0,
        help="largest initial |ω_i| of those (rad/s; default: %(default)s)",
    )
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--out", type=Path, default=Path("data") / f"{SCENE}.npz")
    c.add_argument("--quiet", action="store_true")
    e = sub.add_parser("closed-loop", help="MPC swing-up from rest and seeded random states, learned vs true model")
    e.add_argument("--checkpoint", default=None, help=f"learned model (default: {SCENE}_sign-invariant)")
    e.add_argument("--episodes", type=int, default=21, help="starts: rest + (episodes − 1) random")
    e.add_argument("--duration", type=positive_float, default=10.0, help="seconds per episode")
    e.add_argument("--max-omegas", default="2,5", help="comma-separated |ω₀| bounds cycled over the random starts")
    e.add_argument("--models", default="learned,true", help="comma-separated subset of learned,true")
    e.add_argument("--horizon", type=int, default=None, help="MPC steps (default: the scene's, scene_mpc_settings)")
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--json", type=Path, default=Path("docs/spherical/closed_loop.json"))
    e.add_argument("--markdown", type=Path, default=Path("docs/spherical/closed_loop.md"))
    e.add_argument(
        "--indices", default=None, help="run only starts FIRST-LAST (inclusive), e.g. 0-9, to split the work"
    )
    e.add_argument("--quiet", action="store_true")
    mg = sub.add_parser("merge", help="merge closed-loop JSON files (disjoint starts or models) into one table")
    mg.add_argument("parts", type=Path, nargs="+")
    mg.add_argument("--json", type=Path, default=Path("docs/spherical/closed_loop.json"))
    mg.add_argument("--markdown", type=Path, default=Path("docs/spherical/closed_loop.md"))
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "merge":
        merged = merge_results([json.loads(path.read_text()) for path in args.parts])
        args.json.write_text(json.dumps(merged, indent=1) + "\n")
        tables = markdown_tables(merged)
        args.markdown.write_text(tables + "\n")
        print(tables)
    if args.command == "closed-loop":
        models = tuple(m.strip() for m in args.models.split(",") if m.strip())
        if not models or set(models) - {"learned", "true"}:
            parser.error(f"--models: expected a subset of learned,true, got {args.models!r}")
        max_omegas = tuple(float(w) for w in args.max_omegas.split(","))
        if "learned" in models:
            checked_scene_and_checkpoint(SCENE, args.checkpoint, command="spherical_report closed-loop")
        start = time.perf_counter()
        indices = None
        if args.indices:
            try:
                first, last = (int(v) for v in args.indices.split("-"))
            except ValueError:
                parser.error(f"--indices: expected FIRST-LAST, got {args.indices!r}")
            indices = (first, last)
        results = closed_loop_study(args.checkpoint, args.episodes, args.duration, args.seed, max_omegas, models,
                                    args.horizon, progress=not args.quiet, indices=indices,
                                    partial_path=args.json.with_suffix(".partial.json"))
        results["wall_clock_s"] = time.perf_counter() - start
        for path in (args.json, args.markdown):
            path.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=1) + "\n")
        tables = markdown_tables(results)
        args.markdown.write_text(tables + "\n")
        print(tables)
    if args.command == "collect":
        start = time.perf_counter()
        data = collect(SCENE, args.trajectories, args.steps, args.seed, args.max_omega, args.hold_steps,
                       progress=not args.quiet, max_speed=args.max_speed,
                       near_goal_trajectories=args.near_goal_trajectories, near_goal_angle=args.near_goal_angle,
                       near_goal_omega=args.near_goal_omega)
        save_data(args.out, data)
        print(
            json.dumps(
                {
                    "out": str(args.out),
                    "wall_clock_s": round(time.perf_counter() - start, 1),
                    **{k: data.metadata[k] for k in ("trajectories", "transitions", "attempts", "acceptance_rate")},
                }
            )
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
