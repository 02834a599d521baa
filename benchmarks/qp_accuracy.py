"""How far the real-time iteration's QP is from its solution after a given number of interior-point iterations:
``python -m benchmarks.qp_accuracy``.

The generated QP (``rti.qp_solver="riccati"``) runs a fixed count of primal–dual interior-point iterations
(``rti.qp_iterations``, ``--rti-qp-iterations`` on the closed-loop commands). Per scene this records the first QP of
every warm call in one closed-loop episode (waiting mode, learned model, the scene's settings), solves each again
with each count of ``--counts`` and ``--reference``, and once more exactly (an active-set solver, qpOASES through
``casadi.conic``, on the same QP written out whole), and reports the distance of the first control (the one sent)
to the exact solution's, as a fraction of the torque range: median, p99 and
largest over the episode's QPs and the share of QPs whose first control is more than 1 % of the range away, with the
barrier parameter reached and the bare compiled call's time (median). The episode runs with the wall-clock budgets
lifted, so every run records the same QPs. What
the counts do to the closed loop is a separate measurement (``python -m fvin_mpc.evaluate … --rti-qp-iterations K``).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import time
from pathlib import Path
from typing import Any, Sequence

import casadi as ca
import numpy as np

from benchmarks.c_loop import LeanLoop, controllers
from fvin_mpc._cli import run_command
from fvin_mpc.control.buffered import BufferedFunction
from fvin_mpc.control.closed_loop import run_episode
from fvin_mpc.control.model_export import compile_functions
from fvin_mpc.control.riccati_qp import QP_METHODS, riccati_feedback_function

SCENES = ("pendulum", "spherical_pendulum", "quadrotor")
DURATION_S = {"pendulum": 6.0, "spherical_pendulum": 6.0, "quadrotor": 3.0}


class _RecordingQPs(LeanLoop):
    """``controller`` as the closed loop calls it, writing down before each warm call the QP its first iteration
    solves: the prepared plan's linearization (``RealTimeMPC.linearize``) with the measured state."""

    def __init__(self, controller: Any, records: list[tuple[np.ndarray, ...]]) -> None:
        super().__init__(controller)
        self.records = records

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, dict[str, Any]]:
        plan = self.controller.plan
        u, info = self.controller(x)
        if plan is not None and "cold_start" not in info:
            h, h_n, g, g_n, ab, gaps, _ = self.controller.linearize(plan)
            x0 = self.controller.layout.check(x)
            self.records.append(tuple(np.array(a, dtype=float) for a in (plan.states.T, plan.controls.T, x0, h, h_n,
                                                                          g, g_n, ab, gaps)))
        return u, info


def record_qps(env: Any, controller: Any, duration: float, options: Any, seed: int | None = None
               ) -> list[tuple[np.ndarray, ...]]:
    """The arguments of the first QP of every warm call ``controller`` (a
    :class:`~fvin_mpc.control.rti.RealTimeMPC`) solves in one waiting-mode episode on ``env``, in the generated
    QP's input order (``rti_feedback``'s)."""
    records: list[tuple[np.ndarray, ...]] = []
    run_episode(env, _RecordingQPs(controller, records), duration, options, seed, latency="none")
    return records


def recorded_qps(scene: str, seed: int) -> tuple[Any, list[tuple[np.ndarray, ...]]]:
    """The scene's learned real-time MPC and the QPs it solved in one waiting-mode episode (:func:`record_qps`),
    its wall-clock budgets lifted: the same QPs on every run."""
    env, controller, options, seed = controllers(scene, False, seed,
                                                 rti_options={"budget_s": math.inf, "cold_budget_s": math.inf})
    try:
        return controller, record_qps(env, controller, DURATION_S[scene], options, seed)
    finally:
        env.close()


