"""Helpers shared by the studies: held-out data, models, closed-loop swing-ups, Pareto plots."""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fvin_mpc.control.closed_loop import episode_metrics, run_episode
from fvin_mpc.control.scene import scene_mpc
from fvin_mpc.core.checkpoint import checkpoint_exists, load_checkpoint
from fvin_mpc.core.data import load_data, save_data
from fvin_mpc.envs import RigidBodyEnv
from fvin_mpc.learning.collection import SPEED_BOUNDED, collect

#: The note every timing study carries.
NOISE_NOTE = ("Timings were taken on a 2-core machine shared with other jobs (training, tests): absolute "
              "times are noisy; compare configurations by the ratios within this one run.")


#: Scenes whose held-out data must stay inside the speeds the model can represent: collected
#: with :func:`fvin_mpc.learning.collection.collect`'s ``max_speed`` (``|ω_i| ≤ 15`` rad/s throughout; the
#: unfiltered collector spins the light z axis past the step's solvability limit) and with the
#: size of ``docs/spherical.md``'s held-out set.
BOUNDED_HELDOUT: dict[str, dict[str, Any]] = {"spherical_pendulum": {"trajectories": 100, "max_speed": 15.0}}


def heldout_data(scene: str = "pendulum", control_period: float | None = None, seed: int = 1,
                 trajectories: int | None = None, steps: int = 40, path: Path | None = None,
                 progress: bool = False) -> Any:
    """Held-out MuJoCo trajectories, collected (seeded) and saved under ``data/`` if missing.

    The default is the data of ``python -m fvin_mpc.collect --seed 1 --trajectories 64 --steps 40
    --out data/<scene>_heldout.npz``, for the scenes in :data:`BOUNDED_HELDOUT` that of
    ``python -m benchmarks.spherical_report collect --trajectories 100 --steps 40 --seed 1 --out
    data/<scene>_heldout.npz``. ``control_period`` other than the scene's adds ``-h<period>``
    to the file name.

    Raises:
        ValueError: the file exists but holds other data (different size, seed, period or
            collector): it is never overwritten; delete it or pass another ``path``.
    """

    stem = Path(scene).stem + (f"-h{control_period:g}" if control_period is not None else "")
    bounded = BOUNDED_HELDOUT.get(Path(scene).stem)
    default_trajectories = bounded["trajectories"] if bounded else 64
    trajectories = default_trajectories if trajectories is None else trajectories
    if path is None:
        path = Path("data") / f"{stem}_heldout.npz"
        if (trajectories, steps, seed) != (default_trajectories, 40, 1):
            path = Path("data") / f"{stem}_heldout_{trajectories}x{steps}_s{seed}.npz"
    expected_collector = SPEED_BOUNDED if bounded else None
    if path.is_file():
        data = load_data(path)
        meta = data.metadata
        found = (meta.get("trajectories"), meta.get("steps"), meta.get("seed"), meta.get("collector"))
        if found == (trajectories, steps, seed, expected_collector) and (
                control_period is None or abs(data.control_period - control_period) < 1e-12):
            return data
        raise ValueError(f"{path} holds other data than the held-out set asked for (trajectories, steps, seed, "
                         f"collector = {found}, wanted {(trajectories, steps, seed, expected_collector)}); "
                         "delete it to have it collected again")
    print(f"collecting held-out data {path} (seed {seed}, {trajectories}×{steps})", file=sys.stderr)
    if bounded:
        if control_period is not None:
            raise ValueError(f"{scene}: the speed-bounded held-out data are collected at the scene's own period only")
        data = collect(scene, trajectories, steps, seed, hold_steps=2, max_speed=bounded["max_speed"],
                       progress=progress)
    else:
        data = collect(scene, trajectories, steps, seed, progress=progress, control_period=control_period)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_data(path, data)
    return data


def checkpoint_or_none(name: str) -> Any:
    """The checkpoint called ``name``, or ``None`` if it is not there (studies skip it and say so).

    A checkpoint that is there but corrupted or inconsistent raises its
    :class:`~fvin_mpc.core.checkpoint.CheckpointError`: it is not "missing".
    """

    return load_checkpoint(name) if checkpoint_exists(name) else None


def make_env(scene: str, control_period: float | None = None) -> Any:
    return RigidBodyEnv(scene=scene, control_period=control_period)


