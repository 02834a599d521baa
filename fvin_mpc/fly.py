"""Fly the quadrotor with the real-time MPC: ``python -m fvin_mpc.fly``.

The command line of :mod:`fvin_mpc.studies.flight_report`, whose docstring is this command's ``--help``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

import fvin_mpc.studies.flight_report as study
from fvin_mpc._cli import (
    PLOT_SUFFIXES,
    VIDEO_SUFFIXES,
    add_latency_argument,
    add_relinearize_argument,
    check_craft_period,
    check_output_file,
    check_output_folder,
    check_rendering,
    check_video_writer,
    checked_scene_and_checkpoint,
    run_command,
    seed_value,
)
from fvin_mpc.control.closed_loop import write_video
from fvin_mpc.core.errors import UsageError
from fvin_mpc.studies.report import json_text


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
    parser.add_argument("--seed", type=seed_value, default=0, help="seeds the recovery starts (default: 0)")
    add_latency_argument(parser, default="measured")
    parser.add_argument("--json", type=Path, default=None, help="write the per-episode results as JSON")
    parser.add_argument("--plot", type=Path, default=None, help="recovery or figure-eight plot (PNG)")
    parser.add_argument("--video", type=Path, default=None,
                        help="MP4 of the first recovery episode or of the figure-eight (headless: MUJOCO_GL=egl)")
    parser.add_argument("--still", type=Path, default=None, help="with --video: a PNG strip of frames from it")
    parser.add_argument("--report", type=Path, default=None,
                        help="run both tasks with both models side by side and write the study into this folder "
                             "(e.g. docs/quadrotor); --task and --model are then ignored")
    parser.add_argument("--force", action="store_true", help="with --report: replace the report files in the folder")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    if args.episodes < 1:
        raise UsageError(f"--episodes must be >= 1, got {args.episodes}")
    if args.report is not None:
        check_output_folder(args.report, "--report", args.force, study.REPORT_FILES)
    json_path = check_output_file(args.json, "--json")
    plot = check_output_file(args.plot, "--plot", PLOT_SUFFIXES)
    video = check_output_file(args.video, "--video", VIDEO_SUFFIXES)
    still = check_output_file(args.still, "--still", PLOT_SUFFIXES)
    check_video_writer(video)
    if still is not None and video is None:
        raise UsageError("--still is a strip of the video's frames: give --video too")
    # an R3xS3 model of this scene, before any build
    spec, checkpoint = checked_scene_and_checkpoint(args.scene, args.checkpoint,
                                                    true_model=args.model == "closed-form" and args.report is None)
    if spec.goal_set.attitude_at_rest:
        raise UsageError(f"scene {spec.name!r} is a body on a pivot; swing it up with python -m fvin_mpc.swingup")
    check_craft_period(spec, checkpoint)
    if args.report is not None:
        if args.rti_relinearize_every is not None:
            raise UsageError("--report runs the studies' own controllers; leave out --rti-relinearize-every")
        results = study.side_by_side(args.report, argv, args.episodes, args.seed, args.latency, args.checkpoint,
                                     progress=not args.quiet, scene=args.scene)
        study.print_rows([model["summary"] for model in results["models"].values()])
        print(f"report: {args.report / 'quadrotor.md'}", file=sys.stderr)
        return 0
    env = study.make_env(render=video is not None, scene=args.scene)
    if video is not None:
        check_rendering(env)
    rti = None if args.rti_relinearize_every is None else {"relinearize_every": args.rti_relinearize_every}
    controller = study.make_controller(env, args.model, args.checkpoint, solver=args.solver, rti=rti)
    if args.model == "closed-form":
        for left_out in env.space.closed_form(env.model, env.body_name).unmodelled:
            print(f"note: the closed form leaves out {left_out}", file=sys.stderr)
    print(f"model {controller.model.name}, horizon {controller.settings.horizon} "
          f"({controller.settings.horizon * controller.model.step_size:.2f} s), built in {controller.build_s:.1f} s, "
          f"solver {args.solver}, latency {args.latency}", file=sys.stderr)
    if args.task == "recovery":
        rows, episodes, frames = study.run_recovery(env, controller, args.episodes, args.seed, args.latency,
                                                    progress=not args.quiet, render_first=video is not None)
        summary = study.summarize(args.model, rows, None, episodes)
        data = {"summary": summary, "episodes": rows}
        if plot is not None:
            plot.parent.mkdir(parents=True, exist_ok=True)
            study.plot_recovery({args.model: (episodes, None)}, plot)
    else:
        tracking, episode, frames = study.run_figure_eight(env, controller, args.latency, progress=not args.quiet,
                                                           render=video is not None)
        summary = study.summarize(args.model, None, tracking, [episode])
        data = {"summary": summary, "figure_eight": tracking}
        if plot is not None:
            plot.parent.mkdir(parents=True, exist_ok=True)
            study.plot_figure_eight({args.model: ([], episode)}, study.figure_eight(env), plot)
    study.print_rows([summary])
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json_text({"command": "python -m fvin_mpc.fly " + " ".join(argv), **data}, indent=1)
                             + "\n")
    if video is not None:
        video.parent.mkdir(parents=True, exist_ok=True)
        write_video(frames, video, fps=1.0 / env.dt)
        print(f"video: {video}", file=sys.stderr)
        if still is not None:
            still.parent.mkdir(parents=True, exist_ok=True)
            study.write_still(frames, still)
    env.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
