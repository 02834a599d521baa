"""Whole closed loops' controls on fixed starts, to compare two commits: ``python -m benchmarks.loop_digest
OUT.npz`` on each commit (e.g. the older one's worktree on ``PYTHONPATH``), then ``python -m
benchmarks.loop_digest --compare A.npz B.npz``.

Each loop is the scene's real-time iteration in the waiting mode with wall-clock budgets that never bind (the
iteration counts alone bound it, as in ``tests/test_c_controller.py``), so the controls are a function of the
code alone, not of the machine's load: the learned and closed-form ball joint (unrolled dynamics, the lanes),
the learned damped pendulum (implicit dynamics) and the learned quadrotor. ``--compare`` prints the largest
control difference of each loop over its episode.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from fvin_mpc.control.closed_loop import run_episode
from fvin_mpc.control.flight import quadrotor_model, quadrotor_mpc, quadrotor_mpc_settings
from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings
from fvin_mpc.envs import QuadrotorEnv
from fvin_mpc.envs.scenes import resolve_scene

#: Wall-clock budgets that never bind (s).
UNBOUNDED = {"cold_budget_s": 600.0, "budget_s": 600.0}
#: (scene, closed form?, seconds, reset options, seed) per loop.
LOOPS = (("spherical_pendulum", False, 4.0, {"random": True}, 5),
         ("spherical_pendulum", True, 4.0, {"random": True}, 5),
         ("pendulum_damped", False, 4.0, {"random": True}, 5),
         ("quadrotor", False, 3.0, {"max_omega": 5.0}, 2))


def digest() -> dict[str, np.ndarray]:
    """``loop name → controls (T, m)``."""
    out = {}
    for scene, true_model, duration, options, seed in LOOPS:
        if scene == "quadrotor":
            env = QuadrotorEnv(resolve_scene(scene))
            controller = quadrotor_mpc(env, quadrotor_model(env, true_model=true_model),
                                       quadrotor_mpc_settings().updated(rti=UNBOUNDED))
        else:
            env = scene_env(scene, true_model=true_model)
            controller = scene_mpc(env, scene_model(env, true_model=true_model),
                                   scene_mpc_settings(env, solver="rti").updated(rti=UNBOUNDED))
        episode, _ = run_episode(env, controller, duration, options, seed=seed)
        name = f"{scene}-{'closed-form' if true_model else 'learned'}"
        out[name] = np.asarray(episode.u, dtype=float)
        print(f"{name}: {len(episode.u)} controls", flush=True)
    return out


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.loop_digest", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", nargs="+", type=Path, help="OUT.npz, or with --compare A.npz B.npz")
    parser.add_argument("--compare", action="store_true", help="compare two digests")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if len(args.paths) != (2 if args.compare else 1):
        parser.error("give OUT.npz, or --compare A.npz B.npz")
    if args.compare:
        a, b = (np.load(path) for path in args.paths)
        for name in sorted(set(a.files) | set(b.files)):
            if name not in a.files or name not in b.files:
                print(name, "only in", args.paths[0] if name in a.files else args.paths[1])
            elif a[name].shape != b[name].shape:
                print(name, f"episodes of different lengths {a[name].shape} and {b[name].shape}")
            else:
                difference = float(np.max(np.abs(a[name] - b[name])))
                print(name, "bit-identical" if difference == 0.0 else f"max |Δu| {difference:.3g} "
                      f"(max |u| {float(np.max(np.abs(a[name]))):.3g})")
        return 0
    np.savez(args.paths[0], **digest())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
