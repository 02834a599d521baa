"""Every checkpoint's exported step, CasADi Jacobian and energy on fixed random inputs, to compare two
commits bit for bit: ``python -m benchmarks.export_digest checkpoints OUT.npz`` on each commit (e.g. the
older one's worktree on ``PYTHONPATH``), then ``python -m benchmarks.export_digest --compare A.npz B.npz``.

A checkpoint whose export fails is reported and skipped (before the configuration-space value, the
SO(3) checkpoints did not export).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import casadi as ca
import numpy as np

from fvin_mpc.control import model_export as export

SAMPLES = 20


def digest(directory: Path) -> dict[str, np.ndarray]:
    """``name → (SAMPLES, …)``: per sample the next state, the residual, the Jacobian in ``(x, u)`` and the energy."""
    out = {}
    for sidecar in sorted(directory.glob("*.json")):
        name = sidecar.stem
        try:
            model = export.from_checkpoint(directory / name)
        except Exception as error:  # noqa: BLE001 — reported, not hidden: the comparison names it
            print(f"{name}: export failed ({str(error).splitlines()[0][:100]})")
            continue
        n, m = int(model.step.size1_in(0)), model.control_dim
        rng = np.random.default_rng(0)
        x, u = rng.normal(size=(SAMPLES, n)), rng.normal(size=(SAMPLES, m))
        quaternion = slice(0, 4) if n == 7 else slice(3, 7)  # written so an older commit's layouts read it too
        x[:, quaternion] /= np.linalg.norm(x[:, quaternion], axis=1, keepdims=True)
        xs, us = ca.SX.sym("x", n), ca.SX.sym("u", m)
        jacobian = ca.Function("j", [xs, us], [ca.jacobian(model.step(xs, us)[0], ca.vertcat(xs, us))])
        rows = []
        for i in range(SAMPLES):
            x_next, residual = model.step(x[i], u[i])
            energy = float(model.energy_function(x[i]))
            rows.append(np.concatenate([np.asarray(x_next).ravel(), [float(residual)],
                                        np.asarray(jacobian(x[i], u[i])).ravel(), [energy]]))
        out[name] = np.array(rows)
    return out


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.export_digest", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", nargs=2, type=Path, help="CHECKPOINT_DIR OUT.npz, or with --compare A.npz B.npz")
    parser.add_argument("--compare", action="store_true", help="compare two digests")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.compare:
        a, b = (np.load(path) for path in args.paths)
        for name in sorted(set(a.files) | set(b.files)):
            if name in a.files and name in b.files:
                same = np.array_equal(a[name], b[name])
                print(name, "bit-identical" if same else f"differs, max {np.max(np.abs(a[name] - b[name])):.3g}")
            else:
                print(name, "only in", args.paths[0] if name in a.files else args.paths[1])
        return 0
    np.savez(args.paths[1], **digest(args.paths[0]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
