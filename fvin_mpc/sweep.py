"""Training sweep: a grid of models trained as one job: ``python -m fvin_mpc.sweep``.

The command line of :mod:`fvin_mpc.studies.training_sweep`, whose docstring (the method) is this command's ``--help``.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path
from typing import Any, Callable, Sequence

import fvin_mpc.studies.training_sweep as sweep_module
from fvin_mpc._cli import (
    add_backend_arguments,
    backend_options,
    check_output_folder,
    nonnegative_int,
    number_in,
    positive_float,
    positive_int,
    run_command,
    seed_value,
)
from fvin_mpc.learning.training import DEFAULT_DATA, OPTIMIZERS
from fvin_mpc.studies.training_sweep import SweepConfig, run_sweep, sweep_table, write_report


def _list(kind: Callable[[str], Any]) -> Callable[[str], tuple[Any, ...]]:
    def parse(text: str) -> tuple[Any, ...]:
        try:
            values = tuple(kind(part.strip()) for part in text.split(",") if part.strip())
        except ValueError as error:
            raise argparse.ArgumentTypeError(str(error)) from None
        if not values:
            raise argparse.ArgumentTypeError("expected a comma-separated list")
        return values
    return parse


def _size(text: str) -> int | None:
    return None if text == "all" else number_in_sizes(text)


#: A run's data size: at least 2 trajectories (one is held out for validation).
number_in_sizes = number_in(int, 2)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.sweep", description=sweep_module.__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--data", type=Path, default=DEFAULT_DATA, help="data file from fvin_mpc.collect (default: %(default)s)"
    )
    parser.add_argument("--variants", type=_list(str), default=("sign-invariant",),
                        help="comma-separated model variants (default: sign-invariant)")
    parser.add_argument("--widths", type=_list(positive_int), default=(16,),
                        help="comma-separated hidden widths (default: 16)")
    parser.add_argument("--sizes", type=_list(_size), default=(None,),
                        help="comma-separated trajectories per run, or all (default: all)")
    parser.add_argument("--seeds", type=_list(nonnegative_int), default=(0,),
                        help="comma-separated training seeds (default: 0)")
    parser.add_argument("--seed", type=seed_value, default=0,
                        help="seed of which trajectories each data size takes (default: %(default)s; the training "
                             "seeds are --seeds)")
    parser.add_argument("--hidden-layers", type=positive_int, default=2,
                        help="hidden layers per MLP (default: %(default)s)")
    parser.add_argument("--dissipation", action=argparse.BooleanOptionalAction, default=None,
                        help="learn a damping term −Dω (default: on when the data's scene declares joint damping)")
    parser.add_argument(
        "--optimizer", choices=OPTIMIZERS, default=None, help="training optimizer (default: train's, lm)"
    )
    parser.add_argument(
        "--iterations", type=positive_int, default=None, help="most iterations per run (default: the optimizer's)"
    )
    parser.add_argument("--patience", type=positive_int, default=None,
                        help="early-stopping patience (default: train's)")
    parser.add_argument("--time-limit", type=positive_float, default=None,
                        help="seconds of training per run (default: none)")
    add_backend_arguments(parser, "runs in parallel: processes, or Ray actors with --backend ray; each run uses one "
                                  "torch thread")
    parser.add_argument("--out-dir", type=Path, default=Path("checkpoints/sweep"),
                        help="checkpoints, sweep.md and sweep.json (default: %(default)s); a folder holding an "
                             "earlier sweep's files is replaced only with --force")
    parser.add_argument("--force", action="store_true", help="replace the files of an earlier sweep in --out-dir")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    train = {"optimizer": args.optimizer, "iterations": args.iterations, "patience": args.patience,
             "time_limit_s": args.time_limit}
    try:
        check_output_folder(args.out_dir, "--out-dir", args.force, ("sweep.md", "sweep.json", "*.safetensors"))
        config = SweepConfig(data=str(args.data), variants=args.variants, widths=args.widths, seeds=args.seeds,
                             sizes=args.sizes, subset_seed=args.seed, hidden_layers=args.hidden_layers,
                             dissipation=args.dissipation,
                             train=tuple((k, v) for k, v in train.items() if v is not None))
        backend = backend_options(args)
        result = run_sweep(config, args.out_dir, args.workers, progress=not args.quiet, **backend)
    except (ValueError, FileNotFoundError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    command = "python -m fvin_mpc.sweep " + " ".join(shlex.quote(a) for a in argv)
    written = write_report(result, args.out_dir, command.strip())
    print(sweep_table(result))
    print(json.dumps({"runs": len(result.runs), "failed": len(result.failures),
                      "wall_clock_s": round(result.wall_clock_s, 1)}), file=sys.stderr)
    print("wrote " + ", ".join(str(p) for p in written), file=sys.stderr)
    return 1 if result.failures else 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
