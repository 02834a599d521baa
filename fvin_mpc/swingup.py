"""Swing a MuJoCo pendulum up with MPC on the learned S3FVIN: ``python -m fvin_mpc.swingup``.

With no arguments: the shipped sign-invariant model of the ``pendulum`` scene, starting
hanging at rest, 10 s of closed loop in MuJoCo, a summary on stdout and a plot in
``swingup.png``. ``--true-model`` runs the same MPC on the closed-form rigid body read
off the scene's MJCF, for comparison. The controller is the one the evaluation reports
(``python -m fvin_mpc.evaluate``): the scene's MPC settings, multi-start cold solves.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fvin_mpc._cli import add_closed_loop_arguments, add_scene_arguments, mpc_overrides
from fvin_mpc.control.closed_loop import episode_metrics, plot_episode, run_episode, write_video
from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings


def parse_init(text: str, joint_type: str) -> dict[str, Any] | None:
    """``--init``: ``rest`` (hanging at rest), ``random`` or numbers ``qpos…,qvel…`` → reset options."""
    if text == "rest":
        return None
    if text == "random":
        return {"random": True, "max_omega": 2.0}
    values = np.array([float(v) for v in text.split(",")])
    nq, nv = (1, 1) if joint_type == "hinge" else (4, 3)
    if values.size != nq + nv:
        raise ValueError(f"--init needs {nq} qpos and {nv} qvel numbers for a {joint_type} joint, got {values.size}")
    return {"qpos": values[:nq], "qvel": values[nq:]}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.swingup", description=__doc__,
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    add_scene_arguments(parser)
    parser.add_argument("--body", default=None, help="observed body (default: the scene's)")
    parser.add_argument("--goal", type=float, nargs=4, default=None, metavar=("W", "X", "Y", "Z"),
                        help="goal quaternion (default: the scene's, the potential's maximum)")
    parser.add_argument("--init", default="rest",
                        help="initial state: rest (the potential's minimum) | random | comma-separated qpos,qvel")
    parser.add_argument("--duration", type=float, default=10.0, help="seconds of closed loop")
    parser.add_argument("--seed", type=int, default=0, help="seeds the env (random init, sensor noise)")
    parser.add_argument("--true-model", action="store_true", help="plan with the closed-form rigid body instead")
    parser.add_argument("--json", type=Path, default=None, help="write the summary as JSON")
    parser.add_argument("--plot", type=Path, default=Path("swingup.png"), help="plot path ('' for none)")
    parser.add_argument("--video", type=Path, default=None, help="render an MP4 (headless: MUJOCO_GL=egl)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_closed_loop_arguments(parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    env = scene_env(args.scene, args.checkpoint, args.true_model, args.control_period, body=args.body, goal=args.goal,
                    render_mode="rgb_array" if args.video else None)
    model = scene_model(env, args.checkpoint, args.true_model, args.newton_iters)
    settings = scene_mpc_settings(env, **mpc_overrides(args))
    controller = scene_mpc(env, model, settings)
    report = controller.compile_report
    print(f"model {model.name} (K = {model.newton_iters}, h = {model.step_size} s), horizon {settings.horizon} "
          f"({settings.horizon * model.step_size:.2f} s), cold starts {', '.join(settings.cold_starts)}; "
          f"solver built in {controller.build_s:.1f} s"
          + (f" ({'cached library' if report.cached else f'compiled in {report.compile_s:.1f} s'})" if report else ""),
          file=sys.stderr)
    episode, frames = run_episode(env, controller, args.duration, parse_init(args.init, env.joint_type),
                                  seed=args.seed, render=args.video is not None, progress=not args.quiet,
                                  description=f"swing-up {model.name}", latency=args.latency)
    metrics = episode_metrics(episode)
    summary = {
        "swung_up": metrics["swung_up"], "time_to_upright_s": metrics["time_to_upright_s"],
        "hold_error_rad": metrics["hold_error_rad"], "solve_time_ms": metrics["solve_time_ms"],
        "control_period_s": metrics["control_period_s"], "solver_failures": metrics["controller_failures"],
        "solver": settings.solver, "latency": args.latency, "deadline_misses": metrics["deadline_misses"],
        "newton_iters": model.newton_iters, "horizon": settings.horizon, "horizon_s": settings.horizon * model.step_size,
        "hessian": settings.hessian, "terminal_energy_weight": settings.terminal_energy_weight,
        "cold_starts": list(settings.cold_starts), "max_abs_torque": metrics["max_abs_torque"],
        "accumulated_cost": metrics["accumulated_cost"], "model": model.name, "true_model": args.true_model,
        "scene": str(args.scene), "init": args.init, "seed": args.seed, "duration_s": metrics["duration_s"],
        "build_s": controller.build_s, "compiled_from_cache": report.cached if report else None,
    }
    text = json.dumps(summary, indent=2)
    print(text)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n")
    if str(args.plot) not in ("", "."):
        plot_episode(episode, args.plot, title=f"{model.name} on {env.scene_spec.name}: swung up = {summary['swung_up']}",
                     torque_bound=float(np.max(np.abs(env.torque_high))))
        print(f"plot: {args.plot}", file=sys.stderr)
    if args.video:
        write_video(frames, args.video, fps=1.0 / episode.control_period)
        print(f"video: {args.video}", file=sys.stderr)
    env.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
