"""The 3-D rigid body on a ball joint (scene ``spherical_pendulum``): ``python -m benchmarks.spherical_report``.

Sub-commands:

* ``collect`` — trajectories as :func:`fvin_mpc.learning.collection.collect` draws them with ``max_speed``
  (orientation uniform on
  S³, ω uniform in a ball, constant or piecewise-constant torques uniform in the actuators' box),
  but a trajectory whose angular velocity leaves ``|ω_i| ≤ --max-speed`` at any step is redrawn.
  Why: the z axis has a tiny inertia (0.017 kg·m² against ≈ 0.5 about x, y), so 1.5 N·m spins it up
  by ≈ 4.4 rad/s per control period; unfiltered, 30 % of the states have ``|ω_z| > 20`` rad/s, past
  the point where the FVIN step has a solution at ``h = 0.05`` (``h|ω| ≲ 1`` about a principal axis,
  ``DESIGN.md``). The MPC bounds ``|ω_i| ≤ 0.6/h = 12`` rad/s; 15 rad/s leaves a margin above it.
* ``closed-loop`` — swing-up and hold from hanging at rest and from seeded random (spinning) states,
  learned model and true model side by side: success, time to upright, hold error, MPC solve times,
  the step residual along the plan; writes JSON + a Markdown table.

The model-quality part (held-out rollouts, recovered inertia) is ``python -m fvin_mpc.quality`` on its checkpoints.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from fvin_mpc.control.closed_loop import episode_metrics, run_episode
from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings
from fvin_mpc.studies.starts import episode_starts

SCENE = "spherical_pendulum"


# ---------------------------------------------------------------------------------------------- closed loop
def closed_loop_study(checkpoint: str | None, episodes: int = 21, duration_s: float = 10.0, seed: int = 0,
                      max_omegas: tuple[float, ...] = (2.0, 5.0), models: tuple[str, ...] = ("learned", "true"),
                      horizon: int | None = None, progress: bool = True, indices: tuple[int, int] | None = None,
                      partial_path: Path | None = None) -> dict[str, Any]:
    """Swing-up and hold with the MPC on each model from the same seeded starts (see :func:`episode_starts`).

    ``indices = (first, last)`` runs only those starts (inclusive; for splitting the work over
    processes, merged again by :func:`merge_results`); ``partial_path`` gets the results so far
    after every episode."""
    from tqdm.auto import tqdm

    env = scene_env(SCENE, true_model=True)
    settings = scene_mpc_settings(env, horizon=horizon)
    starts = episode_starts(episodes, seed, max_omegas)
    if indices is not None:
        starts = [start for start in starts if indices[0] <= start.index <= indices[1]]
    checkpoint = checkpoint or env.scene_spec.default_checkpoint
    results: dict[str, Any] = {"settings": dataclasses.asdict(settings),
                               "checkpoint": checkpoint, "duration_s": duration_s, "models": {}}
    for name in models:
        model = scene_model(env, checkpoint if name == "learned" else None, true_model=name == "true")
        mpc = scene_mpc(env, model, settings)
        rows = []
        for start in tqdm(starts, desc=f"closed loop {name}", disable=not progress):
            episode, _ = run_episode(env, mpc, duration_s, start.reset_options, seed=start.seed)
            metrics = episode_metrics(episode)
            records = episode.controller_info
            rows.append({
                "index": start.index, "seed": start.seed, "max_omega0": start.max_omega,
                "q0": episode.q[0].tolist(), "omega0": episode.omega[0].tolist(), **metrics,
                "max_step_residual": float(np.nanmax([r["step_residual"] for r in records])),
                "median_ipopt_iterations": float(np.median([r["iterations"] for r in records])),
                "fallbacks": sum(r["fallback"] is not None for r in records),
                "max_abs_omega": float(np.abs(episode.omega).max()),
                "solve_times_ms": (1e3 * episode.controller_time_s).tolist(),
            })
            if partial_path is not None:
                partial = {**results, "models": {**results["models"], name: {"model": model.name, "episodes": rows}}}
                partial_path.parent.mkdir(parents=True, exist_ok=True)
                partial_path.write_text(json.dumps(partial, indent=1) + "\n")
        results["models"][name] = {"model": model.name, "build_s": mpc.build_s, "episodes": rows,
                                   "summary": summarize(rows)}
    env.close()
    return results


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Aggregate the per-episode rows of one model."""
    times = np.concatenate([r["solve_times_ms"] for r in rows])
    reached = [r["time_to_upright_s"] for r in rows if r["success"]]
    return {
        "episodes": len(rows), "swung_up_and_held": sum(r["swung_up"] for r in rows),
        "success": sum(r["success"] for r in rows),
        "time_to_upright_median_s": float(np.median(reached)) if reached else None,
        "solve_time_median_ms": float(np.median(times)), "solve_time_p95_ms": float(np.percentile(times, 95)),
        "solve_time_max_ms": float(times.max()),
        "controller_failures": int(sum(r["controller_failures"] for r in rows)),
        "max_step_residual": float(max(r["max_step_residual"] for r in rows)),
        "max_abs_omega": float(max(r["max_abs_omega"] for r in rows)),
        "solve_time_per_episode_median_ms": [float(np.median(r["solve_times_ms"])) for r in rows],
    }


