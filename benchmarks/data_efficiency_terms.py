"""``data-efficiency-terms``: why a data-efficiency cell fails or costs more — its learned terms.

For every S3FVIN cell of a ``data-efficiency`` run that is in the cache (the same options pick the
cells: ``--sizes``, ``--seeds``, ``--models``, ``--episodes``, ``--v1-episodes``, ``--cache-dir``;
nothing is trained or simulated here), the trained model's terms along the hinge are compared with
the rod's, on both hemispheres of S³:

- the scale ``λ`` of ``(J, U, g)`` (the one quantity data cannot fix) from the potential on the
  ``w ≥ 0`` hemisphere ``q(θ) = (cos θ/2, 0, sin θ/2, 0)``, ``θ ∈ [−π, π]`` — the hemisphere the
  pool's trajectories start on;
- the largest error of ``U/λ`` (as a fraction of the energy span ``U(π) − U(0)``), of ``J_yy/λ``
  and of ``g_y/λ`` (relative) at ``q`` and at ``−q`` — the same rotations. A sign-invariant model
  averages over ``±q``: its two columns agree by construction; the fixed-inertia (``U``, ``g``) and
  plain (all three) variants only learn the other hemisphere from the few states there;
- the share of the training states with ``w < 0`` (the other hemisphere's data);
- the training's iterations and final validation loss (a run stuck in a poor basin shows here);
- the closed loop's success and which starts cost more than ``COSTLY_FACTOR`` × the closed form's
  on the same start (the costly swing-ups: an extra swing, docs/data-efficiency.md).

``--trace CELL:START[,CELL:START…]`` (e.g. ``sign-invariant_n2000_r0:1,closed-form:1``) instead runs
those episodes again (the study's MPC, waiting latency mode) and tabulates, per control period,
the angle from upright, the applied torque and the **closest approach to upright that the plan
made at that period predicts** — whether the MPC still expects to arrive, or already plans to
fall back and swing again.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import data_efficiency as study
from benchmarks.paper import (
    MODELS,
    TRUE_INERTIA,
    TRUE_TORQUE_PER_CONTROL,
    learned_profiles,
    scale_from_potential,
    true_potential,
)
from benchmarks.study import StudyResult
from fvin_mpc.control.closed_loop import run_episode
from fvin_mpc.control.scene import scene_env, scene_mpc
from fvin_mpc.core import s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.checkpoint import load_checkpoint
from fvin_mpc.core.space import S3

#: A start "costs more" when its cost exceeds the closed form's on that start by this factor.
COSTLY_FACTOR = 1.25
#: Angles along the hinge where the terms are compared (both hemispheres use the same rotations).
HINGE_ANGLES = np.linspace(-np.pi, np.pi, 181)


def hemisphere_errors(variant: str, stem: Path) -> dict[str, float]:
    """The scale-fixed term errors of the checkpoint at ``stem`` at ``q`` and ``−q`` (module docstring)."""

    paper_model = next(m for m in MODELS if m.space is S3 and m.variant == variant)
    checkpoint = load_checkpoint(stem)
    truth = true_potential(HINGE_ANGLES)
    span = float(np.ptp(truth))
    upper = learned_profiles(paper_model, checkpoint, HINGE_ANGLES)
    scale = scale_from_potential(upper["potential"], truth)
    errors: dict[str, float] = {"scale": scale}
    for side, profiles in (
        ("q", upper),
        ("minus_q", learned_profiles(paper_model, checkpoint, HINGE_ANGLES, mirrored=True)),
    ):
        errors[f"potential_err_{side}"] = float(np.max(np.abs(profiles["potential"] / scale - truth)) / span)
        errors[f"inertia_err_{side}"] = float(np.max(np.abs(profiles["inertia_yy"] / scale / TRUE_INERTIA - 1.0)))
        # the S³ gain is twice the body torque per unit control
        errors[f"gain_err_{side}"] = float(
            np.max(np.abs(profiles["gain_y"] / scale / (2.0 * TRUE_TORQUE_PER_CONTROL) - 1.0))
        )
    return errors


def other_hemisphere_share(pool: Any, size: int, draw: int, seed: int) -> float:
    """The share of a cell's training states (every period of its trajectories) with ``w < 0``."""
    data = study.training_subset(pool, size, draw, seed)
    return float(np.mean(np.asarray(data.q)[..., 0] < 0.0))


def costly_starts(record: dict[str, Any], reference: dict[str, Any]) -> list[int]:
    """Starts whose cost exceeds ``COSTLY_FACTOR`` × the closed form's on the same start."""
    ours, theirs = record["closed_loop"]["per_episode"], reference["closed_loop"]["per_episode"]
    return [mine["index"] for mine, ref in zip(ours, theirs) if mine["cost"] > COSTLY_FACTOR * ref["cost"]]