def exact_solver(controller: Any) -> Any:
    """qpOASES through ``casadi.conic`` for :func:`exact_controls`' QPs of ``controller`` (failure is an error)."""
    n, m, nd = controller.horizon, controller.model.control_dim, controller.layout.tangent_dim
    count = n * (nd + m)
    shapes = {"h": ca.Sparsity.dense(count, count), "a": ca.Sparsity.dense(n * nd, count)}
    return ca.conic("exact", "qpoases", shapes, {"error_on_fail": True, "printLevel": "none"})


def exact_controls(controller: Any, arguments: tuple[np.ndarray, ...], solver: Any) -> np.ndarray:
    """The new controls ``clip(Ū + Δu*)`` (m, N) of the QP ``arguments`` (the generated QP's inputs) solved by an
    active-set solver: the same stage-wise QP, written out as one QP in ``z = (Δu_0, δ_1, Δu_1, …, δ_N)``,
    ``δ_0`` fixed by the measured state."""
    states, controls, x0, h, h_n, g, g_n, ab, gaps = arguments
    n, m, nd = controller.horizon, controller.model.control_dim, controller.layout.tangent_dim
    size = nd + m
    delta0 = controller.layout.local(states[:, 0], x0)
    count = n * size
    hessian, gradient = np.zeros((count, count)), np.zeros(count)
    equality, offset = np.zeros((n * nd, count)), np.zeros(n * nd)

    def control(k: int) -> slice:  # Δu_k
        return slice(k * size, k * size + m)

    def state(k: int) -> slice:  # δ_k, k ≥ 1
        return slice((k - 1) * size + m, (k - 1) * size + m + nd)

    for k in range(n):
        block, a, b = h[:, k * size:(k + 1) * size], ab[:, k * size:k * size + nd], ab[:, k * size + nd:(k + 1) * size]
        hessian[control(k), control(k)] += block[nd:, nd:]
        gradient[control(k)] += g[nd:, k]
        if k == 0:
            gradient[control(0)] += block[nd:, :nd] @ delta0
            offset[:nd] = a @ delta0 + gaps[:, 0]
        else:
            hessian[state(k), state(k)] += block[:nd, :nd]
            hessian[control(k), state(k)] += block[nd:, :nd]
            hessian[state(k), control(k)] += block[:nd, nd:]
            gradient[state(k)] += g[:nd, k]
            equality[k * nd:(k + 1) * nd, state(k)] = -a
            offset[k * nd:(k + 1) * nd] = gaps[:, k]
        equality[k * nd:(k + 1) * nd, state(k + 1)] += np.eye(nd)
        equality[k * nd:(k + 1) * nd, control(k)] = -b
    hessian[state(n), state(n)] += h_n
    gradient[state(n)] += g_n
    low, high = (np.broadcast_to(np.asarray(bound, dtype=float), (n, m)).T for bound in controller._control_bounds)
    lower, upper = np.full(count, -np.inf), np.full(count, np.inf)
    for k in range(n):
        lower[control(k)], upper[control(k)] = low[:, k] - controls[:, k], high[:, k] - controls[:, k]
    solution = solver(h=ca.DM(hessian), g=gradient, a=ca.DM(equality), lba=offset, uba=offset, lbx=lower, ubx=upper)
    z = np.asarray(solution["x"], dtype=float).ravel()
    steps = np.stack([z[control(k)] for k in range(n)], axis=1)
    return np.clip(controls + steps, low, high)


