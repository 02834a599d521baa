"""Reference episodes of the real-time loop, recorded on one commit and replayed on another.

``python -m benchmarks.loop_replay record DIR`` runs every built-in scene's real-time iteration (learned and
closed form; the damped pendulum also knocked, the pendulum also with the prepared feedback) over one
closed-loop episode in the waiting mode, with wall-clock budgets that never bind (the iteration counts alone
bound the loop, so its controls are a function of the code, not of the machine's load), and writes each
episode's observations, times, controls and outcome to ``DIR``. ``python -m benchmarks.loop_replay replay
DIR`` judges the code on ``PYTHONPATH`` against them two ways:

* **paired**: the recorded observations fed to a fresh controller in order (``set_time``, call, ``prepare``):
  the largest difference of its controls from the recorded ones, per call — the loops' equality with the
  plant taken out;
* **closed loop**: the whole episode run again: success, the time to upright (or to recovery) and the
  accumulated cost against the recording's.

Recorded at one commit (e.g. a worktree of it on ``PYTHONPATH``) before a rewrite of the loop, replayed after.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from fvin_mpc.control.closed_loop import episode_metrics, run_episode
from fvin_mpc.control.flight import quadrotor_model, quadrotor_mpc, quadrotor_mpc_settings
from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings
from fvin_mpc.envs import QuadrotorEnv, RigidBodyEnv
from fvin_mpc.envs.scenes import resolve_scene

#: Wall-clock budgets that never bind (s).
UNBOUNDED = {"cold_budget_s": 600.0, "budget_s": 600.0}
#: name → (scene, closed form?, seconds, reset options, seed, variant).
LOOPS = {
    "pendulum-learned": ("pendulum", False, 4.0, {"random": True}, 0, None),
    "pendulum-closed-form": ("pendulum", True, 4.0, {"random": True}, 0, None),
    "pendulum-prepared": ("pendulum", True, 4.0, {"random": True}, 1, "prepared"),
    "pendulum_damped-learned": ("pendulum_damped", False, 4.0, {"random": True}, 5, None),
    "pendulum_damped-closed-form": ("pendulum_damped", True, 4.0, {"random": True}, 5, None),
    "pendulum_damped-knocked": ("pendulum_damped", True, 8.0, {"random": True}, 3, "knocked"),
    "spherical_pendulum-learned": ("spherical_pendulum", False, 4.0, {"random": True}, 5, None),
    "spherical_pendulum-closed-form": ("spherical_pendulum", True, 4.0, {"random": True}, 5, None),
    "quadrotor-learned": ("quadrotor", False, 3.0, {"max_omega": 5.0}, 2, None),
    "quadrotor-closed-form": ("quadrotor", True, 3.0, {"max_omega": 5.0}, 2, None),
}
#: Agreement the replay asks for: controls per call, and the outcome of a whole episode.
CONTROL_TOLERANCE = 1e-9
COST_TOLERANCE = 0.01


def loop_setup(name: str) -> tuple[Any, Any, tuple[Any, ...]]:
    """``(env, controller, (seconds, reset options, seed))`` of the loop ``name``."""

    scene, true_model, duration, options, seed, variant = LOOPS[name]
    if scene == "quadrotor":

        env = QuadrotorEnv(resolve_scene(scene))
        controller = quadrotor_mpc(env, quadrotor_model(env, true_model=true_model),
                                   quadrotor_mpc_settings().updated(rti=UNBOUNDED))
        return env, controller, (duration, options, seed)
    env = scene_env(scene, true_model=true_model)
    rti = {**UNBOUNDED, "feedback": "prepared"} if variant == "prepared" else UNBOUNDED
    settings = scene_mpc_settings(env, solver="rti").updated(rti=rti)
    controller = scene_mpc(env, scene_model(env, true_model=true_model), settings)
    if variant == "knocked":  # a 2 rad/s knock once held for a second: the plan restarts cold

        spec = resolve_scene(scene)
        env = RigidBodyEnv(scene=spec, physics=replace(spec.physics, impulse_delta_omega=2.0))
    return env, controller, (duration, options, seed)


def outcome(episode: Any) -> dict[str, Any]:

    metrics = episode_metrics(episode)
    keys = ("success", "time_to_upright_s", "time_to_recovery_s", "accumulated_cost")
    return {key: (None if metrics.get(key) is None else
                  (bool(metrics[key]) if key == "success" else float(metrics[key])))
            for key in keys if key in metrics}


def record(directory: Path, names: list[str]) -> None:

    directory.mkdir(parents=True, exist_ok=True)
    for name in names:
        env, controller, (duration, options, seed) = loop_setup(name)
        episode, _ = run_episode(env, controller, duration, options, seed=seed)
        infos = episode.controller_info
        np.savez(directory / f"{name}.npz", states=episode.states[:-1], time=episode.time[:-1], u=episode.u,
                 cold_start=np.array([str(i.get("cold_start") or "") for i in infos]),
                 fallback=np.array([str(f or "") for f in episode.fallback]))
        (directory / f"{name}.json").write_text(json.dumps(outcome(episode), indent=1) + "\n")
        print(f"{name}: {len(episode.u)} calls, {outcome(episode)}", flush=True)


def paired_difference(controller: Any, recording: Any) -> tuple[float, list[str]]:
    """The largest control difference over the recorded calls, and the cold starts' names per call."""
    controller.reset()
    largest, colds = 0.0, []
    for x, t, u in zip(recording["states"], recording["time"], recording["u"]):
        controller.set_time(float(t))
        control, info = controller(x)
        controller.prepare()
        largest = max(largest, float(np.max(np.abs(np.asarray(control) - u))))
        colds.append(str(info.get("cold_start") or ""))
    return largest, colds