def term_rows(config: study.StudyConfig, progress: bool = True) -> tuple[list[dict[str, Any]], list[str]]:
    """One row per cached S3FVIN cell of ``config`` (and the names of the cells not in the cache)."""
    variants = [m for m in config.models if m in study.S3FVIN_VARIANTS]
    if not variants:
        raise ValueError(f"no S3FVIN variant among --models {','.join(config.models)}: choose from "
                         f"{', '.join(study.S3FVIN_VARIANTS)}")
    config = replace(config, models=tuple(variants))
    reference, records, missing = study.run_cells(config, progress=progress, cached_only=True)
    pool = study.training_pool(config, progress)
    reference_cost = reference["closed_loop"]["cost_mean"]
    rows = []
    for record in records:
        name = study.cell_name(record["model"], record["size"], record["draw"])
        loop = record["closed_loop"]
        rows.append({
            "model": record["model"], "transitions": record["size"], "draw": record["draw"],
            "success": f"{loop['successes']}/{loop['episodes']}", "success_rate": loop["successes"] / loop["episodes"],
            "cost_excess_pct": 100.0 * (loop["cost_mean"] / reference_cost - 1.0),
            "costly_starts": costly_starts(record, reference),
            **hemisphere_errors(record["model"], config.cache_dir / "models" / name),
            "other_hemisphere_share": other_hemisphere_share(pool, record["size"], record["draw"], config.seed),
            "iterations": record["training"]["iterations"],
            "validation_loss": record["training"]["final_validation_loss"],
        })
    return rows, missing


def climb_trace(cell: str, start_index: int, config: study.StudyConfig) -> list[dict[str, Any]]:
    """One episode of ``cell`` (a cached model, or ``closed-form``) from the study's start
    ``start_index``: per control period, the angle from upright, ``u`` and the plan's closest approach."""

    model = study.CLOSED_FORM if cell == study.CLOSED_FORM else cell.split("_n")[0]
    trained_as = study.MLP if model == study.MLP_EXACT else model  # as run_cell: the same network, another MPC
    stem = None if model == study.CLOSED_FORM else config.cache_dir / "models" / (trained_as + cell[len(model):])
    if stem is not None and (model not in study.MODELS or not stem.with_suffix(".json").exists()):
        raise ValueError(
            f"no trained model {cell!r} in {config.cache_dir / 'models'} (names as <model>_n<size>_r<draw>)"
        )
    start = study.study_starts(config, start_index + 1)[start_index]
    env = scene_env("pendulum", true_model=True)
    try:
        exported = study.export_cell_model(trained_as, stem, env)
        settings = study.scene_settings(env, config, study.MODEL_MPC_OVERRIDES.get(model))
        recorder = _PlanRecorder(scene_mpc(env, exported, settings))
        run_episode(env, recorder, config.duration_s, start.reset_options, seed=start.seed, latency="none")
        goal, period = tuple(env.unwrapped.goal), float(env.unwrapped.dt)
    finally:
        env.close()
    ops = get_ops("numpy")

    def from_upright(state: np.ndarray) -> float:
        return float(s3.geodesic_angle(goal, tuple(state[:4]), ops))

    return [{"cell": cell, "start": start_index, "t_s": k * period, "angle_from_upright_rad": from_upright(x),
             "omega": float(np.linalg.norm(x[4:7])), "u": float(u[0]),
             "plan_closest_rad": min(from_upright(state) for state in plan)}
            for k, (x, u, plan) in enumerate(recorder.calls)]


class _PlanRecorder:
    """Passes calls to ``controller`` and keeps each call's state, control and planned states."""

    def __init__(self, controller: Any) -> None:
        self.controller, self.calls = controller, []

    def reset(self) -> None:
        self.controller.reset()
        self.calls = []

    def __call__(self, x: Any) -> tuple[np.ndarray, dict[str, Any]]:
        u, info = self.controller(x)
        self.calls.append((np.asarray(x, float), np.asarray(u, float), np.asarray(info["states"], float)))
        return u, info


def plot_trace(figure: Any, rows: list[dict[str, Any]]) -> None:
    """Angle from upright (solid) and the plan's predicted closest approach (dashed) against time."""
    figure.set_size_inches(11, 4.2)
    angle_axis, torque_axis = figure.subplots(1, 2)
    for key in dict.fromkeys((r["cell"], r["start"]) for r in rows):
        mine = [r for r in rows if (r["cell"], r["start"]) == key]
        t = [r["t_s"] for r in mine]
        line = angle_axis.plot(t, [r["angle_from_upright_rad"] for r in mine], label=f"{key[0]}, start {key[1]}")[0]
        angle_axis.plot(t, [r["plan_closest_rad"] for r in mine], ls="--", color=line.get_color())
        torque_axis.plot(t, [r["u"] for r in mine], color=line.get_color(), label=f"{key[0]}, start {key[1]}")
    angle_axis.set(xlabel="t (s)", ylabel="angle from upright (rad)",
                   title="measured (solid) and the plan's closest approach (dashed)")
    torque_axis.set(xlabel="t (s)", ylabel="u (applied)", title="torque")
    for axis in (angle_axis, torque_axis):
        axis.grid(alpha=0.3)
        axis.legend(fontsize=7)


