"""IPOPT against fatrop on the main command's problem: ``python -m benchmarks.nlp_peers`` (docs/peers.md).

The problem is ``python -m fvin_mpc.swingup``'s with its defaults: the ``pendulum`` scene, its shipped learned
checkpoint, the scene's MPC settings, 10 s of closed loop in waiting mode (the simulator waits for the solver). Both
solvers are :class:`~fvin_mpc.control.mpc.MPC` on that problem: ``solver="ipopt"`` as the command runs it
(Gauss–Newton Hessian, compiled functions, primal–dual warm start) and ``solver="fatrop"`` as it can run (exact
Hessian, functions expanded and interpreted: what ``MPCSettings`` allows fatrop; primal warm start). Per solver and
start: the time per solve (median, p90, max over the episode's calls), iterations, and the closed-loop outcome as the
command reports it (swung up, time to upright, hold error, accumulated cost). Starts: hanging at rest (the command's
default, ``--init rest``; its seed changes nothing there) and ``--seeds`` random starts (``--init random``). Both
solvers run in one process, start by start, so their times are comparable as ratios; the machine is shared, so
absolute times are noisy.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fvin_mpc._cli import run_command
from fvin_mpc.control.closed_loop import episode_metrics, run_episode
from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings, scene_scales
from fvin_mpc.core.errors import UsageError
from fvin_mpc.swingup import default_duration

#: (label, MPCSettings overrides): IPOPT as the command runs it, fatrop as the settings allow it.
SOLVERS: dict[str, dict[str, Any]] = {
    "ipopt": {},
    "fatrop": {"solver": "fatrop", "ipopt": {"hessian": "exact"}, "compile": "none"},
}


def episode_row(env: Any, controller: Any, duration: float, options: dict[str, Any] | None, seed: int
                ) -> dict[str, Any]:
    """One closed-loop episode of ``controller``: the command's summary numbers and the solves' times."""

    episode, _ = run_episode(env, controller, duration, options, seed=seed, latency="none")
    metrics = episode_metrics(episode)
    infos = episode.controller_info
    solve_ms = 1e3 * np.array([info["solve_time_s"] for info in infos])
    iterations = np.array([info.get("iterations", np.nan) for info in infos], dtype=float)
    return {"swung_up": metrics["swung_up"], "time_to_upright_s": metrics["time_to_upright_s"],
            "hold_error_rad": metrics["hold_error_rad"], "accumulated_cost": metrics["accumulated_cost"],
            "solver_failures": metrics["controller_failures"],
            "solve_ms_median": float(np.median(solve_ms)), "solve_ms_p90": float(np.percentile(solve_ms, 90)),
            "solve_ms_max": float(solve_ms.max()), "first_solve_ms": float(solve_ms[0]),
            "iterations_median": float(np.nanmedian(iterations))}


def run(seeds: Sequence[int], solvers: Sequence[str], duration: float | None) -> list[dict[str, Any]]:
    """Hanging at rest, then the random start of each of ``seeds``, each by every solver in turn."""

    env = scene_env("pendulum")
    model = scene_model(env)
    settings = scene_mpc_settings(env)
    duration = default_duration(scene_scales(env)) if duration is None else duration
    controllers = {name: scene_mpc(env, model, settings.updated(**SOLVERS[name])) for name in solvers}
    starts: list[tuple[str, dict[str, Any] | None, int]] = [("rest", None, 0)]
    starts += [("random", {"random": True, "max_omega": 2.0}, seed) for seed in seeds]
    rows = []
    for init, options, seed in starts:
        for name, controller in controllers.items():
            row = {"solver": name, "init": init, "seed": seed, "build_s": controller.build_s,
                   **episode_row(env, controller, duration, options, seed)}
            rows.append(row)
            print(f"{init} seed {seed} {name}: swung up {row['swung_up']}, upright at {row['time_to_upright_s']}, "
                  f"cost {row['accumulated_cost']:.1f}, solve {row['solve_ms_median']:.1f} ms median",
                  file=sys.stderr)
    env.close()
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    reference = {(r["init"], r["seed"]): r["solve_ms_median"] for r in rows if r["solver"] == "ipopt"}
    lines = ["| start | solver | solve ms median / p90 / max | × IPOPT | iterations median | swung up | "
             "time to upright s | hold error rad | accumulated cost | failures |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        base = reference.get((r["init"], r["seed"]))
        ratio = "—" if base is None else f"{r['solve_ms_median'] / base:.1f}"
        upright = "—" if r["time_to_upright_s"] is None else f"{r['time_to_upright_s']:.2f}"
        lines.append(f"| {r['init']} (seed {r['seed']}) | {r['solver']} | {r['solve_ms_median']:.1f} / "
                     f"{r['solve_ms_p90']:.1f} / {r['solve_ms_max']:.0f} | {ratio} | {r['iterations_median']:.0f} | "
                     f"{r['swung_up']} | {upright} | {r['hold_error_rad']:.3f} | {r['accumulated_cost']:.1f} | "
                     f"{r['solver_failures']} |")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.nlp_peers", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=3, help="random starts besides rest (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=None,
                        help="run the random start of this seed only (besides rest); overrides --seeds")
    parser.add_argument("--solvers", nargs="+", choices=sorted(SOLVERS), default=list(SOLVERS),
                        help="default: %(default)s")
    parser.add_argument("--duration", type=float, default=None, help="seconds of closed loop (default: swingup's)")
    parser.add_argument("--out", type=Path, default=None, help="JSON results (refused if present, unless --force)")
    parser.add_argument("--force", action="store_true", help="replace --out")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    import torch

    torch.set_num_threads(1)
    args = build_parser().parse_args(argv)
    if args.seeds < 0 or (args.duration is not None and not args.duration > 0.0):
        raise UsageError("--seeds must be >= 0 and --duration > 0")
    if args.out is not None and args.out.exists() and not args.force:
        raise UsageError(f"--out {args.out} exists; pass --force to replace it, or give another path")
    rows = run(range(1, args.seeds + 1) if args.seed is None else [args.seed], args.solvers, args.duration)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"command": "python -m benchmarks.nlp_peers", "rows": rows}, indent=1))
    print(table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
