"""Which parameter set the online estimator should fit: ``python -m benchmarks.adaptation_sets``.

For each pendulum scene (``--scenes``) and each change of the plant (``--changes``: the bob twice as heavy,
the motor at 70 %), transitions are recorded from the changed MuJoCo plant under random torques in the
motor's range (``--windows`` seeded windows of ``--window`` transitions from random states with |ω| ≤ 2 rad/s,
each followed by as many held-out transitions). On each window the estimator
(:class:`fvin_mpc.control.adaptation.ParameterEstimator`, ``--iterations`` Levenberg–Marquardt steps)
fits each parameter set on the scene's shipped learned model and on the closed-form model of the
*unchanged* MJCF; the report gives the held-out one-step prediction error after the fit relative to the
unfitted model's (lower is better; 1: no gain) and the fitted values. Offline: a model-quality figure; the
time of one Levenberg–Marquardt step (uncompiled CasADi, the window's size) is reported for scale only.

The truth, for reading the fitted values with the gains pinned (the free scale, see the estimator's
docstring): a bob twice as heavy is ``mass = 2``; a motor at 70 % is ``mass = 1/0.7 ≈ 1.43`` with the
gain pinned, or ``gain0 = 0.7`` with the mass pinned.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from dataclasses import replace
from typing import Any, Sequence

import numpy as np

from fvin_mpc.control.adaptation import ParameterEstimator, TransitionWindow
from fvin_mpc.control.scene import scene_env, scene_model
from fvin_mpc.core.errors import run_command
from fvin_mpc.envs import RigidBodyEnv
from fvin_mpc.envs.scenes import SCENES
from fvin_mpc.studies.report import markdown_table, write_report

#: Parameter sets compared: a label → the free parameters (the others pinned at their nominal values).
SETS: dict[str, tuple[str, ...]] = {
    "mass": ("mass",),
    "mass+damping": ("mass", "damping"),
    "gain": ("gain0",),
    "gain+damping": ("gain0", "damping"),
}
#: Plant changes: a label → (the declared plant effects, the motor's strength factor, the true parameters).
CHANGES: dict[str, tuple[dict[str, Any], float, dict[str, float]]] = {
    "bob x2": ({"mass_scale": 2.0}, 1.0, {"mass": 2.0}),
    "motor 70%": ({}, 0.7, {"gain0": 0.7}),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.adaptation_sets", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", default=["pendulum", "pendulum_damped"], choices=sorted(SCENES))
    parser.add_argument("--changes", nargs="+", default=list(CHANGES), choices=list(CHANGES))
    parser.add_argument("--windows", type=int, default=10, help="seeded windows per case (default: %(default)s)")
    parser.add_argument("--window", type=int, default=40, help="transitions per window (default: %(default)s)")
    parser.add_argument("--iterations", type=int, default=10, help="LM steps per window (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="default: %(default)s")
    parser.add_argument("--out-dir", default="docs", help="where adaptation-sets.{md,json} go (default: %(default)s)")
    return parser


def record(env: RigidBodyEnv, motor: float, count: int, rng: np.random.Generator) -> list[tuple[Any, Any, Any]]:
    """``count`` transitions ``(x, u, x_next)`` of the plant from a random state; ``u`` is what the controller
    commanded, ``motor × u`` what reached the joint (a weaker motor the controller does not know of)."""
    base = env.unwrapped
    x, _ = env.reset(seed=int(rng.integers(2**31)), options={"random": True, "max_omega": 2.0})
    bound = float(base.torque_high[0])
    transitions = []
    for _ in range(count):
        u = rng.uniform(-bound, bound, size=1)
        x_next = env.step(motor * u)[0]
        transitions.append((x, u, x_next))
        x = x_next
    return transitions


def window_of(transitions: list[tuple[Any, Any, Any]]) -> TransitionWindow:
    window = TransitionWindow(len(transitions))
    for transition in transitions:
        window.add(*transition)
    return window


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    from tqdm.auto import tqdm

    rows = []
    for scene in args.scenes:
        learned_env = scene_env(scene)
        models = {"learned": scene_model(learned_env), "closed form": scene_model(
            scene_env(scene, true_model=True), true_model=True)}
        for change in args.changes:
            effects, motor, truth = CHANGES[change]
            plant = RigidBodyEnv(scene, physics=replace(SCENES[scene].physics, **effects),
                                 control_period=learned_env.unwrapped.dt)
            rng = np.random.default_rng(args.seed)
            data = [record(plant, motor, 2 * args.window, rng) for _ in range(args.windows)]
            for model_name, model in models.items():
                for set_name, free in tqdm(SETS.items(), desc=f"{scene} {change} {model_name}", leave=False):
                    ratios, floors, fitted, step_ms = [], [], [], []
                    for transitions in data:
                        fit, held_out = window_of(transitions[:args.window]), window_of(transitions[args.window:])
                        estimator = ParameterEstimator(model, free=free)
                        unfitted = estimator.prediction_error(held_out)
                        floors.append(estimator.prediction_error(held_out, truth) / unfitted)
                        for _ in range(args.iterations):
                            start = time.perf_counter()
                            estimator.update(fit)
                            step_ms.append(1e3 * (time.perf_counter() - start))
                        ratios.append(estimator.prediction_error(held_out) / unfitted)
                        fitted.append(estimator.parameters)
                    rows.append({
                        "scene": scene, "change": change, "model": model_name, "set": set_name,
                        "held-out error / unfitted (median)": float(np.median(ratios)),
                        "(worst)": float(np.max(ratios)),
                        "true parameters / unfitted (median)": float(np.median(floors)),
                        "LM step ms (median)": float(np.median(step_ms)),
                        **{f"{name} (median)": float(np.median([f[name] for f in fitted])) for name in free},
                    })
                    print(f"{scene} {change} {model_name} {set_name}: {rows[-1]}", file=sys.stderr)
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    from pathlib import Path

    args = build_parser().parse_args(argv)
    rows = run(args)
    command = "python -m benchmarks.adaptation_sets " + " ".join(
        shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    columns = ["scene", "change", "model", "set", "held-out error / unfitted (median)", "(worst)",
               "true parameters / unfitted (median)", "LM step ms (median)", "mass (median)", "gain0 (median)",
               "damping (median)"]
    body = "\n".join([
        f"{args.windows} seeded windows of {args.window} transitions per case (random torques from random states, "
        f"|ω| ≤ 2 rad/s), {args.iterations} Levenberg–Marquardt steps each, error measured on the next "
        f"{args.window} transitions. Offline (model quality); the LM step's time is from the shared, loaded "
        "machine, for scale only. \"true parameters / unfitted\": the held-out error of the model given the "
        "change's true parameters (the oracle; the others nominal) — the "
        "floor the model's own one-step error leaves; a fit below it has soaked part of that error into a "
        "parameter.",
        "",
        markdown_table(rows, columns),
        "",
    ])
    write_report(Path(args.out_dir) / "adaptation-sets", "Which parameters to adapt", {"rows": rows}, body, command)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
