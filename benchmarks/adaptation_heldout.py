"""Does a fitted parameter set hold beyond its window? ``python -m benchmarks.adaptation_heldout``.

The free-body sets of docs/adaptation.md ("Which set serves") tracked the changed quadrotor very differently: the mass
alone 1.05×, rank-1 corrections of the networks' last layers 4.1×. This asks why, offline: the learned craft (exported
with ``--low-rank`` corrections) flies the figure-eight on the changed plant (``--change``, as
``benchmarks.payload_adaptation``'s; waiting mode, the shipped controller with its disturbance estimate, so the
transitions are the ones a controller meets), and from 2 s after the change on, each of ``--windows`` windows of
``--window`` transitions is fitted from the nominal estimate by every set (``--iterations`` Levenberg–Marquardt steps
of :class:`fvin_mpc.control.adaptation.ParameterEstimator`, no excitation gate). Reported per set: the window's
own one-step error after the fit and the error on the ``--ahead`` transitions that follow it (held out), each
relative to the unfitted model's on the same transitions (1: no gain; lower is better). A set that fits its window
but not what follows is fitting the window, not the body. Model quality; no timing.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from benchmarks.payload_adaptation import SCENE, change_time, scene_physics
from fvin_mpc.control.adaptation import ParameterEstimator, TransitionWindow
from fvin_mpc.control.closed_loop import run_episode
from fvin_mpc.core.errors import UsageError, run_command
from fvin_mpc.envs import QuadrotorEnv
from fvin_mpc.studies.flight_report import figure_eight, make_controller
from fvin_mpc.studies.report import markdown_table, write_report

#: The sets compared: a label → the estimator's free parameters.
SETS: dict[str, tuple[str, ...]] = {
    "mass": ("mass",),
    "gain0 … gain3": ("gain0", "gain1", "gain2", "gain3"),
    "lowrank": ("lowrank",),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.adaptation_heldout", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--change", choices=("payload", "rotor"), default="payload",
                        help="+50 %% mass with the centre 2 cm down, or rotor 0 at 70 %% (default: %(default)s)")
    parser.add_argument("--change-at", type=float, default=4.0,
                        help="the change comes at this time plus a seeded share of a second (default: %(default)s)")
    parser.add_argument("--low-rank", type=int, default=1, help="rank of the corrections (default: %(default)s)")
    parser.add_argument("--windows", type=int, default=8, help="windows per flight (default: %(default)s)")
    parser.add_argument("--window", type=int, default=40, help="transitions per window (default: %(default)s)")
    parser.add_argument("--ahead", type=int, default=30,
                        help="held-out transitions after each window (default: %(default)s: the plan's 0.6 s)")
    parser.add_argument("--iterations", type=int, default=30, help="LM steps per fit (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="the flight's seed (default: %(default)s)")
    parser.add_argument("--out-dir", default="docs/adaptation/heldout", help="default: %(default)s")
    return parser


def flight(args: argparse.Namespace) -> tuple[Any, np.ndarray, np.ndarray, float]:
    """The learned model, the flight's states and applied controls, and the change's time."""
    at = change_time(args, args.seed)
    declared = scene_physics(SCENE)
    physics = (replace(declared, mass_change=(at, 1.5, (0.0, 0.0, -0.02))) if args.change == "payload"
               else replace(declared, actuator_change=(at, 0, 0.7)))
    env = QuadrotorEnv(SCENE, physics=physics)
    controller = make_controller(env, "learned", None, low_rank=args.low_rank)
    controller.set_reference(figure_eight(env))
    episode, _ = run_episode(env, controller, at + 2.0 + (args.windows * args.window + args.ahead) * env.unwrapped.dt
                             + 0.1, {"hover": True}, seed=args.seed, latency="none", progress=True,
                             description="flight")
    env.close()
    return controller.model, episode.states, episode.u, at


def window_of(states: np.ndarray, controls: np.ndarray, start: int, length: int) -> TransitionWindow:
    window = TransitionWindow(length)
    for k in range(start, start + length):
        window.add(states[k], controls[k], states[k + 1])
    return window


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    from tqdm.auto import tqdm

    model, states, controls, at = flight(args)
    first = int(np.searchsorted(np.arange(len(controls)) * model.step_size, at + 2.0))
    results: dict[str, list[tuple[float, float]]] = {name: [] for name in SETS}
    fitted: dict[str, int] = {}
    for i in tqdm(range(args.windows), desc="windows"):
        start = first + i * args.window
        fitted_on = window_of(states, controls, start, args.window)
        held_out = window_of(states, controls, start + args.window, args.ahead)
        for name, free in SETS.items():
            estimator = ParameterEstimator(model, free=free, min_effect=0.0)
            fitted[name] = len(estimator.free)
            before = (estimator.prediction_error(fitted_on), estimator.prediction_error(held_out))
            for _ in range(args.iterations):
                estimator.update(fitted_on)
            after = (estimator.prediction_error(fitted_on), estimator.prediction_error(held_out))
            results[name].append((after[0] / before[0], after[1] / before[1]))
    rows = []
    for name, ratios in results.items():
        window_ratio, ahead_ratio = np.array(ratios).T
        rows.append({"set": name, "numbers fitted": fitted[name],
                     "window error / unfitted (median)": float(np.median(window_ratio)),
                     "held-out error / unfitted (median)": float(np.median(ahead_ratio)),
                     "(worst)": float(np.max(ahead_ratio))})
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if min(args.windows, args.window, args.ahead, args.iterations, args.low_rank) < 1:
        raise UsageError("--windows, --window, --ahead, --iterations and --low-rank must be >= 1")
    rows = run(args)
    command = "python -m benchmarks.adaptation_heldout " + " ".join(
        shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    what = "a payload (+50 %, centre 2 cm down)" if args.change == "payload" else "rotor 0 at 70 %"
    body = "\n".join([
        f"The learned quadrotor (rank-{args.low_rank} corrections exported) flies the figure-eight with {what} "
        f"(seed {args.seed}, waiting mode); {args.windows} consecutive windows of {args.window} transitions from 2 s "
        f"after the change, each fitted from the nominal estimate by {args.iterations} LM steps per set (no "
        f"excitation gate); errors relative to the unfitted model's, on the window and on the {args.ahead} "
        "transitions after it.",
        "",
        markdown_table(rows, list(rows[0])),
        "",
    ])
    write_report(Path(args.out_dir) / "adaptation-heldout", "Fitted on a window, judged after it", {"rows": rows},
                 body, command)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
