"""Swing a MuJoCo pendulum up with IPOPT MPC on the learned S3FVIN: ``python -m fvin_mpc.swingup``.

With no arguments: the shipped sign-invariant model of the ``pendulum`` scene, starting
hanging at rest, 10 s of closed loop in MuJoCo, a summary on stdout and a plot in
``swingup.png``. ``--true-model`` runs the same MPC on the closed-form rigid body read
off the scene's MJCF, for comparison.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .closed_loop import episode_metrics, plot_episode, run_episode, write_video
from .export import ExportedModel, from_checkpoint, from_rigid_body
from .mpc import MPC, MPCSettings


#: MPCSettings fields a built-in scene changes from the defaults (the CLI's options override them).
#: ``spherical_pendulum``: 1.5 N·m against 6 N·m of gravity torque about a slower axis (J ≈ 0.5)
#: needs several pumps; with the default 1.5 s horizon the plan stalls near the bottom, with
#: 2.5 s it swings up (docs/spherical.md). Cold solves from rest take ≈ 130 IPOPT iterations,
#: so the default limit of 100 would leave the body hanging (the zero fallback at rest).
#: ``pendulum_damped``: at horizons 30 and 40 the plan settles on a local optimum that never
#: swings up, with the learned and the closed-form model alike; 2.5 s escapes it (docs/scenes.md).
#: ``pendulum``: the 1.5 s horizon is shorter than a swing-up from near hanging; without the
#: terminal energy cost 1 of 50 evaluation episodes (learned and closed-form alike) never pumps
#: (docs/evaluation.md). The weight makes a full energy deficit cost 1000, against ≤ 40 for the
#: terminal orientation: near upright its gradient vanishes (the deficit is quadratic there).
SCENE_SETTINGS: dict[str, dict[str, Any]] = {
    "pendulum": {"terminal_energy_weight": 1000.0},
    "pendulum_damped": {"horizon": 50},
    "spherical_pendulum": {"horizon": 50, "max_iter": 300},
}


def scene_settings(scene: str, **overrides: Any) -> MPCSettings:
    """:class:`MPCSettings` for ``scene``: the defaults, the scene's :data:`SCENE_SETTINGS`, then ``overrides``."""
    fields = {**SCENE_SETTINGS.get(str(scene), {}), **{k: v for k, v in overrides.items() if v is not None}}
    return replace(MPCSettings(), **fields)


def default_checkpoint(scene: str) -> str:
    """The shipped sign-invariant checkpoint of a built-in scene."""
    return f"{Path(scene).stem}_sign-invariant"


def scene_model(env: Any, checkpoint: str | None = None, true_model: bool = False,
                newton_iters: int | None = None) -> ExportedModel:
    """The model the MPC plans with: a checkpoint's, or the scene's closed-form rigid body.

    Raises ``ValueError`` if the model's step differs from the env's control period.
    """
    from .rigid_body import from_mujoco

    base = env.unwrapped
    if true_model:
        body = from_mujoco(base.model, base.body_name)
        return from_rigid_body(body, base.dt, newton_iters or 2, name=f"true_{getattr(base.scene_spec, 'name', 'scene')}")
    model = from_checkpoint(checkpoint, newton_iters)
    if abs(model.step_size - base.dt) > 1e-9:
        raise ValueError(f"the model's step {model.step_size} s differs from the scene's control period {base.dt} s")
    if model.control_dim != base.action_space.shape[0]:
        raise ValueError(f"the model has {model.control_dim} controls, the scene {base.action_space.shape[0]}")
    return model