def plot(figure: Any, rows: list[dict[str, Any]]) -> None:
    """Success against the potential's error on the other hemisphere, and against the validation loss."""
    figure.set_size_inches(11, 4.2)
    axes = figure.subplots(1, 2)
    for model in dict.fromkeys(r["model"] for r in rows):
        mine = [r for r in rows if r["model"] == model]
        success = [100 * r["success_rate"] for r in mine]
        axes[0].scatter([max(r["potential_err_minus_q"], 1e-4) for r in mine], success, label=model, alpha=0.7)
        axes[1].scatter([r["validation_loss"] for r in mine], success, label=model, alpha=0.7)
    axes[0].set(xscale="log", xlabel="max |U/λ − U| at −q (fraction of the energy span)",
                ylabel="closed-loop success (%)", title="the other hemisphere's potential")
    axes[1].set(xscale="log", xlabel="final validation loss", ylabel="closed-loop success (%)",
                title="training outcome")
    for axis in axes:
        axis.grid(alpha=0.3, which="both")
        axis.legend(fontsize=7)


COLUMNS = ("model", "transitions", "draw", "success", "cost_excess_pct", "costly_starts", "potential_err_q",
           "potential_err_minus_q", "inertia_err_q", "inertia_err_minus_q", "gain_err_q", "gain_err_minus_q",
           "other_hemisphere_share", "iterations", "validation_loss")


def run(quick: bool = False, seed: int = 0, repeats: int = 1, sizes: str = study.DEFAULT_SIZES, seeds: str = "0,1",
        models: str = ",".join(study.S3FVIN_VARIANTS), episodes: int = 10, v1_episodes: int = 10,
        cache_dir: Path = Path("data/data-efficiency"), pool: int | None = 20000, progress: bool = True,
        trace: str | None = None, **_: Any) -> StudyResult:
    """The table of :func:`term_rows`, or with ``trace`` the episodes it names (:func:`climb_trace`);
    ``repeats`` is unused: nothing here is timed."""
    config = study.study_config(quick, seed, sizes, seeds, models, episodes, v1_episodes, Path(cache_dir), "cached",
                                10.0, pool)
    if trace:
        rows = []
        for item in trace.split(","):
            cell, _, start = item.strip().rpartition(":")
            if not cell or not start.isdigit():
                raise ValueError(f"--trace wants CELL:START items (e.g. sign-invariant_n2000_r0:1), got {item!r}")
            rows += climb_trace(cell, int(start), config)
        return StudyResult(name="data-efficiency-trace", rows=rows, plot=plot_trace, columns=(
            "cell", "start", "t_s", "angle_from_upright_rad", "omega", "u", "plan_closest_rad"), notes=[(
            "Waiting latency mode (model quality). `plan_closest_rad`: the smallest angle from upright along the "
            "plan made at that period (its first state is the measured one).")])
    rows, missing = term_rows(config, progress)
    if not rows:
        raise ValueError(f"none of the cells is in {config.cache_dir}: run `python -m benchmarks data-efficiency` "
                         "with the same options first")
    notes = [(
        "Errors after fixing the scale λ on the w ≥ 0 hemisphere: `potential_err_*` as a fraction of the energy "
        "span, `inertia_err_*` and `gain_err_*` relative; `_q` on w ≥ 0, `_minus_q` at −q (the same rotations). "
        f"`costly_starts`: the starts costing more than {COSTLY_FACTOR:g}× the closed form's on the same start. "
        "`other_hemisphere_share`: the training states with w < 0."
    )]
    if missing:
        notes.append(f"Not in the cache (not analysed): {', '.join(missing)}.")
    return StudyResult(name="data-efficiency-terms", rows=rows, columns=COLUMNS, plot=plot, notes=notes)


def add_arguments(parser: Any) -> None:
    parser.add_argument("--sizes", default=study.DEFAULT_SIZES, help="training-set sizes (default: %(default)s)")
    parser.add_argument("--seeds", default="0,1", help="draws, comma-separated (default: %(default)s)")
    parser.add_argument("--models", default=",".join(study.S3FVIN_VARIANTS),
                        help="S3FVIN variants, comma-separated (default: %(default)s)")
    parser.add_argument(
        "--episodes",
        type=int,
        default=10,
        help="the data-efficiency run's closed-loop starts, which pick its cells (default: %(default)s)",
    )
    parser.add_argument("--v1-episodes", type=int, default=10,
                        help="the data-efficiency run's Pendulum-v1 seeds, which pick its cells (default: %(default)s)")
    parser.add_argument("--pool", type=int, default=20000, help="the data-efficiency run's pool (default: %(default)s)")
    parser.add_argument("--cache-dir", type=Path, default=Path("data/data-efficiency"),
                        help="the data-efficiency run's cache (default: %(default)s)")
    parser.add_argument("--trace", default=None,
                        help="CELL:START[,CELL:START...]: run these episodes again instead (e.g. "
                             "sign-invariant_n2000_r0:1,closed-form:1) and report, per period, the angle from upright, "
                             "the torque and the plan's predicted closest approach (data-efficiency-trace.*)")
