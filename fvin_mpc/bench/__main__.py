"""``python -m fvin_mpc.bench <study>`` — accuracy-vs-time studies (see :mod:`fvin_mpc.bench`)."""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

#: study name → module (each has ``run(quick, seed, repeats, **options) -> StudyResult``).
STUDIES = {
    "train-speed": "fvin_mpc.bench.train_speed",
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.bench", description=__doc__)
    parser.add_argument("study", choices=sorted(STUDIES), help="which study to run")
    parser.add_argument("--quick", action="store_true", help="tiny workload (used by the test suite)")
    parser.add_argument("--out-dir", type=Path, default=Path("docs/bench"), help="where to write (default: %(default)s)")
    parser.add_argument("--repeats", type=int, default=5, help="timing repeats per configuration")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    from . import write_study

    module = importlib.import_module(STUDIES[args.study])
    result = module.run(quick=args.quick, seed=args.seed, repeats=args.repeats)
    paths = write_study(result, args.out_dir, argv)
    print(paths["md"].read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
