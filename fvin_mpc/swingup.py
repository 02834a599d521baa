"""Swing a MuJoCo pendulum up with MPC on the learned S3FVIN: ``python -m fvin_mpc.swingup``.

With no arguments: the shipped sign-invariant model of the ``pendulum`` scene, starting
hanging at rest, 10 s of closed loop in MuJoCo (a scene whose motor is weaker against gravity
gets longer: ``--duration``), a summary on stdout and a plot in ``swingup.png``.
``--true-model`` runs the same MPC on the closed-form rigid body read off the scene's MJCF, for
comparison. The controller is the one the evaluation reports
(``python -m fvin_mpc.evaluate``): the scene's MPC settings, multi-start cold solves.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fvin_mpc._cli import (
    PLOT_SUFFIXES,
    VIDEO_SUFFIXES,
    add_closed_loop_arguments,
    add_scene_arguments,
    check_output_file,
    check_rendering,
    check_video_writer,
    checked_scene_and_checkpoint,
    duration_s,
    mpc_overrides,
    number_in,
    run_command,
    seed_value,
)
from fvin_mpc.control.closed_loop import HOLD_WINDOW_S, episode_metrics, plot_episode, run_episode, write_video
from fvin_mpc.control.scene import SceneScales, scene_env, scene_model, scene_mpc, scene_mpc_settings, scene_scales
from fvin_mpc.core.errors import UsageError
from fvin_mpc.studies.report import json_text

#: The shortest default episode: the former fixed default, which the built-in scenes keep.
MIN_DEFAULT_DURATION_S = 10.0
DURATION_RULE = (f"none given: time for the swing-up, (1 + peak gravity torque / motor torque) natural periods, "
                 f"plus the {HOLD_WINDOW_S:g} s hold window, at least {MIN_DEFAULT_DURATION_S:g} s")


def default_duration(scales: SceneScales) -> float:
    """Seconds of closed loop that leave room for the swing-up and the hold window after it.

    A motor weaker than gravity pumps: each half swing raises the amplitude by about
    ``2u/(m g l)`` rad, so reaching upright takes about ``(π/2)·m g l/u`` half swings of at least half
    a natural period each, ≈ 0.8 ``m g l/u`` periods; ``(1 + m g l/u)`` periods bounds that with room
    for a strong motor's single swing. ``m g l``, the peak gravity torque, is half the energy span
    between hanging and upright, and the natural period is ``4π/ω_s`` (``ω_s = 2√(m g l/J)``, the
    scene's speed scale). On the ``pendulum`` scene this is 5.7 s + 3 s, so it keeps 10 s; the weak
    pendulum of docs/custom_scene.md (±1 N·m against 5 N·m) gets 12.7 s.
    """
    gravity_torque = scales.energy_span / 2.0
    natural_period = 4.0 * math.pi / scales.speed
    swing_up_s = (1.0 + gravity_torque / scales.torque) * natural_period
    return max(MIN_DEFAULT_DURATION_S, swing_up_s + HOLD_WINDOW_S)


def parse_init(text: str, joint_type: str) -> dict[str, Any] | None:
    """``--init``: ``rest`` (hanging at rest), ``random`` or numbers ``qpos…,qvel…`` → reset options."""
    if text == "rest":
        return None
    if text == "random":
        return {"random": True, "max_omega": 2.0}
    try:
        values = np.array([float(v) for v in text.split(",")])
    except ValueError:
        raise UsageError(f"--init: expected rest, random or comma-separated numbers, got {text!r}") from None
    if not np.all(np.isfinite(values)):
        raise UsageError(f"--init: every number must be finite, got {text!r}")
    nq, nv = (1, 1) if joint_type == "hinge" else (4, 3)
    if values.size != nq + nv:
        raise UsageError(f"--init needs {nq} qpos and {nv} qvel numbers for a {joint_type} joint, got {values.size}")
    return {"qpos": values[:nq], "qvel": values[nq:]}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.swingup", description=__doc__,
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    add_scene_arguments(parser)
    parser.add_argument("--body", default=None, help="observed body (default: the scene's)")
    parser.add_argument("--goal", type=number_in(float), nargs=4, default=None, metavar=("W", "X", "Y", "Z"),
                        help="goal quaternion (default: the scene's, the potential's maximum)")
    parser.add_argument("--init", default="rest",
                        help="initial state: rest (the potential's minimum) | random | comma-separated qpos,qvel")
    parser.add_argument("--duration", type=duration_s, default=None,
                        help=f"seconds of closed loop; {DURATION_RULE}")
    parser.add_argument("--seed", type=seed_value, default=0, help="seeds the env (random init, sensor noise)")
    parser.add_argument("--true-model", action="store_true", help="plan with the closed-form rigid body instead")
    parser.add_argument("--json", type=Path, default=None, help="write the summary as JSON")
    parser.add_argument("--plot", type=Path, default=Path("swingup.png"), help="plot path, a .png ('' for none)")
    parser.add_argument("--video", type=Path, default=None, help="render an MP4 (headless: MUJOCO_GL=egl)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_closed_loop_arguments(parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    json_path = check_output_file(args.json, "--json")
    plot = check_output_file(args.plot, "--plot", PLOT_SUFFIXES)
    video = check_output_file(args.video, "--video", VIDEO_SUFFIXES)
    check_video_writer(video)
    if args.goal is not None and not np.linalg.norm(args.goal) > 0.0:
        raise UsageError("--goal must be a nonzero quaternion W X Y Z (it is normalized), got 0 0 0 0")
    spec, checkpoint = checked_scene_and_checkpoint(args.scene, args.checkpoint, args.true_model, "swingup")
    env = scene_env(spec, checkpoint, args.true_model, args.control_period, body=args.body, goal=args.goal,
                    render_mode="rgb_array" if video is not None else None)
    if video is not None:
        check_rendering(env)
    reset_options = parse_init(args.init, env.joint_type)
    duration = args.duration if args.duration is not None else default_duration(scene_scales(env))
    model = scene_model(env, checkpoint, args.true_model, args.newton_iters)
    settings = scene_mpc_settings(env, **mpc_overrides(args))
    controller = scene_mpc(env, model, settings)
    report = controller.compile_report
    print(f"model {model.name} (K = {model.newton_iters}, h = {model.step_size} s), horizon {settings.horizon} "
          f"({settings.horizon * model.step_size:.2f} s), cold starts {', '.join(settings.cold_starts)}; "
          f"solver built in {controller.build_s:.1f} s"
          + (f" ({'cached library' if report.cached else f'compiled in {report.compile_s:.1f} s'})" if report else ""),
          file=sys.stderr)
    episode, frames = run_episode(env, controller, duration, reset_options,
                                  seed=args.seed, render=video is not None, progress=not args.quiet,
                                  description=f"swing-up {model.name}", latency=args.latency)
    metrics = episode_metrics(episode)
    summary = {
        "swung_up": metrics["swung_up"],
        "time_to_upright_s": metrics["time_to_upright_s"],
        "hold_error_rad": metrics["hold_error_rad"],
        "solve_time_ms": metrics["solve_time_ms"],
        "control_period_s": metrics["control_period_s"],
        "solver_failures": metrics["controller_failures"],
        "solver": settings.solver,
        "latency": args.latency,
        "deadline_misses": metrics["deadline_misses"],
        "newton_iters": model.newton_iters,
        "horizon": settings.horizon,
        "horizon_s": settings.horizon * model.step_size,
        "hessian": settings.ipopt.hessian,
        "terminal_energy_weight": settings.terminal_energy_weight,
        "cold_starts": list(settings.cold_starts),
        "max_abs_torque": metrics["max_abs_torque"],
        "accumulated_cost": metrics["accumulated_cost"],
        "model": model.name,
        "true_model": args.true_model,
        "scene": str(args.scene),
        "init": args.init,
        "seed": args.seed,
        "duration_s": metrics["duration_s"],
        "build_s": controller.build_s,
        "compiled_from_cache": report.cached if report else None,
    }
    text = json_text(summary, indent=2)
    print(text)
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(text + "\n")
    if plot is not None:
        plot.parent.mkdir(parents=True, exist_ok=True)
        plot_episode(
            episode,
            plot,
            title=f"{model.name} on {env.scene_spec.name}: swung up = {summary['swung_up']}",
            torque_bound=float(np.max(np.abs(env.torque_high))),
        )
        print(f"plot: {plot}", file=sys.stderr)
    if video is not None:
        video.parent.mkdir(parents=True, exist_ok=True)
        write_video(frames, video, fps=1.0 / episode.control_period)
        print(f"video: {video}", file=sys.stderr)
    env.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
