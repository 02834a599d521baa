"""``solver``: Hessian, compiled code, warm start and NLP solver of the MPC — solve time vs result.

Configurations of :class:`fvin_mpc.control.mpc.MPCSettings` on the same swing-up from rest (MuJoCo
pendulum, the shipped learned model or ``--model true``): IPOPT with the Gauss–Newton,
exact and limited-memory Hessians, with the NLP's functions compiled to C (cached) or
interpreted; warm start none / primal / primal–dual; and CasADi's ``sqpmethod`` (qrqp) and
``fatrop`` on the same problem. Per configuration: median / p95 solve time, mean iterations,
closed-loop success and time to upright, and — for compiled configurations — the time to
build the solver with an empty cache (gcc runs) and with the library cached.

A second table (unless ``--no-realtime``; not in ``--quick``) puts the real-time iteration
(:class:`fvin_mpc.control.rti.RealTimeMPC`) beside IPOPT on both scenes (``pendulum``,
``spherical_pendulum``), learned and closed-form model in the same run, with the scene's own MPC
settings (what the commands use): IPOPT in waiting mode (the reference: the simulator waits for it)
and with measured latency, and the RTI with measured latency (``run_episode(latency="measured")``:
each torque acts from the first MuJoCo sub-step after the controller's compute time). Per row: the
whole controller call (feedback plus preparation; median, p99, max), its CPU time, the feedback
alone (observation to torque), iterations per call, deadline misses, and the swing-up from rest (time to upright,
hold error over the last 3 s).
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import replace
from typing import Any

from benchmarks.common import NOISE_NOTE, checkpoint_or_none, make_env, plot_pareto, solve_stats
from benchmarks.study import StudyResult, StudySkipped
from fvin_mpc.control.closed_loop import episode_metrics, run_episode
from fvin_mpc.control.model_export import cache_dir, from_checkpoint, from_rigid_body
from fvin_mpc.control.mpc import MPC, MPCSettings
from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings
from fvin_mpc.core.checkpoint import load_checkpoint
from fvin_mpc.core.rigid_body import from_mujoco
from fvin_mpc.studies.report import markdown_table

#: (label, settings overrides) — IPOPT (the default solver) first.
CONFIGS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("ipopt GN cached pd (default)", {}),
    ("ipopt GN cached primal", {"ipopt": {"warm_start": "primal"}}),
    ("ipopt GN cached none", {"ipopt": {"warm_start": "none"}}),
    ("ipopt GN interpreted pd", {"compile": "none"}),
    ("ipopt exact cached pd", {"ipopt": {"hessian": "exact"}}),
    ("ipopt exact interpreted pd", {"ipopt": {"hessian": "exact"}, "compile": "none"}),
    ("ipopt L-BFGS cached pd", {"ipopt": {"hessian": "limited-memory"}}),
    ("ipopt L-BFGS interpreted pd", {"ipopt": {"hessian": "limited-memory"}, "compile": "none"}),
    ("sqpmethod GN cached pd", {"solver": "sqpmethod"}),
    ("sqpmethod exact cached pd", {"solver": "sqpmethod", "ipopt": {"hessian": "exact"}}),
    ("fatrop exact interpreted", {"solver": "fatrop", "ipopt": {"hessian": "exact"}, "compile": "none"}),
)
QUICK = ("ipopt GN cached pd (default)", "sqpmethod GN cached pd", "fatrop exact interpreted")


def _model(model: str) -> tuple[Any, Any, str]:
    env = make_env("pendulum")
    base = env.unwrapped
    if model == "true":
        return (
            env,
            from_rigid_body(from_mujoco(base.model, base.body_name), base.dt, 2, name="true_pendulum"),
            "closed form",
        )
    ckpt = checkpoint_or_none("pendulum_sign-invariant")
    if ckpt is None:
        raise StudySkipped("checkpoint 'pendulum_sign-invariant' not found in checkpoints/; run with --model true")
    return env, from_checkpoint(ckpt), "pendulum_sign-invariant"


def _cold_build_s(exported: Any, settings: Any) -> float:
    """Seconds to build the solver with an empty compiled-code cache (a private temporary one).

    The library it compiles is then copied into the real cache, so the next build is a cached one."""
    import shutil
    from pathlib import Path

    previous = os.environ.get("FVIN_MPC_CACHE")
    with tempfile.TemporaryDirectory(prefix="fvin_mpc_cold_") as empty:
        os.environ["FVIN_MPC_CACHE"] = empty
        try:
            seconds = MPC(exported, settings).build_s
        finally:
            if previous is None:
                os.environ.pop("FVIN_MPC_CACHE", None)
            else:
                os.environ["FVIN_MPC_CACHE"] = previous
        cache_dir().mkdir(parents=True, exist_ok=True)
        for library in Path(empty).glob("*.so"):
            if not (cache_dir() / library.name).exists():
                shutil.copy2(library, cache_dir() / library.name)
    return seconds


#: (label, settings overrides, latency) of the real-time table; IPOPT's waiting row is the reference.
REALTIME_CONFIGS: tuple[tuple[str, dict[str, Any], Any], ...] = (
    ("ipopt (waiting)", {}, "none"),
    ("ipopt", {}, "measured"),
    ("rti", {"solver": "rti"}, "measured"),
    ("rti, unrolled step", {"solver": "rti", "rti": {"dynamics": "unrolled"}}, "measured"),
    ("rti, implicit", {"solver": "rti", "rti": {"dynamics": "implicit"}}, "measured"),
    ("rti ≤4 it. in 10 ms", {"solver": "rti", "rti": {"max_iter": 4, "budget_s": 0.01}}, "measured"),
)
REALTIME_SCENES = ("pendulum", "spherical_pendulum")
#: Further learned checkpoints per scene, beside the scene's own: what the model's structure costs in
#: time. The fixed-inertia pendulum has one network for ``U`` and one for ``g``, each evaluated once
#: per point; the sign-invariant default evaluates three networks (``J(q)`` too) at ``q`` and ``−q``,
#: and ``J`` again at the step's end (docs/realtime.md).
REALTIME_EXTRA_CHECKPOINTS: dict[str, tuple[str, ...]] = {"pendulum": ("pendulum_fixed-inertia",)}
REALTIME_COLUMNS = [
    "scene",
    "model",
    "controller",
    "latency",
    "call_ms_median",
    "call_ms_p99",
    "call_ms_max",
    "cpu_ms_median",
    "learned_vs_true",
    "feedback_ms_median",
    "feedback_ms_p99",
    "feedback_learned_vs_true",
    "iterations_mean",
    "deadline_misses",
    "failures",
    "time_to_upright_s",
    "hold_error_rad",
    "swung_up",
]


def realtime_rows(duration: float = 10.0, seed: int = 0, scenes: tuple[str, ...] = REALTIME_SCENES,
                  configs: tuple[tuple[str, dict[str, Any], Any], ...] = REALTIME_CONFIGS,
                  extra_checkpoints: dict[str, tuple[str, ...]] = REALTIME_EXTRA_CHECKPOINTS) -> list[dict[str, Any]]:
    """One swing-up from rest per scene × model (learned, closed form, and ``extra_checkpoints[scene]``,
    labelled ``learned (<variant>)``) × configuration."""
    import numpy as np

    rows: list[dict[str, Any]] = []
    for scene in scenes:
        models = [("learned", None, False), ("closed form", None, True)]
        models += [(f"learned ({_variant(name)})", name, False) for name in extra_checkpoints.get(scene, ())]
        for model_label, checkpoint, true_model in models:
            env = scene_env(scene, checkpoint=checkpoint, true_model=true_model)
            exported = scene_model(env, checkpoint=checkpoint, true_model=true_model)
            for label, overrides, latency in configs:
                controller = scene_mpc(env, exported, scene_mpc_settings(env, **overrides))
                episode, _ = run_episode(env, controller, duration, seed=seed, latency=latency)
                metrics = episode_metrics(episode)
                calls = 1e3 * episode.controller_time_s[np.isfinite(episode.controller_time_s)]
                feedback = 1e3 * episode.feedback_s[np.isfinite(episode.feedback_s)]
                iterations = [i["iterations"] for i in episode.controller_info if "iterations" in i]
                rows.append(
                    {
                        "scene": scene,
                        "model": model_label,
                        "controller": label,
                        "latency": latency,
                        "call_ms_median": float(np.median(calls)),
                        "call_ms_p99": float(np.percentile(calls, 99)),
                        "call_ms_max": float(calls.max()),
                        "feedback_ms_median": float(np.median(feedback)),
                        "feedback_ms_p99": float(np.percentile(feedback, 99)),
                        "cpu_ms_median": float(np.nanmedian(1e3 * episode.cpu_s))
                        if episode.cpu_s is not None
                        else None,
                        "iterations_mean": float(np.mean(iterations)) if iterations else None,
                        "deadline_misses": metrics["deadline_misses"],
                        "failures": metrics["controller_failures"],
                        "time_to_upright_s": metrics["time_to_upright_s"],
                        "hold_error_rad": metrics["hold_error_rad"],
                        "swung_up": metrics["swung_up"],
                    }
                )
            env.close()
    for row in rows:
        true_row = next(r for r in rows if r["scene"] == row["scene"] and r["controller"] == row["controller"]
                        and r["model"] == "closed form")
        learned = row["model"].startswith("learned")
        row["learned_vs_true"] = row["call_ms_median"] / true_row["call_ms_median"] if learned else None
        row["feedback_learned_vs_true"] = (row["feedback_ms_median"] / true_row["feedback_ms_median"]
                                           if learned else None)
    return rows


def _variant(checkpoint: str) -> str:
    """The checkpoint's variant, from its metadata (``pendulum_fixed-inertia`` → ``fixed-inertia``)."""

    return load_checkpoint(checkpoint).config.variant


