"""One Riccati stage, generated against hand-written: ``python -m benchmarks.riccati_stage``.

For each size ``(n_δ, m)`` the generated stage (:func:`fvin_mpc.control.riccati_qp.riccati_stage_function`, CasADi's
straight-line C, compiled as the package compiles generated code: ``-O2`` and the host's target flags) and the
kernel (:func:`fvin_mpc.control.riccati_kernel.riccati_stage_kernel`, ``-O3`` and the target flags, its own
object as in both loops' libraries) are linked into one C program that calls each on the same random stage
(``P``, ``H`` symmetric positive definite) in turns of ``--calls`` calls, ``--turns`` turns, and prints the
nanoseconds per call of every turn. Reported: the median per call of each, their ratio, and the largest
difference of the outputs (the kernel is tested against the generated stage in ``tests/test_riccati_kernel.py``).
The stage alone: what a period gains is in ``python -m benchmarks.c_loop``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import tempfile
from pathlib import Path
from typing import Sequence

import numpy as np

from fvin_mpc._cli import positive_int, run_command
from fvin_mpc.control.model_export import (
    COMPILER_FLAGS,
    KERNEL_FLAGS,
    compile_kernel,
    generated_code_flags,
    write_generated_source,
)
from fvin_mpc.control.riccati_kernel import riccati_stage_kernel
from fvin_mpc.control.riccati_qp import riccati_stage_function

SIZES = ((12, 4), (12, 1), (12, 6), (6, 3), (6, 1))

HARNESS = r"""
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "generated.h"
int KERNEL(const casadi_real **arg, casadi_real **res, casadi_int *iw, casadi_real *w, int mem);
#define S (ND + M)
static double uniform(void) { return rand() / (double)RAND_MAX - 0.5; }
static double now(void) { struct timespec t; clock_gettime(CLOCK_MONOTONIC, &t); return t.tv_sec + 1e-9 * t.tv_nsec; }
int main(int argc, char **argv) {
  int calls = atoi(argv[1]), turns = atoi(argv[2]), i, j, e, turn;
  (void)argc;
  static double P[ND * ND], p[ND], H[S * S], g[S], AB[ND * S], c[ND], d[M], r[M], X[S * S];
  static double out[2][ND * ND + ND + M * ND + M];
  static casadi_real w[100000]; static casadi_int iw[1000];
  srand((unsigned)atoi(argv[3]) + 1u);
  for (i = 0; i < S * S; ++i) X[i] = uniform();
  for (i = 0; i < S; ++i) for (j = 0; j < S; ++j) {
    double t = i == j; for (e = 0; e < S; ++e) t += X[e + S * i] * X[e + S * j]; H[i + S * j] = t; }
  for (i = 0; i < ND; ++i) for (j = 0; j < ND; ++j) {
    double t = 2.0 * (i == j); for (e = 0; e < S; ++e) t += X[e + S * i] * X[e + S * j]; P[i + ND * j] = t; }
  for (i = 0; i < ND * S; ++i) AB[i] = uniform() + (i % (ND + 1) == 0);
  for (i = 0; i < ND; ++i) { p[i] = uniform(); c[i] = uniform(); }
  for (i = 0; i < S; ++i) g[i] = uniform();
  for (i = 0; i < M; ++i) { d[i] = fabs(uniform()); r[i] = uniform(); }
  const casadi_real *arg[8] = {P, p, H, g, AB, c, d, r};
  casadi_real *res[2][4];
  for (i = 0; i < 2; ++i) {
    res[i][0] = out[i]; res[i][1] = out[i] + ND * ND; res[i][2] = res[i][1] + ND; res[i][3] = res[i][2] + M * ND; }
  rti_riccati_stage(arg, res[0], iw, w, 0);
  KERNEL(arg, res[1], iw, w, 0);
  double difference = 0.0;
  for (i = 0; i < ND * ND + ND + M * ND + M; ++i) difference = fmax(difference, fabs(out[0][i] - out[1][i]));
  printf("difference %.3e\n", difference);
  for (turn = 0; turn < turns; ++turn) {
    double start = now();
    for (i = 0; i < calls; ++i) { rti_riccati_stage(arg, res[0], iw, w, 0); P[0] += 1e-300 * out[0][1]; }
    double generated = (now() - start) / calls * 1e9;
    start = now();
    for (i = 0; i < calls; ++i) { KERNEL(arg, res[1], iw, w, 0); P[0] += 1e-300 * out[1][1]; }
    printf("turn %.1f %.1f\n", generated, (now() - start) / calls * 1e9);
  }
  return 0;
}
"""


def measure(nd: int, m: int, calls: int, turns: int, seed: int, compiler: str) -> dict:
    """One size: the medians per call (ns), their ratio and the outputs' largest difference."""
    kernel = riccati_stage_kernel(nd, m)
    target = generated_code_flags(compiler)
    with tempfile.TemporaryDirectory(prefix="fvin_mpc_riccati_") as work:
        directory = Path(work)
        write_generated_source([riccati_stage_function(nd, m)], "generated", directory)
        (directory / "harness.c").write_text(HARNESS)
        kernel_object = compile_kernel(kernel, compiler, (*KERNEL_FLAGS, *target), directory)
        generated_flags = [flag for flag in COMPILER_FLAGS if flag not in ("-shared",)]
        program = directory / "stage"
        subprocess.run([compiler, *generated_flags, *target, f"-DND={nd}", f"-DM={m}", f"-DKERNEL={kernel.name}",
                        "harness.c", "generated.c", str(kernel_object), "-o", str(program), "-lm"],
                       cwd=directory, check=True, capture_output=True, text=True)
        lines = subprocess.run([str(program), str(calls), str(turns), str(seed)], check=True, capture_output=True,
                               text=True).stdout.splitlines()
    difference = float(lines[0].split()[1])
    times = np.array([[float(x) for x in line.split()[1:]] for line in lines[1:]])
    generated_ns, kernel_ns = np.median(times, axis=0)
    return {"n_delta": nd, "m": m, "generated_ns": float(generated_ns), "kernel_ns": float(kernel_ns),
            "speed_up": float(np.median(times[:, 0] / times[:, 1])), "largest_difference": difference,
            "turns": turns, "calls_per_turn": calls}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.riccati_stage",
                                     description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--calls", type=positive_int, default=20000, help="calls per turn (default 20000)")
    parser.add_argument("--turns", type=positive_int, default=10, help="turns of each (default 10)")
    parser.add_argument("--out", type=Path, default=None, help="write the rows as JSON here")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random stage (default 0)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    compiler = os.environ.get("CC", "gcc")
    rows = [measure(nd, m, args.calls, args.turns, args.seed, compiler) for nd, m in SIZES]
    print("| (n_δ, m) | generated ns | kernel ns | speed-up | largest difference |")
    print("|---|---|---|---|---|")
    for row in rows:
        print(f"| ({row['n_delta']}, {row['m']}) | {row['generated_ns']:.0f} | {row['kernel_ns']:.0f} | "
              f"{row['speed_up']:.2f}× | {row['largest_difference']:.1e} |")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"command": "python -m benchmarks.riccati_stage", "seed": args.seed,
                                        "target_flags": list(generated_code_flags(compiler)), "rows": rows},
                                       indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