def solve_stats(env: Any, model: Any, settings: Any, duration_s: float, reset_options: dict | None = None,
            seed: int = 0) -> dict[str, Any]:
    """Build the scene's MPC on ``model`` with ``settings``, run one episode; metrics, build info and
    the solver's iterations and solve times of every call."""

    controller = scene_mpc(env, model, settings)
    episode, _ = run_episode(env, controller, duration_s, reset_options, seed=seed)
    metrics = episode_metrics(episode)
    infos = episode.controller_info
    solve_ms = 1e3 * np.array([i["solve_time_s"] for i in infos])
    report = controller.compile_report
    metrics.update(
        build_s=controller.build_s, compile_cached=None if report is None else report.cached,
        compile_s=None if report is None else report.compile_s,
        solver_ms_median=float(np.median(solve_ms)), solver_ms_p95=float(np.percentile(solve_ms, 95)),
        iterations_mean=float(np.mean([i["iterations"] for i in infos])),
        solver_failures=int((~episode.controller_success).sum()),
    )
    return metrics


def pareto_mask(x: Sequence[float], y: Sequence[float]) -> np.ndarray:
    """Points not dominated (smaller ``x`` and smaller ``y`` are better); NaN/None never on the front."""
    x = np.array([np.nan if v is None else v for v in x], dtype=float)
    y = np.array([np.nan if v is None else v for v in y], dtype=float)
    ok = np.isfinite(x) & np.isfinite(y)
    mask = np.zeros(x.size, dtype=bool)
    for i in np.flatnonzero(ok):
        dominated = ok & (x <= x[i]) & (y <= y[i]) & ((x < x[i]) | (y < y[i]))
        mask[i] = not dominated.any()
    return mask


def plot_pareto(axis: Any, rows: list[dict[str, Any]], x: str, y: str, label: str, xlabel: str, ylabel: str,
                log: bool = True, group: str | None = None) -> None:
    """Scatter ``rows`` as (``x``, ``y``), label each point, draw the Pareto front as a step line."""
    xs = [r.get(x) for r in rows]
    ys = [r.get(y) for r in rows]
    groups = sorted({str(r.get(group)) for r in rows}) if group else [None]
    colors = dict(zip(groups, ["tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown"] * 3))
    for r, xv, yv in zip(rows, xs, ys):
        if xv is None or yv is None or not (np.isfinite(xv) and np.isfinite(yv)):
            continue
        g = str(r.get(group)) if group else None
        axis.scatter([xv], [yv], color=colors[g], s=25, zorder=3)
        axis.annotate(str(r.get(label)), (xv, yv), fontsize=6, xytext=(3, 3), textcoords="offset points")
    mask = pareto_mask(xs, ys)
    if mask.any():
        front = sorted((xs[i], ys[i]) for i in np.flatnonzero(mask))
        axis.step([p[0] for p in front], [p[1] for p in front], where="post", color="tab:gray", ls="--",
                  label="Pareto front", zorder=2)
        axis.legend(loc="best", fontsize=8)
    if group:
        for g in groups:
            axis.scatter([], [], color=colors[g], label=f"{group} = {g}")
        axis.legend(loc="best", fontsize=8)
    finite = [(a, b) for a, b in zip(xs, ys) if a is not None and b is not None and np.isfinite(a) and np.isfinite(b)]
    from matplotlib.ticker import NullFormatter

    for values, set_scale, scale_axis in (([a for a, _ in finite], axis.set_xscale, axis.xaxis),
                                          ([b for _, b in finite], axis.set_yscale, axis.yaxis)):
        if log and values and min(values) > 0:
            set_scale("log")
            if max(values) / min(values) > 10:  # within one decade the minor labels are the only labels
                scale_axis.set_minor_formatter(NullFormatter())
    axis.set_xlabel(xlabel)
    axis.set_ylabel(ylabel)
    axis.grid(True, which="both", alpha=0.3)


def timed(function: Any) -> tuple[Any, float]:
    start = time.perf_counter()
    value = function()
    return value, time.perf_counter() - start


__all__ = [
    "NOISE_NOTE",
    "BOUNDED_HELDOUT",
    "heldout_data",
    "checkpoint_or_none",
    "make_env",
    "solve_stats",
    "pareto_mask",
    "plot_pareto",
    "timed",
    "replace",
]
