"""Fly the quadrotor with the real-time MPC: ``python -m fvin_mpc.fly``.

The command line of :mod:`fvin_mpc.studies.flight_report`, whose docstring is this command's ``--help``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Sequence

import fvin_mpc.studies.flight_report as study
from fvin_mpc._cli import (
    add_latency_argument,
    add_loop_argument,
    add_relinearize_argument,
    checked_scene_and_checkpoint,
    run_command,
)
from fvin_mpc.control.c_controller import on_loop
from fvin_mpc.control.closed_loop import write_video
from fvin_mpc.core.errors import UsageError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.fly", description=study.__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default=study.SCENE,
                        help="the built-in quadrotor or the path of an MJCF of one body on a free joint "
                             "(default: %(default)s)")
    parser.add_argument("--task", choices=["recovery", "figure-eight"], default="recovery", help="(default: recovery)")
    parser.add_argument("--model", choices=list(study.MODELS), default="learned",
                        help="plan with the learned R³ × S³ checkpoint or the closed form read off the MJCF "
                             "(default: learned)")
    parser.add_argument("--checkpoint", default=None, help="learned model: shipped name or path (default: the scene's)")
    parser.add_argument("--solver", choices=["rti", "ipopt"], default="rti",
                        help="rti: one real-time iteration per period (default); ipopt: the same problem solved to "
                             "convergence every period")
    add_relinearize_argument(parser)
    parser.add_argument("--episodes", type=int, default=20, help="recovery starts (default: 20)")
    parser.add_argument("--seed", type=int, default=0, help="seeds the recovery starts (default: 0)")
    add_latency_argument(parser, default="measured")
    add_loop_argument(parser)
    parser.add_argument("--json", type=Path, default=None, help="write the per-episode results as JSON")
    parser.add_argument("--plot", type=Path, default=None, help="recovery or figure-eight plot (PNG)")
    parser.add_argument("--video", type=Path, default=None,
                        help="MP4 of the first recovery episode or of the figure-eight (headless: MUJOCO_GL=egl)")
    parser.add_argument("--still", type=Path, default=None, help="with --video: a PNG strip of frames from it")
    parser.add_argument("--report", type=Path, default=None,
                        help="run both tasks with both models side by side and write the study into this folder "
                             "(e.g. docs/quadrotor); --task and --model are then ignored")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    if args.episodes < 1:
        raise UsageError(f"--episodes must be >= 1, got {args.episodes}")
    # an R3xS3 model of this scene, before any build
    spec, _ = checked_scene_and_checkpoint(args.scene, args.checkpoint,
                                           true_model=args.model == "closed-form" and args.report is None)
    if spec.goal_set.attitude_at_rest:
        raise UsageError(f"scene {spec.name!r} is a body on a pivot; swing it up with python -m fvin_mpc.swingup")
    if args.report is not None:
        if args.loop != "python" or args.rti_relinearize_every is not None:
            raise UsageError("--report runs the studies' own controllers in Python; leave out --loop c and "
                             "--rti-relinearize-every")
        results = study.side_by_side(args.report, argv, args.episodes, args.seed, args.latency, args.checkpoint,
                                     progress=not args.quiet, scene=args.scene)
        study.print_rows([model["summary"] for model in results["models"].values()])
        print(f"report: {args.report / 'quadrotor.md'}", file=sys.stderr)
        return 0
    env = study.make_env(render=args.video is not None, scene=args.scene)
    rti = None if args.rti_relinearize_every is None else {"relinearize_every": args.rti_relinearize_every}
    controller = on_loop(study.make_controller(env, args.model, args.checkpoint, solver=args.solver, rti=rti),
                         args.loop)
    if args.model == "closed-form":
        for left_out in env.space.closed_form(env.model, env.body_name).unmodelled:
            print(f"note: the closed form leaves out {left_out}", file=sys.stderr)
    print(f"model {controller.model.name}, horizon {controller.settings.horizon} "
          f"({controller.settings.horizon * controller.model.step_size:.2f} s), built in {controller.build_s:.1f} s, "
          f"solver {args.solver}, {args.loop} loop, latency {args.latency}", file=sys.stderr)
    if args.task == "recovery":
        rows, episodes, frames = study.run_recovery(env, controller, args.episodes, args.seed, args.latency,
                                                    progress=not args.quiet, render_first=args.video is not None)
        summary = study.summarize(args.model, rows, None, episodes)
        data = {"summary": summary, "episodes": rows}
        if args.plot:
            study.plot_recovery({args.model: (episodes, None)}, args.plot)
    else:
        tracking, episode, frames = study.run_figure_eight(env, controller, args.latency, progress=not args.quiet,
                                                           render=args.video is not None)
        summary = study.summarize(args.model, None, tracking, [episode])
        data = {"summary": summary, "figure_eight": tracking}
        if args.plot:
            study.plot_figure_eight({args.model: ([], episode)}, study.figure_eight(env), args.plot)
    study.print_rows([summary])
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"command": "python -m fvin_mpc.fly " + " ".join(argv), **data}, indent=1,
                                        default=float) + "\n")
    if args.video:

        args.video.parent.mkdir(parents=True, exist_ok=True)
        write_video(frames, args.video, fps=1.0 / env.dt)
        print(f"video: {args.video}", file=sys.stderr)
        if args.still:
            study.write_still(frames, args.still)
    env.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