def accuracy(controller: Any, records: list[tuple[np.ndarray, ...]], counts: Sequence[int], reference: int,
             method: str = "path") -> list[dict[str, Any]]:
    """One row per count (and the ``reference`` count): the distances of the first control to the exact
    solution's (:func:`exact_controls`), as a fraction of the torque range; ``method``: the interior-point
    method (:data:`~fvin_mpc.control.riccati_qp.QP_METHODS`)."""
    n, m = controller.horizon, controller.model.control_dim
    functions = [riccati_feedback_function(controller.layout, n, m, *controller._control_bounds,
                                           controller._step_limits, controller._omega_valid, count,
                                           method=method)[0]
                 for count in (*counts, reference)]
    # one library per count: every one is named rti_feedback
    prefix = re.sub(r"[^0-9A-Za-z_]", "_", f"qp_accuracy_{method}_{controller.model.name}")
    compiled = [compile_functions([function], prefix=f"{prefix}_{count}")[0]["rti_feedback"]
                for function, count in zip(functions, (*counts, reference))]
    solvers = [BufferedFunction(function) for function in compiled]
    span = float(np.max(controller._control_bounds[1] - controller._control_bounds[0]))
    solutions: list[list[np.ndarray]] = [[] for _ in solvers]
    barrier: list[list[float]] = [[] for _ in solvers]
    seconds: list[list[float]] = [[] for _ in solvers]
    for arguments in records:
        for index, solver in enumerate(solvers):
            _, controls, _, mu, _, _ = solver(*arguments)
            start = time.perf_counter()
            solver._evaluate()  # the bare compiled call on the filled buffers
            seconds[index].append(time.perf_counter() - start)
            solutions[index].append(np.asarray(controls, dtype=float))
            barrier[index].append(float(mu))
    active_set = exact_solver(controller)
    exact = [exact_controls(controller, arguments, active_set) for arguments in records]
    rows = []
    for index, count in enumerate((*counts, reference)):
        first = np.array([np.max(np.abs(u[:, 0] - v[:, 0])) for u, v in zip(solutions[index], exact)]) / span
        rows.append({"method": method, "qp_iterations": count, "qps": len(records),
                     "first_control_median": float(np.median(first)),
                     "first_control_p99": float(np.percentile(first, 99)), "first_control_max": float(first.max()),
                     "share_off_by_1_percent": float(np.mean(first > 0.01)),
                     "mu_median": float(np.median(barrier[index])),
                     "call_us_median": 1e6 * float(np.median(seconds[index]))})
    return rows


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.qp_accuracy", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", choices=SCENES, default=list(SCENES), help="default: all")
    parser.add_argument("--counts", nargs="+", type=int, default=[3, 6, 10, 16], help="default: %(default)s")
    parser.add_argument("--reference", type=int, default=40,
                        help="one more count, beyond the others (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="the episode's start (default: %(default)s)")
    parser.add_argument("--methods", nargs="+", choices=QP_METHODS, default=["path"],
                        help="interior-point methods to compare on the same QPs (default: %(default)s)")
    parser.add_argument("--out", type=Path, default=Path("docs/bench/qp_accuracy.json"), help="JSON results")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from tqdm.auto import tqdm

    args = build_parser().parse_args(argv)
    if min(args.counts) < 1 or args.reference <= max(args.counts):
        raise ValueError("--counts must be >= 1 and --reference larger than every count")
    rows = []
    for scene in tqdm(args.scenes, desc="scenes"):
        controller, records = recorded_qps(scene, args.seed)
        rows += [{"scene": scene, "model": controller.model.name, "horizon": controller.horizon,
                  "scene_qp_iterations": controller.settings.rti.qp_iterations, **row}
                 for method in args.methods for row in accuracy(controller, records, args.counts, args.reference,
                                                                 method)]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"command": "python -m benchmarks.qp_accuracy", "counts": args.counts,
                                    "reference": args.reference, "seed": args.seed, "rows": rows}, indent=1))
    lines = ["| scene | QPs | method | interior-point iterations | first control − exact, / torque range: median / "
             "p99 / max | QPs off by > 1 % | μ median | call µs median |", "|---|---|---|---|---|---|---|---|"]
    mark = {True: " (the scene's)", False: ""}
    lines += [f"| {r['scene']} (N = {r['horizon']}) | {r['qps']} | {r['method']} | {r['qp_iterations']}"
              f"{mark[r['qp_iterations'] == r['scene_qp_iterations'] and r['method'] == 'path']} "
              f"| {r['first_control_median']:.1e} / {r['first_control_p99']:.1e} / {r['first_control_max']:.1e} "
              f"| {100 * r['share_off_by_1_percent']:.1f} % | {r['mu_median']:.0e} | {r['call_us_median']:.0f} |"
              for r in rows]
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