def merge_results(parts: list[dict[str, Any]]) -> dict[str, Any]:
    """Combine results of :func:`closed_loop_study` runs over disjoint starts (and/or models)."""
    merged: dict[str, Any] = {k: v for k, v in parts[0].items() if k != "models"}
    merged["models"] = {}
    for part in parts:
        for name, entry in part["models"].items():
            target = merged["models"].setdefault(name, {"model": entry["model"], "episodes": []})
            target["episodes"] += entry["episodes"]
    for entry in merged["models"].values():
        entry["episodes"].sort(key=lambda r: r["index"])
        entry["summary"] = summarize(entry["episodes"])
    return merged


def markdown_tables(results: dict[str, Any]) -> str:
    """A summary table (one row per model) and a per-start table, learned and true side by side."""
    models = list(results["models"])
    lines = ["| model | swung up and held | upright at end | time to upright, median (s) | solve ms median | p95 "
             "| max | failed solves | max step residual (rad/s) | max \\|ω_i\\| (rad/s) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name in models:
        s = results["models"][name]["summary"]
        t = "—" if s["time_to_upright_median_s"] is None else f"{s['time_to_upright_median_s']:.2f}"
        lines.append(f"| {name} (`{results['models'][name]['model']}`) | {s['swung_up_and_held']}/{s['episodes']} "
                     f"| {s['success']}/{s['episodes']} | {t} | {s['solve_time_median_ms']:.0f} "
                     f"| {s['solve_time_p95_ms']:.0f} | {s['solve_time_max_ms']:.0f} | {s['controller_failures']} "
                     f"| {s['max_step_residual']:.1e} | {s['max_abs_omega']:.1f} |")
    lines += [
        "",
        "| # | seed | start | \\|ω₀\\| (rad/s) | " + " | ".join(f"{n}: t↑ (s) / hold err (rad)" for n in models) + " |",
        "|" + "---|" * (4 + len(models)),
    ]
    first = results["models"][models[0]]["episodes"]
    for i, row in enumerate(first):
        start = "rest" if row["index"] == 0 else f"random (≤ {row['max_omega0']:g})"
        cells = []
        for name in models:
            r = results["models"][name]["episodes"][i]
            t = f"{r['time_to_upright_s']:.2f}" if r["success"] else "**fail**"
            cells.append(f"{t} / {r['hold_error_rad']:.3f}")
        lines.append(f"| {row['index']} | {row['seed']} | {start} | {np.linalg.norm(row['omega0']):.2f} | "
                     + " | ".join(cells) + " |")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------- CLI
