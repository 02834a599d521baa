"""The real-time loop's timing: ``python -m benchmarks.c_loop``.

Per scene, the real-time MPC (:class:`~fvin_mpc.control.rti.RealTimeMPC`, whose loop is its generated C library)
runs closed-loop episodes in MuJoCo with **measured latency** (the controller's wall-clock feedback time delays
its control; ``run_episode(latency="measured")``), first on the machine as it is, then under a bounded
background busy loop (one spinning process per core; started and stopped by this command, no pinning or
priority changes), driven two ways: as the studies call it (``controller(x)`` with its ``info``) and lean (one
``ctypes`` call per phase, no ``info``: :class:`LeanLoop`). Reported per run: the feedback call (state in →
control out) and the whole period (feedback + preparation), median and p99, and its CPU time (the thread's: on
a shared machine, less moved by the other processes than the wall clock), deadline misses (and whether the cold
first period was one of them: a robot runs the cold start before its clock starts), and whether the episode
reached its goal.

Beside them, the generated code alone: each warm period of a waiting-mode episode also times the library's
compiled functions on the prepared plan — the linearization and the QP once per iteration the period ran, the
two one-step predictions, bare calls on filled buffers — so the driver's share of a period is the difference;
and the CasADi instructions of each part (linearize, QP, predict), a count that the machine's load does not move.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import time
from pathlib import Path
from typing import Any, Sequence

import casadi as ca
import numpy as np

from fvin_mpc._cli import positive_int, run_command
from fvin_mpc.control.closed_loop import episode_metrics, run_episode
from fvin_mpc.control.flight import quadrotor_model, quadrotor_mpc, quadrotor_mpc_settings, recovery_starts
from fvin_mpc.control.lane_kernel import STAGE_LANES
from fvin_mpc.control.model_export import COMPILER_FLAGS, generated_code_flags
from fvin_mpc.control.riccati_kernel import RICCATI_STAGES
from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings
from fvin_mpc.envs import QuadrotorEnv
from fvin_mpc.envs.scenes import resolve_scene

SCENES = ("pendulum", "spherical_pendulum", "quadrotor")
#: Seconds per episode: a swing-up and its catch, a ball-joint swing-up, a quadrotor recovery.
DURATION_S = {"pendulum": 8.0, "spherical_pendulum": 8.0, "quadrotor": 4.0}


class LeanLoop:
    """The library as a robot's loop calls it: one ctypes call for the control, one for the preparation."""

    def __init__(self, controller: Any) -> None:
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
                rti_options: dict[str, Any] | None = None) -> tuple[Any, Any, dict[str, Any], int]:
    """``(env, controller, reset options, env seed)`` of ``scene``: a random start, or the quadrotor's first
    random recovery start. ``feedback``: ``RTIOptions.feedback`` (``"prepared"`` with one iteration per period);
    ``rti_options``: more ``RTIOptions`` fields (``cold_iter``, ``relinearize_every``, ``qp_iterations``,
    ``qp_method``, ``riccati_stage``, ``stage_lanes``, budgets; the scene's where not given)."""
    rti: dict[str, Any] = {} if feedback == "qp" else {"feedback": feedback, "max_iter": 1}
    rti.update(rti_options or {})
    if resolve_scene(scene).goal_set.attitude_at_rest:
        env = scene_env(scene, true_model=true_model)
        controller = scene_mpc(env, scene_model(env, true_model=true_model),
                               scene_mpc_settings(env, solver="rti").updated(rti=rti))
        options = {"random": True}
    else:
        env = QuadrotorEnv(resolve_scene(scene))
        controller = quadrotor_mpc(env, quadrotor_model(env, true_model=true_model),
                                   quadrotor_mpc_settings().updated(rti=rti))
        options, seed = recovery_starts(env.unwrapped.goal_state[:3], count=3, seed=seed)[2]
    return env, controller, options, seed


def generated_period(controller: Any, iterations: int) -> float:
    """Seconds the library's compiled functions of one warm period take by themselves on ``controller``'s
    prepared plan: ``rti_linearize_blocks`` and ``rti_feedback`` (the QP's interior-point iterations) once per
    Gauss–Newton iteration the period ran, ``rti_predict`` twice (the shifted plan's last node and the
    disturbance estimate's prediction) — the ``"qp"`` feedback. Each is called once to fill its buffers, then
    timed as the bare compiled call. Every item of the linearization is renewed (with kept Jacobians,
    ``rti.relinearize_every``, an upper bound)."""
    plan = controller.plan
    linearization = controller.linearize(plan)
    linearize, qp = controller.loop_function("rti_linearize_blocks"), controller.loop_function("rti_feedback")
    predict = controller.loop_function("rti_predict")
    qp(plan.states.T, plan.controls.T, plan.states[0], *linearization[:6])
    predict(plan.states[-1], plan.controls[-1], controller.parameters)
    start = time.perf_counter()
    for _ in range(iterations):
        linearize._evaluate()
        qp._evaluate()
    for _ in range(2):
        predict._evaluate()
    return time.perf_counter() - start


def generated_instructions(controller: Any) -> dict[str, int]:
    """CasADi instructions of the functions a warm period calls (each expanded to scalar operations): a
    count, deterministic where the machine's timings are not. The linearization's with every item renewed: the
    most a period runs (with ``rti.relinearize_every`` its kept items run their values alone; the timings say
    what that saves). A lane kernel's instructions (:mod:`fvin_mpc.control.lane_kernel`) are its scalar code's,
    every stage counted: it runs them four stages at a time. The Riccati kernel's are not counted (hand-written)."""
    names = {"rti_linearize_blocks": "linearize", "rti_feedback": "qp", "rti_predict": "predict"}
    counts = {}
    for function in controller.loop_functions:
        if function.name() not in names:
            continue
        name = names[function.name()]
        if name == "linearize":  # every item renewed
            inputs = function.mx_in()
            inputs[function.index_in("fresh")] = ca.DM.ones(1, controller.kept_jacobians[0])
            kept = [x for i, x in enumerate(function.mx_in()) if function.name_in(i) != "fresh"]
            function = ca.Function("warm", kept, function.call(inputs))
        counts[name] = int((function.expand() if function.is_a("MXFunction") else function).n_instructions())
    counts["linearize"] += sum(kernel.scalar_instructions or 0 for kernel in controller.loop_kernels)
    return counts