def run(quick: bool = False, seed: int = 0, repeats: int = 5, model: str = "learned", horizon: int = 30,
        duration: float = 8.0, cold: bool = True, realtime: bool = True, realtime_duration: float = 10.0,
        **_: Any) -> StudyResult:

    model = "true" if quick else model
    env, exported, label = _model(model)
    if quick:
        horizon, duration, cold = 10, 1.0, False
    configs = [c for c in CONFIGS if not quick or c[0] in QUICK]
    rows: list[dict[str, Any]] = []
    for name, overrides in configs:
        settings = MPCSettings().updated(horizon=horizon, **overrides)
        if quick and settings.compile == "cached":
            settings = replace(settings, compile="none")
        cold_s = _cold_build_s(exported, settings) if cold and settings.compile == "cached" else None
        metrics = solve_stats(env, exported, settings, duration, seed=seed)
        if quick:
            name = name.replace("cached", "interpreted")
        rows.append({
            "config": name, "solver": settings.solver, "hessian": settings.ipopt.hessian, "compile": settings.compile,
            "warm_start": settings.ipopt.warm_start if settings.solver != "fatrop" else "primal",
            "mpc_ms_median": metrics["solver_ms_median"], "mpc_ms_p95": metrics["solver_ms_p95"],
            "iterations_mean": metrics["iterations_mean"], "success": metrics["success"],
            "time_to_upright_s": metrics["time_to_upright_s"], "solver_failures": metrics["solver_failures"],
            "build_cold_s": cold_s, "build_cached_s": metrics["build_s"],
        })
    default = rows[0]["mpc_ms_median"]
    for r in rows:
        r["time_vs_default"] = r["mpc_ms_median"] / default
    notes = [
        f"Model: **{label}**, N = {horizon}, swing-up from rest on MuJoCo for {duration:g} s (h = 0.05 s). "
        "GN = Gauss–Newton (constant cost Hessian, no second derivatives of the model), exact = with the "
        "dynamics' second derivatives, L-BFGS = IPOPT's limited-memory quasi-Newton; cached = the NLP's functions "
        "compiled to C once (`build_cold_s`: gcc with an empty cache; `build_cached_s`: library found on disk), "
        "interpreted = CasADi's virtual machine; warm start pd = shifted plan and multipliers. "
        "`sqpmethod` uses the qrqp active-set QP solver; `fatrop` needs the exact Hessian and the problem "
        "ordered stage by stage, and is run on expanded functions in the virtual machine (it accepts no "
        "external Hessian); it is given the shifted plan as its starting point.",
        "All configurations solve the same problem: differences in success or time to upright come from "
        "solver failures (fallback torques), iteration limits, or convergence to a different local optimum.",
        NOISE_NOTE,
    ]
    if realtime and not quick:

        load = os.getloadavg()
        realtime_table = realtime_rows(realtime_duration, seed)
        notes += [
            "## Real-time controllers, both scenes, learned vs closed form",
            markdown_table(realtime_table, REALTIME_COLUMNS),
            f"Swing-up from hanging at rest, {realtime_duration:g} s, the scene's MPC settings. `latency` none: the "
            "simulator waits for the controller (IPOPT's reference row: model quality, not real time); measured: "
            "each torque acts from the first 5 ms MuJoCo sub-step after the controller's measured compute time, "
            "the previous torque holds until then, and a call that outlasts the 50 ms period skips the next "
            "observation (a deadline miss). `call_ms`: wall time of the whole controller call per sampled period "
            "(feedback plus the RTI's preparation); `cpu_ms`: its CPU time (the difference is time the shared "
            "machine gave to other jobs); `learned_vs_true`: median call time, learned over closed form, same "
            "controller. `feedback_ms`: the call alone, observation to torque (the delay the plant sees; the "
            "RTI prepares the next call after the torque is sent), and its learned / closed-form ratio. "
            "`rti`: the scene's RTI settings (its dynamics constraint: `implicit` on `pendulum`, `unrolled` on "
            "`spherical_pendulum`); `rti, unrolled step` / `rti, implicit`: the same with that constraint "
            "(fvin_mpc/control/implicit_dynamics.py). "
            "`rti ≤4 it. in 10 ms`: further Gauss–Newton iterations while the call's wall time allows. "
            "`learned (fixed-inertia)`: the scene's shipped fixed-inertia checkpoint beside its default "
            "(sign-invariant) one — what the learned model's structure costs per call. "
            f"Load average (1, 5, 15 min) when the table started: {load[0]:.2f}, {load[1]:.2f}, {load[2]:.2f}.",
        ]

    return StudyResult("solver", rows,
                       ["config", "mpc_ms_median", "mpc_ms_p95", "time_vs_default", "iterations_mean", "success",
                        "time_to_upright_s", "solver_failures", "build_cold_s", "build_cached_s"], plot, notes)


