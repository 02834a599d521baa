"""A trained S3FVIN as a symbolic CasADi function, and compiled code cached on disk.

:func:`step_function` builds ``F(x, u) -> x_next`` (``x = [q (w,x,y,z), ω]``, 7 entries)
with ``K`` Newton iterations unrolled, by calling the same :func:`fvin_mpc.core.fvin.fvin_step`
and :class:`fvin_mpc.core.networks.LearnedTerms` code the torch model trains with — only the
leaf operations (:class:`fvin_mpc.core.backend.CasadiOps`) differ. Tests prove the two agree
to 1e-12 in value and 1e-8 in Jacobian.

:class:`ExportedModel` bundles the function with what a controller needs (step size,
control dimension, a NumPy evaluation of ``J``, ``U``, ``g`` for energies) and is made by
:func:`from_checkpoint` or :func:`from_rigid_body` (the closed-form ``--true-model``).

:func:`compile_functions` turns CasADi functions into one shared library with gcc and
loads it back with ``casadi.external``; the library is cached under :func:`cache_dir`,
named by the SHA-256 of the generated C source (which spells out the weights, ``K`` and
every option baked into the functions), so a second run with the same model and
settings does not compile again.

No torch here: the control runtime reads weights with safetensors/NumPy.
"""

from __future__ import annotations
from pathlib import Path
from typing import Sequence
from fvin_mpc.control.export import from_checkpoint, save_function


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m fvin_mpc.export``: write a checkpoint's step ``F(x, u)`` as a CasADi file."""
    import argparse
    import json

    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.export", description=main.__doc__,
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--checkpoint", default="pendulum_sign-invariant", help="shipped name or path")
    parser.add_argument("--newton-iters", type=int, default=None, help="K unrolled (default: the checkpoint's)")
    parser.add_argument("--out", type=Path, default=None, help="output file (default: <checkpoint>_K<K>.casadi)")
    parser.add_argument("--seed", type=int, default=0, help="unused (the export is deterministic); for CLI uniformity")
    args = parser.parse_args(argv)
    model = from_checkpoint(args.checkpoint, args.newton_iters)
    out = args.out or Path(f"{model.name}_K{model.newton_iters}.casadi")
    save_function(model.step, out)
    print(json.dumps({"out": str(out), "function": str(model.step), "newton_iters": model.newton_iters,
                      "step_size": model.step_size, "instructions": int(model.step.n_instructions())}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
