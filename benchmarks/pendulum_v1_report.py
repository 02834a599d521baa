"""The learned model's MPC on Gymnasium's own ``Pendulum-v1``: ``python -m benchmarks.pendulum_v1_report``.

The command line of :mod:`benchmarks.pendulum_v1_mpc`, whose docstring (the method) is this command's ``--help``.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path
from typing import Sequence

import benchmarks.pendulum_v1_mpc as pendulum_v1_module
from benchmarks.pendulum_v1_mpc import (
    REFERENCE_GRIDS,
    BenchmarkConfig,
    plot_returns,
    run_benchmark,
    summarize,
    write_markdown,
)
from benchmarks.pendulum_v1_plan import SwingUpConfig, describe_swing_up, run_swing_up_benchmark
from fvin_mpc._cli import add_backend_arguments, backend_options, checked_scene_and_checkpoint, exit_status, run_command
from fvin_mpc.studies.pool import TasksFailed


def _grids(text: str) -> tuple[tuple[int, int], ...]:
    try:
        grids = tuple(tuple(int(n) for n in item.split("x")) for item in text.split(","))
    except ValueError:
        grids = ()
    if not grids or any(len(g) != 2 for g in grids):
        raise argparse.ArgumentTypeError(f"expected THETAxRATE[,THETAxRATE...], e.g. 256x129,512x257; got {text!r}")
    return grids  # type: ignore[return-value]


def _positive_ints(text: str) -> tuple[int, ...]:
    try:
        values = tuple(int(item) for item in text.split(","))
    except ValueError:
        values = ()
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers N[,N...], e.g. 30 or 30,40; got {text!r}")
    return values


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.pendulum_v1_report",
        description=pendulum_v1_module.__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--checkpoint", default=BenchmarkConfig.checkpoint, help="learned model (default: %(default)s)")
    parser.add_argument("--true-model", action="store_true", help="plan with the closed-form pendulum instead")
    parser.add_argument("--horizon", type=int, default=30, help="MPC steps (default: %(default)s)")
    parser.add_argument(
        "--episodes", type=int, default=100, help="episodes, seeds seed … seed+episodes−1 (default: %(default)s)"
    )
    parser.add_argument("--seed", type=int, default=0, help="first env.reset seed (default: %(default)s)")
    parser.add_argument(
        "--energy-weight",
        type=float,
        default=None,
        help="terminal energy-deficit weight W_E (default: the scenes' default, DEFAULT_TERMINAL_ENERGY_WEIGHT)",
    )
    parser.add_argument("--solver", choices=["ipopt", "rti"], default="ipopt",
                        help="ipopt: solved to convergence every step; rti: one real-time iteration per step "
                             "(default: %(default)s)")
    parser.add_argument("--rti-cold-solver", choices=["rti", "ipopt"], default="rti",
                        help="with --solver rti: the first call's plan from budgeted RTI iterations or from IPOPT "
                             "(default: %(default)s)")
    parser.add_argument("--rti-dynamics", choices=["unrolled", "implicit"], default=None,
                        help="with --solver rti: the dynamics constraint (fvin_mpc.control.implicit_dynamics; "
                             "default: the pendulum scene's RTI setting)")
    parser.add_argument("--single-start", action="store_true",
                        help="plain MPC: one first guess per episode instead of the multi-start")
    parser.add_argument("--rank-cold-starts", action="store_true",
                        help="the multi-start cold call keeps the plan with the lowest estimate of the episode's "
                             "Pendulum-v1 cost (stage costs + the learned model's value after the horizon) instead "
                             "of the lowest NLP cost")
    parser.add_argument("--dp-swing-up", action="store_true",
                        help="per episode, simulate on the learned model the plain MPC and a swing-up by the "
                             "learned model's DP policy handing over to the MPC once the swing-up fits in the "
                             "horizon; the swing-up runs if cheaper there by more than --dp-choice-margin, else "
                             "the MPC (benchmarks.pendulum_v1_plan; learned model only)")
    parser.add_argument("--dp-lookahead", type=_positive_ints, default=None,
                        help="with --dp-swing-up: the handover's greedy-rollout lookaheads, one candidate each, "
                             "as N[,N...] (default: 30)")
    parser.add_argument("--dp-simulated-steps", type=int, default=None,
                        help="with --dp-swing-up: steps each candidate is simulated for the choice (default: 120)")
    parser.add_argument("--dp-choice-margin", type=float, default=None,
                        help="with --dp-swing-up: a swing-up runs only if its simulated cost is lower than the plain "
                             "MPC's by more than this (default: 10)")
    parser.add_argument("--value-grid", type=_grids, default=((256, 129),),
                        help="with --rank-cold-starts or --dp-swing-up: the value's DP grid THETAxRATE "
                             "(default: 256x129)")
    parser.add_argument("--no-reference", action="store_true", help="skip the per-seed global reference")
    parser.add_argument("--reference-grids", type=_grids, default=REFERENCE_GRIDS,
                        help="the reference's DP grids, coarse to fine, as THETAxRATE,... (at least two; default: "
                             + ",".join(f"{a}x{b}" for a, b in REFERENCE_GRIDS) + ")")
    parser.add_argument("--reference-from", type=Path, default=None,
                        help="reuse an earlier run's JSON's reference search (same seeds and DP grids; it does not "
                             "depend on the MPC) and polish only this run's MPC episodes")
    parser.add_argument("--previous", type=Path, default=None,
                        help="an earlier run's JSON: its MPC returns and references per seed go into the table")
    add_backend_arguments(parser)
    parser.add_argument("--out", type=Path, default=Path("docs/pendulum-v1.md"),
                        help="Markdown report; .json and .png next to it (default: %(default)s)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    try:
        options = dict(checkpoint=args.checkpoint, true_model=args.true_model, horizon=args.horizon,
                       episodes=args.episodes, seed=args.seed, reference=not args.no_reference,
                       multistart=not args.single_start, terminal_energy_weight=args.energy_weight,
                       solver=args.solver, rti_cold_solver=args.rti_cold_solver, rti_dynamics=args.rti_dynamics,
                       reference_grids=args.reference_grids,
                       rank_cold_starts=args.rank_cold_starts, value_grid=args.value_grid[0])
        swing_up = {"dp_lookaheads": args.dp_lookahead, "dp_simulated_steps": args.dp_simulated_steps,
                    "dp_choice_margin": args.dp_choice_margin}
        if not args.dp_swing_up and any(v is not None for v in swing_up.values()):
            raise ValueError("--dp-lookahead, --dp-simulated-steps and --dp-choice-margin need --dp-swing-up")
        if args.dp_swing_up:

            config = SwingUpConfig(**options, **{k: v for k, v in swing_up.items() if v is not None})
        else:
            config = BenchmarkConfig(**options)
        previous = json.loads(args.previous.read_text()) if args.previous else None
        if not config.true_model:  # a clear error before any worker starts (Pendulum-v1: one torque)
            checked_scene_and_checkpoint("pendulum", config.checkpoint, command="pendulum_v1", controls=1)
        backend = backend_options(args)
        reference_from = json.loads(args.reference_from.read_text()) if args.reference_from else None
        if args.dp_swing_up:

            records = run_swing_up_benchmark(config, args.workers, progress=not args.quiet,
                                             reference_from=reference_from, **backend)
        else:
            records = run_benchmark(config, args.workers, progress=not args.quiet, reference_from=reference_from,
                                    **backend)
    except (ValueError, FileNotFoundError, TasksFailed) as error:
        return exit_status(error)
    summary = summarize(records)
    command = "python -m benchmarks.pendulum_v1_report " + " ".join(shlex.quote(a) for a in argv)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    label = "MPC (true model)" if config.true_model else "MPC (learned)"
    plot_returns(records, args.out.with_suffix(".png"), label)
    write_markdown(summary, records, config, command.strip(), args.out, previous,
                   str(args.reference_from) if args.reference_from else None)
    if args.dp_swing_up:

        describe_swing_up(args.out, config, records)
    print(json.dumps(summary, indent=2))
    print(f"wrote {args.out}, {args.out.with_suffix('.json')}, {args.out.with_suffix('.png')}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