def plot(figure: Any, rows: list[dict[str, Any]]) -> None:
    """Left: median solve time (bar) and p95 (tick) per configuration, hatched where the swing-up failed.
    Right: solve time vs mean iterations with the Pareto front."""
    left, right = figure.subplots(1, 2, gridspec_kw={"width_ratios": [1.3, 1]})
    colors = {"ipopt": "tab:orange", "sqpmethod": "tab:green", "fatrop": "tab:blue"}
    order = sorted(range(len(rows)), key=lambda i: rows[i]["mpc_ms_median"], reverse=True)
    for position, i in enumerate(order):
        r = rows[i]
        left.barh(position, r["mpc_ms_median"], color=colors.get(r["solver"], "tab:gray"),
                  hatch=None if r["success"] else "///", edgecolor="black", linewidth=0.3)
        left.plot([r["mpc_ms_p95"]], [position], "k|", ms=8)
    left.set_yticks(range(len(order)), [rows[i]["config"] for i in order], fontsize=6)
    left.set_xscale("log")
    left.set_xlabel("solve time (ms): median bar, p95 tick", fontsize=8)
    left.set_title("hatched: swing-up failed", fontsize=8)
    plot_pareto(right, rows, "mpc_ms_median", "iterations_mean", "config", "median solve time (ms)",
                "mean iterations per control step", group="solver")


def add_arguments(parser: Any) -> None:
    parser.add_argument("--model", choices=["learned", "true"], default="learned",
                        help="shipped checkpoint or the closed-form body (default: %(default)s)")
    parser.add_argument("--horizon", type=int, default=30, help="MPC horizon N (default: %(default)s)")
    parser.add_argument("--duration", type=float, default=8.0, help="closed-loop seconds (default: %(default)s)")
    parser.add_argument("--no-cold", dest="cold", action="store_false",
                        help="skip the build with an empty compiled-code cache")
    parser.add_argument("--no-realtime", dest="realtime", action="store_false",
                        help="skip the real-time table (RTI beside IPOPT on both scenes, measured latency)")
    parser.add_argument("--realtime-duration", type=float, default=10.0,
                        help="closed-loop seconds per real-time row (default: %(default)s)")
