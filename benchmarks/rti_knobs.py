"""``rti``: what the real-time iteration's knobs cost in time and buy in control, learned beside closed form.

On the planar pendulum, from the scene's RTI settings, one knob changed at a time: the QP's
interior-point iterations (``rti.qp_iterations``), the horizon ``N``, and further Gauss–Newton
iterations within a per-call budget (``rti.max_iter``, ``rti.budget_s``). Every configuration runs
the same seeded starts (episode 0 hanging at rest, then the evaluation's random starts) in the
waiting mode (the simulator waits for the controller: the quality columns isolate the controller,
and the wall times are still measured per call) with the learned model and with the closed-form
body. Columns: whole controller time per period (call plus the preparation after the torque is
sent) and the feedback alone (observation to torque), medians and p99; success, mean closed-loop
cost and median time to upright over the starts.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from benchmarks.common import NOISE_NOTE, plot_pareto
from benchmarks.study import StudyResult
from fvin_mpc.control.closed_loop import episode_metrics, run_episode
from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings
from fvin_mpc.studies.starts import episode_starts

#: (label, overrides of the scene's RTI settings); the first is the scene's own.
CONFIGS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("scene default", {}),
    ("unrolled step", {"rti": {"dynamics": "unrolled"}}),
    ("implicit", {"rti": {"dynamics": "implicit"}}),
    ("3 QP it.", {"rti": {"qp_iterations": 3}}),
    ("5 QP it.", {"rti": {"qp_iterations": 5}}),
    ("20 QP it.", {"rti": {"qp_iterations": 20}}),
    ("N=15", {"horizon": 15}),
    ("N=30", {"horizon": 30}),
    ("N=40", {"horizon": 40}),
    ("≤3 GN it. in 5 ms", {"rti": {"max_iter": 3, "budget_s": 0.005}}),
)
QUICK = ("scene default", "5 QP it.")
COLUMNS = ["config", "model", "call_ms_median", "call_ms_p99", "feedback_ms_median", "feedback_ms_p99",
           "learned_vs_true", "successes", "starts", "cost_mean", "time_to_upright_median_s"]


def measure(scene: str, overrides: dict[str, Any], true_model: bool, starts: list[Any], duration: float,
            compile_: str = "cached") -> dict[str, Any]:
    """One configuration on one model over ``starts``: times per period and closed-loop outcome."""

    env = scene_env(scene, true_model=true_model)
    controller = scene_mpc(env, scene_model(env, true_model=true_model),
                           scene_mpc_settings(env, solver="rti", compile=compile_, **overrides))
    calls, feedback, costs, reached = [], [], [], []
    for start in starts:
        episode, _ = run_episode(env, controller, duration, start.reset_options, seed=start.seed, latency="none")
        calls.append(episode.controller_time_s)
        feedback.append(episode.feedback_s)
        metrics = episode_metrics(episode)
        costs.append(metrics["accumulated_cost"])
        reached.append(metrics["time_to_upright_s"])
    env.close()
    calls_ms, feedback_ms = 1e3 * np.concatenate(calls), 1e3 * np.concatenate(feedback)
    times = [t for t in reached if t is not None]
    return {"call_ms_median": float(np.median(calls_ms)), "call_ms_p99": float(np.percentile(calls_ms, 99)),
            "feedback_ms_median": float(np.median(feedback_ms)),
            "feedback_ms_p99": float(np.percentile(feedback_ms, 99)),
            "successes": len(times), "starts": len(starts), "cost_mean": float(np.mean(costs)),
            "time_to_upright_median_s": float(np.median(times)) if times else None}


def run(quick: bool = False, seed: int = 0, starts: int = 20, duration: float = 10.0, scene: str = "pendulum",
        **_: Any) -> StudyResult:
    from tqdm.auto import tqdm

    if quick:
        starts, duration = 2, 2.0
    episodes = episode_starts(starts, seed, (2.0,))
    configs = [c for c in CONFIGS if not quick or c[0] in QUICK]
    load = os.getloadavg()

    probe = scene_env(scene, true_model=True)
    default = scene_mpc_settings(probe, solver="rti")
    probe.close()
    rows: list[dict[str, Any]] = []
    jobs = [(label, overrides, true_model) for label, overrides in configs for true_model in (False, True)]
    for label, overrides, true_model in tqdm(jobs, desc="rti configurations", leave=False):
        row = measure(scene, overrides, true_model, episodes, duration, "none" if quick else "cached")
        rows.append({"config": label, "model": "closed form" if true_model else "learned", **row})
    for row in rows:
        if row["model"] == "learned":
            closed = next(r for r in rows if r["config"] == row["config"] and r["model"] == "closed form")
            row["learned_vs_true"] = row["call_ms_median"] / closed["call_ms_median"]
        else:
            row["learned_vs_true"] = None
    notes = [
        f"`{scene}` scene, {starts} starts of {duration:g} s (episode 0 hanging at rest, then seeded random starts "
        f"with |ω₀| ≤ 2 rad/s, seed {seed}), the scene's RTI settings (N = {default.horizon}, "
        f"{default.rti.qp_iterations} QP iterations, {default.rti.max_iter} Gauss–Newton iteration per period, "
        f"{default.rti.dynamics} dynamics) with "
        "one knob changed per row, in the "
        "waiting mode (the simulator waits for the controller; quality, not real-time closed-loop behaviour — "
        "the per-call wall times are measured all the same). `call_ms`: the whole controller time per period "
        "(the call and the preparation after the torque is sent); `feedback_ms`: the call alone, observation "
        "to torque; `learned_vs_true`: median whole time, learned over closed form, same configuration; "
        "`cost_mean`: the env's accumulated cost (angle² + 0.1 ω² + 0.001 u² per period).",
        "The cold start's budget is wall clock (`rti.cold_budget_s`), so the first plans, and with them the "
        "costs, differ from run to run (by ~10 % in the mean over 20 starts); compare rows within one run.",
        f"Load average (1, 5, 15 min) when the study started: {load[0]:.2f}, {load[1]:.2f}, {load[2]:.2f}.",
        NOISE_NOTE,
    ]

    def plot(figure: Any, rows_: list[dict[str, Any]]) -> None:
        left, right = figure.subplots(1, 2)
        plot_pareto(left, [r for r in rows_ if r["model"] == "learned"], "call_ms_median", "cost_mean", "config",
                    "whole controller time, median (ms)", "mean closed-loop cost")
        left.set_title("learned model", fontsize=9)
        plot_pareto(right, [r for r in rows_ if r["model"] == "closed form"], "call_ms_median", "cost_mean",
                    "config", "whole controller time, median (ms)", "mean closed-loop cost")
        right.set_title("closed-form model", fontsize=9)
        figure.suptitle("Real-time iteration: time per period against closed-loop cost", fontsize=10)

    return StudyResult("rti", rows, COLUMNS, plot, notes)


def add_arguments(parser: Any) -> None:
    parser.add_argument("--starts", type=int, default=20, help="seeded starts per configuration (default: %(default)s)")
    parser.add_argument("--duration", type=float, default=10.0, help="seconds per episode (default: %(default)s)")
    parser.add_argument("--scene", default="pendulum", help="scene with a pivoted body (default: %(default)s)")