def generated_share(env: Any, controller: Any, duration: float, options: dict[str, Any], seed: int) -> dict[str, Any]:
    """One waiting-mode episode, each warm period timed whole and its generated code alone
    (:func:`generated_period`): medians (µs) and the median share of the period the generated code takes."""
    if controller.settings.rti.feedback != "qp":
        raise ValueError("the generated code's share is timed for the 'qp' feedback")
    episode, _ = run_episode(env, controller, duration, options, seed, latency="none")
    periods, generated = [], []
    controller.reset()
    for t, x in zip(episode.time[:-1], episode.states[:-1]):
        controller.set_time(float(t))
        start = time.perf_counter()
        _, info = controller(x)
        controller.prepare()
        period = time.perf_counter() - start
        if "cold_start" not in info:
            periods.append(period)
            generated.append(generated_period(controller, info["iterations"]))
    periods_us, generated_us = 1e6 * np.array(periods), 1e6 * np.array(generated)
    return {"periods": len(periods), "period_us_median": float(np.median(periods_us)),
            "generated_us_median": float(np.median(generated_us)),
            "generated_share": float(np.median(generated_us / periods_us))}


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
        env, controller, options, seed = controllers(scene, true_model, seed, feedback, rti_options)
        duration = DURATION_S.get(scene, 8.0)
        row: dict[str, Any] = {"scene": scene, "model": controller.model.name, "horizon": controller.horizon}
        for condition in ("as is", "loaded"):
            for name, loop in (("studies", controller), ("lean", LeanLoop(controller))):
                if condition == "loaded":
                    with BackgroundLoad(load_workers, limit_s=120.0):
                        episode, _ = run_episode(env, loop, duration, options, seed, latency="measured")
                else:
                    episode, _ = run_episode(env, loop, duration, options, seed, latency="measured")
                row[f"{name} {condition}"] = summary(episode)
        qp = controller.settings.rti.feedback == "qp"
        row["generated"] = generated_share(env, controller, duration, options, seed) if qp else None
        row["instructions"] = generated_instructions(controller)
        rows.append(row)
    return rows


def markdown(rows: list[dict[str, Any]]) -> str:
    lines = ["| scene | model | N | driven | load | feedback µs median / p99 | period µs median / p99 "
             "| first period µs | period CPU µs median | deadline misses (the cold first period's) | reached goal |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        for condition in ("as is", "loaded"):
            for name in ("studies", "lean"):
                r = row[f"{name} {condition}"]
                lines.append(f"| {row['scene']} | {row['model']} | {row['horizon']} | {name} | {condition} "
                             f"| {r['feedback_us_median']:.0f} / {r['feedback_us_p99']:.0f} "
                             f"| {r['period_us_median']:.0f} / {r['period_us_p99']:.0f} | {r['first_period_us']:.0f} "
                             f"| {r['period_cpu_us_median']:.0f} "
                             f"| {r['deadline_misses']} of {r['periods']} ({int(r['cold_miss'])}) | {r['success']} |")
    lines += ["", "The generated code alone (waiting mode, warm periods):", "",
              "| scene | periods | period µs | generated code µs | its share | CasADi instructions: linearize / QP / "
              "predict |", "|---|---|---|---|---|---|"]
    for row in rows:
        g, counts = row["generated"], row["instructions"]
        timing = ("— (the prepared feedback) | | |" if g is None else
                  f"{g['periods']} | {g['period_us_median']:.0f} | {g['generated_us_median']:.0f} "
                  f"| {g['generated_share']:.0%} |")
        lines.append(f"| {row['scene']} | {timing} {counts['linearize']:,} / {counts['qp']:,} / "
                     f"{counts['predict']:,} |")
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
                        help="RTIOptions.feedback: qp (the QP at the measured state, the default) or "
                             "prepared (the preparation's Riccati gains applied to it; one iteration per period)")
    parser.add_argument("--cold-iter", type=positive_int, default=None,
                        help="RTIOptions.cold_iter: the iterations per first guess of the cold call, "
                             "a count (default: the scene's; the quadrotor's is 2)")
    parser.add_argument("--relinearize-every", type=positive_int, default=None,
                        help="RTIOptions.relinearize_every: renew the dynamics' Jacobians of every K-th "
                             "stage (and the first and last), keep the others' from the last linearization "
                             "(default: the scene's, 1)")
    parser.add_argument("--qp-iterations", type=positive_int, default=None,
                        help="RTIOptions.qp_iterations (default: the scene's)")
    parser.add_argument("--qp-method", choices=["path", "mehrotra"], default=None,
                        help="RTIOptions.qp_method: the Riccati QP's interior-point method (default: "
                             "the scene's, path)")
    parser.add_argument("--riccati-stage", choices=RICCATI_STAGES, default=None,
                        help="RTIOptions.riccati_stage: the QP's Riccati stage as generated code or as "
                             "the hand-written kernel (default: auto, the kernel for a free body)")
    parser.add_argument("--stage-lanes", choices=STAGE_LANES, default=None,
                        help="RTIOptions.stage_lanes: the linearization four stages at a time on the "
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
