"""``horizon``: model step h ∈ {0.02, 0.05} s and MPC horizon 0.5 … 3 s — solve time vs closed-loop quality.

Each model runs at its own control period (the scene's env with ``control_period = h``):
``h = 0.05`` with the shipped ``pendulum_sign-invariant``, ``h = 0.02`` with
``pendulum-h0.02_sign-invariant`` (trained on data collected at 0.02 s; the commands are in
``docs/bench/horizon.md``). Horizons are chosen in seconds, so ``N = T/h`` (10 … 60 steps at
0.05 s, 25 … 150 at 0.02 s). Every configuration swings the MuJoCo pendulum up from rest with
the default MPC (IPOPT, Gauss–Newton, compiled, primal–dual warm start).
``--model true`` uses the closed-form body at both step sizes instead.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from benchmarks.common import NOISE_NOTE, checkpoint_or_none, make_env, plot_pareto, solve_stats
from benchmarks.study import StudyResult
from fvin_mpc.control.model_export import from_checkpoint, from_rigid_body
from fvin_mpc.control.mpc import MPCSettings
from fvin_mpc.core.rigid_body import from_mujoco

CHECKPOINTS = {0.05: "pendulum_sign-invariant", 0.02: "pendulum-h0.02_sign-invariant"}
HORIZONS_S = (0.5, 1.0, 1.5, 2.0, 3.0)

#: Commands that produced the h = 0.02 checkpoint (also in the notes of the study).
H002_COMMANDS = (
    "python -m fvin_mpc.collect --scene pendulum --control-period 0.02 --trajectories 320 --steps 20 --seed 0 "
    "--out data/pendulum-h0.02.npz",
    "python -m fvin_mpc.train --data data/pendulum-h0.02.npz --variant sign-invariant "
    "--out checkpoints/pendulum-h0.02_sign-invariant",
)


def run(quick: bool = False, seed: int = 0, repeats: int = 5, model: str = "learned", duration: float = 8.0,
        steps: str = "0.05,0.02", horizons: str = ",".join(f"{t:g}" for t in HORIZONS_S), **_: Any) -> StudyResult:

    step_sizes = [0.05] if quick else [float(v) for v in steps.split(",")]
    horizon_s = [0.5, 1.0] if quick else [float(v) for v in horizons.split(",")]
    duration = 1.0 if quick else duration
    model = "true" if quick else model
    rows: list[dict[str, Any]] = []
    notes: list[str] = []
    trained: list[str] = []
    for h in step_sizes:
        env = make_env("pendulum", h)
        base = env.unwrapped
        if model == "true":
            exported = from_rigid_body(from_mujoco(base.model, base.body_name), h, 2, name=f"true_pendulum_h{h:g}")
            label = "closed form"
        else:
            name = CHECKPOINTS.get(h)
            ckpt = checkpoint_or_none(name) if name else None
            if ckpt is None:
                notes.append(f"**h = {h:g} s skipped**: checkpoint {name!r} not found in checkpoints/.")
                continue
            if abs(ckpt.config.step_size - h) > 1e-12:
                raise ValueError(f"checkpoint {name} has step {ckpt.config.step_size}, expected {h}")
            exported = from_checkpoint(ckpt)
            label = name
            training = ckpt.metadata.get("training", {})
            trained.append(f"`{name}`: {training.get('iterations')} iterations, "
                           f"{training.get('wall_clock_s', float('nan')):.0f} s wall clock, "
                           f"validation loss {training.get('final_validation_loss', float('nan')):.2g}")
        for seconds in horizon_s:
            n = int(round(seconds / h))
            settings = replace(MPCSettings(), horizon=n, compile="none" if quick else "cached")
            metrics = solve_stats(env, exported, settings, duration, seed=seed)
            rows.append({
                "model": label, "h": h, "N": n, "horizon_s": n * h,
                "mpc_ms_median": metrics["solver_ms_median"], "mpc_ms_p95": metrics["solver_ms_p95"],
                "period_ms": 1e3 * h, "iterations_mean": metrics["iterations_mean"],
                "success": metrics["success"], "swung_up": metrics["swung_up"],
                "time_to_upright_s": metrics["time_to_upright_s"],
                "hold_error_rad": metrics["hold_error_rad"],
                # The env's cost is summed per control period; × h makes it a time integral, comparable across h.
                "cost_integral": metrics["accumulated_cost"] * h,
                "solver_failures": metrics["solver_failures"], "build_s": metrics["build_s"],
                "label": f"h={h:g}, N={n}",
            })
        env.close()
    notes = [
        f"Swing-up from rest on the MuJoCo pendulum, {duration:g} s at the model's own control period; "
        "`mpc_ms_*` is IPOPT's time per control step (real time needs it below `period_ms`); `cost_integral` is "
        "∫(angle² + 0.1 ω² + 0.001 u²) dt over the episode (the env's cost × h, comparable across h); "
        "`time_to_upright_s` is when the pendulum is within 0.1 rad of upright for good.",
        "The h = 0.02 model: data and training commands — "
        + "; ".join(f"`{c}`" for c in H002_COMMANDS)
        + ". Same number of trajectories, steps and windows as the h = 0.05 model's data; its trajectories cover "
          "0.4 s instead of 1 s. " + ("Training (from the checkpoints' JSON sidecars): " + "; ".join(trained) + "."
                                       if trained else ""),
        *notes,
        NOISE_NOTE,
    ]
    good = [r for r in rows if r["swung_up"]]
    if good:
        best = min(good, key=lambda r: r["mpc_ms_median"])
        notes.insert(
            1,
            f"Cheapest successful configuration: **{best['label']}** ({best['horizon_s']:g} s horizon, "
            f"{best['mpc_ms_median']:.1f} ms median solve, upright after {best['time_to_upright_s']:.2f} s). "
            "`success` = upright (within 0.1 rad) from some time to the end of the episode; `swung_up` = "
            "also held within 0.05 rad over the last 3 s.",
        )

    def plot(figure: Any, rows_: list[dict[str, Any]]) -> None:
        left, right = figure.subplots(1, 2)
        for h in sorted({r["h"] for r in rows_}):
            group = [r for r in rows_ if r["h"] == h]
            left.plot([r["horizon_s"] for r in group], [r["mpc_ms_median"] for r in group], "o-", label=f"h = {h:g} s")
            left.axhline(1e3 * h, ls=":", color=left.lines[-1].get_color())
        left.set_yscale("log")
        left.set_xlabel("horizon (s)")
        left.set_ylabel("MPC solve time, median (ms)")
        left.legend(fontsize=8)
        left.grid(True, alpha=0.3)
        plot_pareto(right, rows_, "mpc_ms_median", "cost_integral", "label", "MPC solve time, median (ms)",
                    "closed-loop cost ∫ c dt", group="h")
        figure.suptitle("Horizon and step size (dotted: control period)", fontsize=10)

    return StudyResult("horizon", rows,
                       ["model", "h", "N", "horizon_s", "mpc_ms_median", "mpc_ms_p95", "period_ms", "iterations_mean",
                        "success", "swung_up", "time_to_upright_s", "hold_error_rad", "cost_integral",
                        "solver_failures", "build_s"],
                       plot, notes)


def add_arguments(parser: Any) -> None:
    parser.add_argument("--model", choices=["learned", "true"], default="learned",
                        help="shipped checkpoints per step size, or the closed-form body (default: %(default)s)")
    parser.add_argument("--duration", type=float, default=8.0, help="closed-loop seconds (default: %(default)s)")
    parser.add_argument("--steps", default="0.05,0.02", help="model step sizes h in s (default: %(default)s)")
    parser.add_argument("--horizons", default=",".join(f"{t:g}" for t in HORIZONS_S),
                        help="horizons in seconds (default: %(default)s)")
