"""``python -m benchmarks <study>`` — accuracy-vs-time studies (see :mod:`benchmarks`).

Every study writes ``<out-dir>/<study>.{json,md,png}``; ``python -m benchmarks <study> --help``
lists its own options.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

from benchmarks.study import StudySkipped, write_study
from fvin_mpc._cli import add_backend_arguments, backend_options, exit_status, run_command
from fvin_mpc.core.errors import UsageError
from fvin_mpc.studies.pool import TasksFailed

#: study name → module (each has ``run(quick, seed, repeats, **options) -> StudyResult`` and
#: optionally ``add_arguments(parser)`` for its own options).
STUDIES = {
    "train-speed": "benchmarks.train_speed",
    "newton": "benchmarks.newton",
    "horizon": "benchmarks.horizon",
    "width": "benchmarks.width",
    "solver": "benchmarks.solver",
    "rti": "benchmarks.rti_knobs",
    "ops": "benchmarks.ops",
    "sim": "benchmarks.sim",
    "paper": "benchmarks.paper",
    "data-efficiency": "benchmarks.data_efficiency",
    "data-efficiency-terms": "benchmarks.data_efficiency_terms",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    subparsers = parser.add_subparsers(dest="study", required=True, metavar="study",
                                       help=f"one of: {', '.join(STUDIES)}")
    for name, module_name in STUDIES.items():
        module = importlib.import_module(module_name)
        summary = (module.__doc__ or "").strip().splitlines()[0] if module.__doc__ else name
        sub = subparsers.add_parser(name, help=summary, description=module.__doc__,
                                    formatter_class=argparse.RawDescriptionHelpFormatter)
        sub.add_argument("--quick", action="store_true", help="tiny workload (used by the test suite)")
        sub.add_argument(
            "--out-dir", type=Path, default=Path("docs/bench"), help="where to write (default: %(default)s)"
        )
        sub.add_argument(
            "--repeats", type=int, default=5, help="timing repeats per configuration (default: %(default)s)"
        )
        sub.add_argument(
            "--seed", type=int, default=0, help="seeds data, initial states and training (default: %(default)s)"
        )
        if hasattr(module, "add_arguments"):
            module.add_arguments(sub)
        if getattr(module, "PARALLEL_ROWS", False):
            add_backend_arguments(sub, "rows in parallel (processes, or Ray actors with --backend ray); the rows' "
                                       "timings then include the contention")
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(argv)
    if args.repeats < 1:
        raise UsageError(f"--repeats must be >= 1, got {args.repeats}")

    module = importlib.import_module(STUDIES[args.study])
    options = {k: v for k, v in vars(args).items() if k not in ("study", "quick", "out_dir", "repeats", "seed")}
    try:
        if "backend" in options:
            backend_options(args)  # checks --workers, --ray-address and that Ray is there
        result = module.run(quick=args.quick, seed=args.seed, repeats=args.repeats, **options)
    except StudySkipped as reason:
        print(f"skipped {args.study}: {reason}", file=sys.stderr)
        return 0
    except (ValueError, FileNotFoundError, TasksFailed) as error:
        return exit_status(error)
    paths = write_study(result, args.out_dir, argv)
    print(paths["md"].read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