def replay(directory: Path, names: list[str]) -> int:

    failures = 0
    print(f"{'loop':34s} {'paired max |Δu|':>16s}  cold starts  closed loop (recorded → now)")
    for name in names:
        recording = np.load(directory / f"{name}.npz")
        recorded = json.loads((directory / f"{name}.json").read_text())
        env, controller, (duration, options, seed) = loop_setup(name)
        difference, colds = paired_difference(controller, recording)
        same_colds = colds == [str(c) for c in recording["cold_start"]]
        episode, _ = run_episode(env, controller, duration, options, seed=seed)
        now = outcome(episode)
        period = float(env.unwrapped.dt)
        agrees = now["success"] == recorded["success"] and all(
            (now.get(key) is None) == (recorded.get(key) is None)
            and (now.get(key) is None or abs(now[key] - recorded[key]) <= period + 1e-9)
            for key in ("time_to_upright_s", "time_to_recovery_s") if key in recorded)
        cost_ratio = now["accumulated_cost"] / recorded["accumulated_cost"]
        agrees &= abs(cost_ratio - 1.0) <= COST_TOLERANCE
        ok = difference <= CONTROL_TOLERANCE and same_colds and agrees
        failures += not ok
        print(f"{name:34s} {difference:16.3g}  {'same' if same_colds else 'DIFFER':11s}  "
              f"success {recorded['success']}→{now['success']}, cost ×{cost_ratio:.6f}  "
              f"{'ok' if ok else 'NOT MET'}", flush=True)
    return 1 if failures else 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.loop_replay", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("action", choices=("record", "replay"))
    parser.add_argument("directory", type=Path, help="where the recordings are written or read")
    parser.add_argument("--loops", nargs="+", choices=sorted(LOOPS), default=list(LOOPS),
                        help="which loops (default: all)")
    parser.add_argument("--force", action="store_true", help="record over an existing directory's recordings")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.action == "record":
        existing = [name for name in args.loops if (args.directory / f"{name}.npz").exists()]
        if existing and not args.force:
            print(f"error: {args.directory} already holds recordings of {existing[0]} (add --force)", file=sys.stderr)
            return 2
        record(args.directory, args.loops)
        return 0
    missing = [name for name in args.loops if not (args.directory / f"{name}.npz").is_file()]
    if missing:
        print(f"error: no recording of {missing[0]} in {args.directory} (record it first)", file=sys.stderr)
        return 2
    return replay(args.directory, args.loops)


if __name__ == "__main__":
    raise SystemExit(main())
