"""Write a checkpoint's step ``F(x, u)`` as a CasADi file: ``python -m fvin_mpc.export``.

The export itself (and the compile cache) is :mod:`fvin_mpc.control.model_export`.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Sequence

from fvin_mpc._cli import run_command
from fvin_mpc.control.model_export import from_checkpoint, save_function
from fvin_mpc.envs.scenes import resolve_scene


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.export", description=__doc__,
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--checkpoint", default=resolve_scene("pendulum").default_checkpoint,
                        help="shipped name or path")
    parser.add_argument("--newton-iters", type=int, default=None, help="K unrolled (default: the checkpoint's)")
    parser.add_argument("--out", type=Path, default=None, help="output file (default: <checkpoint>_K<K>.casadi)")
    parser.add_argument("--seed", type=int, default=0, help="unused (the export is deterministic); for CLI uniformity")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m fvin_mpc.export``: write a checkpoint's step ``F(x, u)`` as a CasADi file."""
    args = build_parser().parse_args(argv)
    model = from_checkpoint(args.checkpoint, args.newton_iters)
    out = args.out or Path(f"{model.name}_K{model.newton_iters}.casadi")
    save_function(model.step, out)
    print(json.dumps({"out": str(out), "function": str(model.step), "newton_iters": model.newton_iters,
                      "step_size": model.step_size, "instructions": int(model.step.n_instructions())}))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
