"""What the cold start's iteration count buys a craft: ``python -m benchmarks.cold_count``.

The C loop bounds its cold call by counts (``RTIOptions.cold_iter`` iterations per first guess), not by the
wall clock; on a quadrotor 10 took longer than a 20 ms period, which is why its default is now 2
(docs/c-controller.md). This flies
``fly``'s recovery starts and its figure-eight in **waiting mode** (the simulator waits for the controller: the
count's effect on the plan, not on timing; the wall-clock budgets lifted, as the C loop has none) with each
``--cold-iters`` value, both models, on the built-in craft or any flyer (``--scenes``, with ``--checkpoints``
beside them for the learned model). One JSON row per (scene, model, count): recoveries, their median and worst
time, the figure-eight's RMS position error.
"""

from __future__ import annotations

import argparse
import json
from typing import Sequence

import numpy as np

from fvin_mpc.core.errors import run_command
from fvin_mpc.envs.quadrotor_env import QuadrotorEnv
from fvin_mpc.studies.flight_report import make_controller, run_figure_eight, run_recovery


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.cold_count", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", default=["quadrotor"], help="built-in names or MJCF paths "
                        "(default: %(default)s)")
    parser.add_argument("--checkpoints", nargs="+", default=None,
                        help="the learned model of each scene, in order (default: the scene's shipped one)")
    parser.add_argument("--cold-iters", nargs="+", type=int, default=[10, 2], help="default: %(default)s")
    parser.add_argument("--models", nargs="+", default=["closed-form", "learned"], choices=("closed-form", "learned"))
    parser.add_argument("--starts", type=int, default=20, help="recovery starts (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="the recovery starts' seed (default: %(default)s)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from tqdm.auto import tqdm

    args = build_parser().parse_args(argv)
    checkpoints = args.checkpoints or [None] * len(args.scenes)
    if len(checkpoints) != len(args.scenes) or min(args.cold_iters) < 1 or args.starts < 1:
        raise ValueError("need one checkpoint per scene, --cold-iters >= 1 and --starts >= 1")
    cells = [(scene, checkpoint, model, count) for scene, checkpoint in zip(args.scenes, checkpoints)
             for model in args.models for count in args.cold_iters]
    for scene, checkpoint, model, count in tqdm(cells, desc="cells"):
        env = QuadrotorEnv(scene)
        waiting = {"cold_iter": count, "cold_budget_s": float("inf"), "budget_s": float("inf")}
        controller = make_controller(env, model, checkpoint, rti=waiting)
        rows, _, _ = run_recovery(env, controller, args.starts, args.seed, "none", progress=False)
        figure_eight, _, _ = run_figure_eight(env, controller, "none", progress=False)
        env.close()
        times = [row["time_to_recover_s"] for row in rows if row["recovered"]]
        print(json.dumps({"scene": scene, "model": model, "cold_iter": count,
                          "recovered": f"{sum(row['recovered'] for row in rows)}/{len(rows)}",
                          "recovery_s_median": round(float(np.median(times)), 3) if times else None,
                          "recovery_s_worst": round(max(times), 3) if times else None,
                          "figure_eight_rms_mm": round(1e3 * figure_eight["rms_position_m"], 4)}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