def scene_mpc(env: Any, model: ExportedModel, settings: MPCSettings = MPCSettings(), goal: Any = None) -> MPC:
    """An :class:`MPC` with the scene's goal and torque bounds."""
    base = env.unwrapped
    return MPC(model, settings, base.goal if goal is None else goal, base.torque_low, base.torque_high)


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
    parser.add_argument("--checkpoint", default=None,
                        help="shipped name or path (default: <scene>_sign-invariant)")
    parser.add_argument("--scene", default="pendulum", help="built-in scene or MJCF path")
    parser.add_argument("--body", default=None, help="observed body (default: the scene's)")
    parser.add_argument("--goal", type=float, nargs=4, default=None, metavar=("W", "X", "Y", "Z"),
                        help="goal quaternion (default: the scene's, upright)")
    parser.add_argument("--init", default="rest",
                        help="initial state: rest | random | comma-separated qpos,qvel (hinge: θ,θ̇)")
    parser.add_argument("--horizon", type=int, default=None,
                        help=f"MPC steps (default: {MPCSettings.horizon}, or the scene's in SCENE_SETTINGS)")
    parser.add_argument("--energy-weight", type=float, default=None,
                        help="terminal energy-deficit weight W_E (default: the scene's in SCENE_SETTINGS, else 0)")
    parser.add_argument("--newton-iters", type=int, default=None, help="K (default: the model's)")
    parser.add_argument("--hessian", choices=["gauss-newton", "exact", "limited-memory"], default=None,
                        help=f"Lagrangian Hessian (default: {MPCSettings.hessian})")
    parser.add_argument("--duration", type=float, default=10.0, help="seconds of closed loop")
    parser.add_argument("--seed", type=int, default=0, help="seeds the env (random init, sensor noise)")
    parser.add_argument("--true-model", action="store_true", help="plan with the closed-form rigid body instead")
    parser.add_argument("--json", type=Path, default=None, help="write the summary as JSON")
    parser.add_argument("--plot", type=Path, default=Path("swingup.png"), help="plot path ('' for none)")
    parser.add_argument("--video", type=Path, default=None, help="render an MP4 (headless: MUJOCO_GL=egl)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from envs import RigidBodyEnv

    env = RigidBodyEnv(scene=args.scene, body=args.body, goal=args.goal,
                       render_mode="rgb_array" if args.video else None)
    checkpoint = args.checkpoint or default_checkpoint(args.scene)
    model = scene_model(env, checkpoint, args.true_model, args.newton_iters)
    settings = scene_settings(args.scene, horizon=args.horizon, hessian=args.hessian,
                              terminal_energy_weight=args.energy_weight)
    controller = scene_mpc(env, model, settings)
    report = controller.compile_report
    print(f"model {model.name} (K = {model.newton_iters}, h = {model.step_size} s), horizon {settings.horizon} "
          f"({settings.horizon * model.step_size:.2f} s); solver built in {controller.build_s:.1f} s"
          + (f" ({'cached library' if report.cached else f'compiled in {report.compile_s:.1f} s'})" if report else ""),
          file=sys.stderr)
    episode, frames = run_episode(env, controller, args.duration, parse_init(args.init, env.joint_type),
                                  seed=args.seed, render=args.video is not None, progress=not args.quiet,
                                  description=f"swing-up {model.name}")
    metrics = episode_metrics(episode)
    summary = {
        "swung_up": metrics["swung_up"], "time_to_upright_s": metrics["time_to_upright_s"],
        "hold_error_rad": metrics["hold_error_rad"], "solve_time_ms": metrics["solve_time_ms"],
        "control_period_s": metrics["control_period_s"], "ipopt_failures": metrics["controller_failures"],
        "newton_iters": model.newton_iters, "horizon": settings.horizon, "horizon_s": settings.horizon * model.step_size,
        "hessian": settings.hessian, "terminal_energy_weight": settings.terminal_energy_weight,
        "max_abs_torque": metrics["max_abs_torque"],
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
        plot_episode(episode, args.plot, title=f"{model.name} on {args.scene}: swung up = {summary['swung_up']}",
                     torque_bound=float(np.max(np.abs(env.torque_high))))
        print(f"plot: {args.plot}", file=sys.stderr)
    if args.video:
        write_video(frames, args.video, fps=1.0 / episode.control_period)
        print(f"video: {args.video}", file=sys.stderr)
    env.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
