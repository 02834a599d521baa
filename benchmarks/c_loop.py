"""The real-time loop in C against the same loop in Python: ``python -m benchmarks.c_loop``.

Per scene, the Python :class:`~fvin_mpc.control.rti.RealTimeMPC` and its generated C library
(:class:`~fvin_mpc.control.c_controller.CRealTimeMPC`; same problem, horizon and model) run closed-loop
episodes in MuJoCo with **measured latency** (the controller's wall-clock feedback time delays its
control; ``run_episode(latency="measured")``), first on the machine as it is, then under a bounded
background busy loop (one spinning process per core; started and stopped by this command, no pinning or
priority changes). Reported per loop: the feedback call (state in → control out) and the whole period
(feedback + preparation), median and p99, and its CPU time (the thread's: on a shared machine, less
moved by the other processes than the wall clock), deadline misses (and whether the cold first period was
one of them: a robot runs the cold start before its clock starts), and whether the episode reached its
goal.
The C loop is called as one ``ctypes`` call per phase (no ``info`` dict); the Python loop as the
studies call it. The Python loop runs with the scene's own wall-clock budgets; the C loop is bounded
by iteration counts, so a cold first call may take longer in C than Python's cold budget allows.

Paired periods (``paired`` in the JSON; the speed-up figures of the report). On this shared machine a
core's speed moves by up to 2× from one second to the next, and episodes run one after the other see
different machines. So the observations of one waiting-mode episode are replayed to both loops, period
by period, in alternating order (the Python loop's wall-clock budgets lifted: both run the iterations
their counts allow, are equal to 1e-9 and stay on the same plan), and each warm period also times the
generated functions alone on the Python loop's prepared plan — the linearization and the QP once per
iteration the period ran, the two one-step predictions, the bare compiled calls on filled buffers: what
both loops run. Cold calls (the first, and restarts) are left out. Reported:
medians of each and the median of the per-period ratios Python / C and Python / generated. The C loop
saves only what is around the generated code, so the second ratio bounds the speed-up any driver of this
generated code can reach. The replay runs twice: in turns of one period, and in turns of
:data:`PAIRED_BLOCK` periods per loop (the order swapped each turn). Period by period, each of a loop's
periods follows the other loop's whole period, which evicts from the caches what the loop's next period
would find there on a robot (there only the plant's I/O runs between two periods); in blocks, most periods
follow the loop's own previous one (what that changes: docs/c-controller.md).
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
import time
from pathlib import Path
from typing import Any, Sequence

import casadi as ca
import numpy as np

from fvin_mpc._cli import positive_int, run_command
from fvin_mpc.control.c_controller import CRealTimeMPC
from fvin_mpc.control.closed_loop import episode_metrics, run_episode
from fvin_mpc.control.flight import quadrotor_model, quadrotor_mpc, quadrotor_mpc_settings, recovery_starts
from fvin_mpc.control.lane_kernel import STAGE_LANES
from fvin_mpc.control.model_export import COMPILER_FLAGS, generated_code_flags
from fvin_mpc.control.riccati_kernel import RICCATI_STAGES
from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings
from fvin_mpc.envs import QuadrotorEnv
from fvin_mpc.envs.scenes import resolve_scene

SCENES = ("pendulum", "spherical_pendulum", "quadrotor")
#: Periods per turn of the paired timing's second replay: each loop runs that many consecutive periods before the
#: other runs them, so most of a loop's periods follow its own previous period, as on a robot, where the first
#: replay (turns of one period) puts the other loop's whole period, and its use of the caches, before each one.
PAIRED_BLOCK = 10
#: Seconds per episode: a swing-up and its catch, a ball-joint swing-up, a quadrotor recovery.
DURATION_S = {"pendulum": 8.0, "spherical_pendulum": 8.0, "quadrotor": 4.0}


class LeanC:
    """The C loop as the closed loop calls it: one ctypes call for the control, one for the preparation."""

    def __init__(self, controller: CRealTimeMPC) -> None:
        self.controller = controller

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, dict[str, Any]]:
        return self.controller.feedback(x), {}

    def prepare(self) -> None:
        self.controller.prepare()

    def reset(self) -> None:
        self.controller.reset()

    def set_time(self, t: float) -> None:
        self.controller.set_time(t)


def spin(until: float) -> None:
    """A bounded busy loop: burn one core until the wall clock passes ``until``."""
    while time.time() < until:
        pass


class BackgroundLoad:
    """``workers`` busy-loop processes for at most ``limit_s`` seconds; stopped on exit."""

    def __init__(self, workers: int, limit_s: float) -> None:
        self.workers, self.limit_s = workers, limit_s

    def __enter__(self) -> "BackgroundLoad":
        until = time.time() + self.limit_s
        self.processes = [multiprocessing.Process(target=spin, args=(until,), daemon=True) for _ in range(self.workers)]
        for process in self.processes:
            process.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        for process in self.processes:
            process.terminate()
            process.join()


def controllers(scene: str, true_model: bool, seed: int, feedback: str = "qp",
                rti_options: dict[str, Any] | None = None) -> tuple[Any, Any, Any, dict[str, Any], int]:
    """``(env, python loop, C loop, reset options, env seed)`` of ``scene``: a random start, or the
    quadrotor's first random recovery start. ``feedback``: ``RTIOptions.feedback`` of both loops
    (``"prepared"`` with one iteration per period); ``rti_options``: more ``RTIOptions`` fields of both loops
    (``cold_iter``, ``relinearize_every``, ``qp_iterations``, ``qp_method``, ``riccati_stage``, ``stage_lanes``;
    the scene's where not given)."""
    rti: dict[str, Any] = {} if feedback == "qp" else {"feedback": feedback, "max_iter": 1}
    rti.update(rti_options or {})
    if resolve_scene(scene).goal_set.attitude_at_rest:
        env = scene_env(scene, true_model=true_model)
        python = scene_mpc(env, scene_model(env, true_model=true_model),
                           scene_mpc_settings(env, solver="rti").updated(rti=rti))
        options = {"random": True}
    else:
        env = QuadrotorEnv(resolve_scene(scene))
        python = quadrotor_mpc(env, quadrotor_model(env, true_model=true_model),
                               quadrotor_mpc_settings().updated(rti=rti))
        options, seed = recovery_starts(env.unwrapped.goal_state[:3], count=3, seed=seed)[2]
    return env, python, LeanC(CRealTimeMPC(python)), options, seed


def generated_period(python: Any, iterations: int) -> float:
    """Seconds the compiled functions of one warm period take by themselves on ``python``'s prepared plan:
    ``rti_linearize_blocks`` and ``rti_feedback`` (the QP's interior-point iterations) once per Gauss–Newton
    iteration the period ran (the first linearization is the preparation's), ``rti_predict`` twice (the
    shifted plan's last node and the disturbance estimate's prediction) — the ``"qp"`` feedback. Each is
    called once to fill its buffers, then timed as the bare compiled call (no Python conversions). With kept
    Jacobians (``rti.relinearize_every``) the linearizations renew what a warm period's would on this plan: the
    first those the rule names and those that moved since the kept ones were computed, the further ones only
    those that moved (from the same kept points here: the plan stands still) — an estimate, where the loops'
    own periods are measured."""
    plan, linearization = python._plan, python._linearization
    python._linearize_at(plan, python._plan_jacobians)  # a warm linearization: the items it renews
    python._feedback(plan.states.T, plan.controls.T, plan.states[0], *linearization[:6])
    python._predict(plan.states[-1], plan.controls[-1])
    renew = python._linearize._inputs[python._linearize.function.index_in("fresh")]
    _, _, _, first, further = python.kept_jacobians

    elapsed = 0.0
    for iteration in range(iterations):
        renew[...] = (first if iteration == 0 else further).reshape(renew.shape)
        start = time.perf_counter()
        python._linearize._evaluate()
        python._feedback._evaluate()
        elapsed += time.perf_counter() - start
    start = time.perf_counter()
    for _ in range(2):
        python._predict_with_parameters._evaluate()
    return elapsed + time.perf_counter() - start


def generated_instructions(python: Any) -> dict[str, int]:
    """CasADi instructions of the functions a warm period calls (each expanded to scalar operations): a
    count, deterministic where the machine's timings are not. The linearization's with every item renewed: the
    most a period runs (with ``rti.relinearize_every`` its kept items run their values alone; the timings say
    what that saves). A lane kernel's instructions (:mod:`fvin_mpc.control.lane_kernel`) are its scalar code's,
    every stage counted: it runs them four stages at a time. The Riccati kernel's are not counted (hand-written)."""
    names = {"rti_linearize_blocks": "linearize", "rti_feedback": "qp", "rti_predict": "predict"}
    counts = {}
    for function in python.loop_functions:
        if function.name() not in names:
            continue
        name = names[function.name()]
        if name == "linearize":  # every item renewed
            inputs = function.mx_in()
            inputs[function.index_in("fresh")] = ca.DM.ones(1, python.kept_jacobians[0])
            kept = [x for i, x in enumerate(function.mx_in()) if function.name_in(i) != "fresh"]
            function = ca.Function("warm", kept, function.call(inputs))
        counts[name] = int((function.expand() if function.is_a("MXFunction") else function).n_instructions())
    counts["linearize"] += sum(kernel.scalar_instructions or 0 for kernel in python.loop_kernels)
    return counts


def paired(env: Any, python: Any, c_loop: Any, duration: float, options: dict[str, Any], seed: int,
           block: int = 1) -> dict[str, Any]:
    """The observations of one waiting-mode episode replayed to both loops (module docstring), the Python
    loop's wall-clock budgets lifted so that both run the same iterations, in turns of ``block`` periods:
    each loop runs a block of consecutive observations, then the other the same block, the order swapped
    from one block to the next (``block=1``: period by period). Returns medians of the warm periods (feedback
    + preparation) of each loop and of the generated code alone, µs, the medians of the per-period ratios,
    and the largest difference of the two loops' controls. Cold calls (the first, and restarts) are left
    out."""
    if python.settings.rti.feedback != "qp":
        raise ValueError("the paired periods time the 'qp' feedback")
    if block < 1:
        raise ValueError(f"block must be >= 1, got {block}")
    episode, _ = run_episode(env, python, duration, options, seed, latency="none")
    observations = [(float(t), python.layout.check(x))  # what the Python loop normalizes; LeanC passes x as is
                    for t, x in zip(episode.time[:-1], episode.states[:-1])]
    count = len(observations)
    periods = {name: np.full(count, np.nan) for name in ("python", "c", "generated")}
    controls = {name: np.full((count, python.model.control_dim), np.nan) for name in ("python", "c")}
    cold = np.zeros(count, dtype=bool)
    scene_settings = python.settings
    python.settings = scene_settings.updated(rti={"budget_s": math.inf, "cold_budget_s": math.inf})
    try:
        loops = {"python": python, "c": c_loop}
        for loop in loops.values():
            loop.reset()
        for first in range(0, count, block):
            turn = range(first, min(first + block, count))
            for name in ("python", "c") if (first // block) % 2 == 0 else ("c", "python"):
                loop = loops[name]
                for index in turn:
                    t, x = observations[index]
                    loop.set_time(t)
                    start = time.perf_counter()
                    controls[name][index], info = loop(x)
                    loop.prepare()
                    periods[name][index] = time.perf_counter() - start
                    if name == "python":
                        cold[index] = "cold_start" in info or python._linearization is None
                        if not cold[index]:
                            periods["generated"][index] = generated_period(python, info["iterations"])
    finally:
        python.settings = scene_settings
    warm = {name: 1e6 * np.where(cold, np.nan, values) for name, values in periods.items()}
    return {"periods": int((~cold).sum()), "block": block,
            "control_difference_max": float(np.max(np.abs(controls["python"] - controls["c"]))),
            **{f"{name}_us_median": float(np.nanmedian(values)) for name, values in warm.items()},
            "speed-up": float(np.nanmedian(warm["python"] / warm["c"])),
            "speed-up bound": float(np.nanmedian(warm["python"] / warm["generated"]))}


def summary(episode: Any) -> dict[str, Any]:
    feedback, busy = 1e6 * episode.feedback_s, 1e6 * episode.busy_s
    cpu = 1e6 * episode.cpu_s
    feedback, busy, cpu = feedback[np.isfinite(feedback)], busy[np.isfinite(busy)], cpu[np.isfinite(cpu)]
    metrics = episode_metrics(episode)
    # a robot would run the cold start before its clock starts; a miss there is told apart from the loop's
    cold_miss = bool(busy.size and busy[0] > 1e6 * episode.control_period)
    return {"feedback_us_median": float(np.median(feedback)), "feedback_us_p99": float(np.percentile(feedback, 99)),
            "period_us_median": float(np.median(busy)), "period_us_p99": float(np.percentile(busy, 99)),
            "period_cpu_us_median": float(np.median(cpu)),
            "first_period_us": float(busy[0]), "deadline_misses": int(episode.deadline_misses),
            "cold_miss": cold_miss, "skipped": int(episode.skipped), "success": bool(metrics["success"]),
            "periods": int(busy.size),
            "control_period_us": 1e6 * episode.control_period}


def run(scenes: Sequence[str], true_model: bool, load_workers: int, seed: int,
        feedback: str = "qp", rti_options: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    from tqdm.auto import tqdm

    rows = []
    for scene in tqdm(scenes, desc="scenes"):
        env, python, c_loop, options, seed = controllers(scene, true_model, seed, feedback, rti_options)
        duration = DURATION_S.get(scene, 8.0)
        row: dict[str, Any] = {"scene": scene, "model": python.model.name, "horizon": python.horizon}
        for condition in ("as is", "loaded"):
            for name, loop in (("python", python), ("c", c_loop)):
                if condition == "loaded":
                    with BackgroundLoad(load_workers, limit_s=120.0):
                        episode, _ = run_episode(env, loop, duration, options, seed, latency="measured")
                else:
                    episode, _ = run_episode(env, loop, duration, options, seed, latency="measured")
                row[f"{name} {condition}"] = summary(episode)
        for condition in ("as is", "loaded"):
            python_row, c_row = row[f"python {condition}"], row[f"c {condition}"]
            row[f"period speed-up {condition}"] = python_row["period_us_median"] / c_row["period_us_median"]
            row[f"feedback speed-up {condition}"] = python_row["feedback_us_median"] / c_row["feedback_us_median"]
            row[f"period CPU speed-up {condition}"] = (python_row["period_cpu_us_median"]
                                                       / c_row["period_cpu_us_median"])
        qp = python.settings.rti.feedback == "qp"
        row["paired"] = paired(env, python, c_loop, duration, options, seed) if qp else None
        row["paired in blocks"] = paired(env, python, c_loop, duration, options, seed, PAIRED_BLOCK) if qp else None
        row["instructions"] = generated_instructions(python)
        rows.append(row)
    return rows


def markdown(rows: list[dict[str, Any]]) -> str:
    lines = ["| scene | model | N | loop | load | feedback µs median / p99 | period µs median / p99 | first period µs "
             "| period CPU µs median | deadline misses (the cold first period's) | reached goal "
             "| period speed-up (wall / CPU) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        for condition in ("as is", "loaded"):
            for name in ("python", "c"):
                r = row[f"{name} {condition}"]
                speed = (f"{row[f'period speed-up {condition}']:.2f}× / {row[f'period CPU speed-up {condition}']:.2f}×"
                         if name == "c" else "")
                lines.append(f"| {row['scene']} | {row['model']} | {row['horizon']} | {name} | {condition} "
                             f"| {r['feedback_us_median']:.0f} / {r['feedback_us_p99']:.0f} "
                             f"| {r['period_us_median']:.0f} / {r['period_us_p99']:.0f} | {r['first_period_us']:.0f} "
                             f"| {r['period_cpu_us_median']:.0f} "
                             f"| {r['deadline_misses']} of {r['periods']} ({int(r['cold_miss'])}) | {r['success']} "
                             f"| {speed} |")
    lines += ["", "Paired periods (the same observations to both loops in turns of one period, or of "
              f"{PAIRED_BLOCK} in blocks; waiting mode):", "",
              "| scene | turns | periods | Python µs | C µs | generated code alone µs | speed-up Python / C "
              "| bound: Python / generated | largest control difference |", "|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        for key in ("paired", "paired in blocks"):
            p = row.get(key)
            if p is None:
                lines.append(f"| {row['scene']} | — (the prepared feedback) | | | | | | | |")
                continue
            lines.append(f"| {row['scene']} | {p['block']} | {p['periods']} | {p['python_us_median']:.0f} "
                         f"| {p['c_us_median']:.0f} | {p['generated_us_median']:.0f} | {p['speed-up']:.2f}× "
                         f"| {p['speed-up bound']:.2f}× | {p['control_difference_max']:.1e} |")
    lines += ["", "| scene | CasADi instructions: linearize / QP / predict |", "|---|---|"]
    lines += [f"| {row['scene']} | {row['instructions']['linearize']:,} / {row['instructions']['qp']:,} / "
              f"{row['instructions']['predict']:,} |" for row in rows]
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.c_loop", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", choices=SCENES, default=list(SCENES), help="scenes to time")
    parser.add_argument("--true-model", action="store_true", help="plan with the closed form instead of the checkpoint")
    parser.add_argument("--load-workers", type=int, default=os.cpu_count() or 2,
                        help="busy-loop processes of the loaded runs (default: one per core)")
    parser.add_argument("--out", type=Path, default=Path("docs/bench/c_loop.json"), help="JSON results")
    parser.add_argument("--seed", type=int, default=0, help="the episodes' random starts")
    parser.add_argument("--feedback", choices=["qp", "prepared"], default="qp",
                        help="RTIOptions.feedback of both loops: qp (the QP at the measured state, the default) or "
                             "prepared (the preparation's Riccati gains applied to it; one iteration per period)")
    parser.add_argument("--cold-iter", type=positive_int, default=None,
                        help="RTIOptions.cold_iter of both loops: the iterations per first guess of the cold call, "
                             "a count (default: the scene's; the quadrotor's is 2, which the C loop runs in full)")
    parser.add_argument("--relinearize-every", type=positive_int, default=None,
                        help="RTIOptions.relinearize_every of both loops: renew the dynamics' Jacobians of every K-th "
                             "stage (and the first and last), keep the others' from the last linearization "
                             "(default: the scene's, 1)")
    parser.add_argument("--qp-iterations", type=positive_int, default=None,
                        help="RTIOptions.qp_iterations of both loops (default: the scene's)")
    parser.add_argument("--qp-method", choices=["path", "mehrotra"], default=None,
                        help="RTIOptions.qp_method of both loops: the Riccati QP's interior-point method (default: "
                             "the scene's, path)")
    parser.add_argument("--riccati-stage", choices=RICCATI_STAGES, default=None,
                        help="RTIOptions.riccati_stage of both loops: the QP's Riccati stage as generated code or as "
                             "the hand-written kernel (default: auto, the kernel for a free body)")
    parser.add_argument("--stage-lanes", choices=STAGE_LANES, default=None,
                        help="RTIOptions.stage_lanes of both loops: the linearization four stages at a time on the "
                             "vector units, or a stage at a time (default: auto, lanes wherever they can run)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    given = {"cold_iter": args.cold_iter, "relinearize_every": args.relinearize_every,
             "qp_iterations": args.qp_iterations, "qp_method": args.qp_method, "riccati_stage": args.riccati_stage,
             "stage_lanes": args.stage_lanes}
    rti_options = {name: value for name, value in given.items() if value is not None}
    rows = run(args.scenes, args.true_model, args.load_workers, args.seed, args.feedback, rti_options)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"command": "python -m benchmarks.c_loop", "feedback": args.feedback,
                                    **given,
                                    "load_average": os.getloadavg(), "cpus": os.cpu_count(),
                                    "load_workers": args.load_workers,
                                    "compiler_flags": [*COMPILER_FLAGS,
                                                       *generated_code_flags(os.environ.get("CC", "gcc"))],
                                    "rows": rows}, indent=1))
    print(markdown(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
