"""``width``: network width and variant — held-out rollout error vs MPC solve time vs training time.

Models of hidden width 8, 16, 32, 64 (two hidden layers) in the ``sign-invariant`` and
``fixed-inertia`` variants are trained briefly (``--iterations``, eager torch, full batch on
``--train-trajectories`` trajectories of ``data/pendulum.npz``, which is collected if missing)
and evaluated by their open-loop rollout error on the held-out data
(``data/pendulum_heldout.npz``) and by the MPC's solve time in a swing-up from rest.

Trained models are cached under ``<cache>/bench-width/`` (``$FVIN_MPC_CACHE`` or
``~/.cache/fvin_mpc``), keyed by everything that defines the training, so reruns skip
training; the training-time columns always come from the real run that produced the cached
model (its ``training.wall_clock_s``), and ``trained_now`` says whether that run was this one.
"""

from __future__ import annotations

import hashlib
import json
import sys
from dataclasses import replace
from typing import Any

import numpy as np

from benchmarks.common import NOISE_NOTE, heldout_data, make_env, plot_pareto, solve_stats
from benchmarks.study import StudyResult
from fvin_mpc.control.model_export import cache_dir, from_checkpoint
from fvin_mpc.control.mpc import MPCSettings
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.checkpoint import load_checkpoint, save_checkpoint
from fvin_mpc.core.data import load_data, save_data
from fvin_mpc.core.networks import LearnedTerms, ModelConfig
from fvin_mpc.learning.collection import collect
from fvin_mpc.learning.timing import torch_threads
from fvin_mpc.learning.training import TrainSettings, train
from fvin_mpc.studies.model_quality import rollout
from fvin_mpc.studies.pool import run_tasks

WIDTHS = (8, 16, 32, 64)
#: ``run`` takes ``workers``, ``backend`` and ``ray_address``: its rows go through
#: :func:`fvin_mpc.studies.pool.run_tasks` (``python -m benchmarks`` adds the options).
PARALLEL_ROWS = True
VARIANTS = ("sign-invariant", "fixed-inertia")


def _training_data(seed: int) -> Any:
    from pathlib import Path

    path = Path("data/pendulum.npz")
    if path.is_file():
        return load_data(path)
    print(f"collecting training data {path} (python -m fvin_mpc.collect, seed 0)", file=sys.stderr)
    data = collect("pendulum", progress=False)
    save_data(path, data)
    return data


def _trained(data: Any, variant: str, width: int, iterations: int, seed: int, progress: bool) -> tuple[Any, bool]:
    """A checkpoint trained with these settings: from the cache, or trained now and cached."""

    config = ModelConfig(variant=variant, control_dim=data.u.shape[2], hidden_width=width,
                         step_size=data.control_period)
    settings = TrainSettings(iterations=iterations, seed=seed, eval_every=max(1, iterations // 4), compile=False)
    digest = hashlib.sha256(
        json.dumps([config.to_dict(), settings.__dict__]).encode()
        + np.ascontiguousarray(data.q).tobytes()
        + np.ascontiguousarray(data.u).tobytes()
    ).hexdigest()[:16]
    stem = cache_dir() / "bench-width" / f"pendulum_w{width}_{variant}_{digest}"
    if stem.with_suffix(".json").is_file() and stem.with_suffix(".safetensors").is_file():
        return load_checkpoint(stem), False
    with torch_threads(1):
        model, report = train(data, config, settings, progress=progress)
    save_checkpoint(stem, config, model.numpy_weights(), scene="pendulum", training=report)
    return load_checkpoint(stem), True


_WORKER: dict[str, Any] = {}


def _init_worker(
    data: Any, heldout: Any, iterations: int, seed: int, horizon: int, duration: float, quick: bool
) -> None:
    _WORKER.clear()
    _WORKER.update(data=data, heldout=heldout, iterations=iterations, seed=seed, horizon=horizon, duration=duration,
                   quick=quick, env=make_env("pendulum"))


def width_row(variant: str, width: int) -> dict[str, Any]:
    """One row (in the current worker): the model trained (or from the cache), its held-out rollout
    error and its MPC's swing-up; ``compile_failure`` says if the MPC fell back to interpreted."""

    w = _WORKER
    heldout, quick, seed = w["heldout"], w["quick"], w["seed"]
    checkpoint, trained_now = _trained(w["data"], variant, width, w["iterations"], seed, progress=False)
    training = checkpoint.metadata["training"]
    terms = LearnedTerms(checkpoint.weights, checkpoint.config, get_ops("numpy"))
    q_hat, _, _ = rollout(terms, checkpoint.config.step_size, checkpoint.config.newton_iters,
                          heldout.q[:, 0], heldout.omega[:, 0], heldout.u)
    d = np.clip(np.abs((q_hat * heldout.q).sum(-1)), 0.0, 1.0)
    angle = 2.0 * np.arctan2(np.sqrt(np.maximum(0.0, 1.0 - d * d)), d)
    exported = from_checkpoint(checkpoint)
    settings = replace(MPCSettings(), horizon=w["horizon"], compile="none" if quick else "cached")
    compile_failure = None
    try:
        metrics = solve_stats(w["env"], exported, settings, w["duration"], seed=seed)
    except RuntimeError as error:  # the C compiler gave up (seen: gcc segfault at width 64)
        first_line = str(error).splitlines()[0][:160]
        compile_failure = f"{variant} width {width}: {first_line}"
        settings = replace(settings, compile="none")
        metrics = solve_stats(w["env"], exported, settings, w["duration"], seed=seed)
    return {
        "variant": variant, "width": width, "parameters": int(sum(np.size(v) for v in checkpoint.weights.values())),
        "rollout_angle_final_mean": float(angle[:, -1].mean()), "rollout_angle_mean": float(angle.mean()),
        "validation_loss": training["final_validation_loss"],
        "train_s": training["wall_clock_s"], "train_s_per_iter": training["seconds_per_iteration"],
        "trained_now": trained_now,
        "mpc_ms_median": metrics["solver_ms_median"], "mpc_ms_p95": metrics["solver_ms_p95"],
        "iterations_mean": metrics["iterations_mean"], "success": metrics["success"],
        "time_to_upright_s": metrics["time_to_upright_s"], "mpc_build_s": metrics["build_s"],
        "label": f"{variant[:4]} w{width}", "mpc_compile": settings.compile, "compile_failure": compile_failure,
    }


def run(quick: bool = False, seed: int = 0, repeats: int = 5, iterations: int = 200, train_trajectories: int = 32,
        horizon: int = 30, duration: float = 4.0, widths: str = ",".join(map(str, WIDTHS)), workers: int = 1,
        backend: str = "process", ray_address: str | None = None, **_: Any) -> StudyResult:

    width_list = [4] if quick else [int(w) for w in widths.split(",")]
    variants = ("fixed-inertia",) if quick else VARIANTS
    if quick:
        iterations, train_trajectories, horizon, duration = 3, 8, 10, 1.0
    if quick:

        full = collect("pendulum", train_trajectories, 20, seed, progress=False)
    else:
        full = _training_data(seed)
    data = full.subset(np.sort(np.random.default_rng(seed).permutation(full.num_trajectories)[:train_trajectories]))
    if quick:

        heldout = collect("pendulum", 8, 10, 1, progress=False)
    else:
        heldout = heldout_data("pendulum", seed=1)
    # Rows are independent (each trains, rolls out and swings up its own model): they go through the
    # one execution backend, serially by default (``--workers``/``--backend`` to spread them).
    rows = run_tasks(width_row, [(variant, width) for variant in variants for width in width_list], _init_worker,
                     (data, heldout, iterations, seed, horizon, duration, quick), workers, not quick, "width study",
                     backend=backend, address=ray_address)
    compile_failures = [row.pop("compile_failure") for row in rows]
    compile_failures = [failure for failure in compile_failures if failure]
    if "env" in _WORKER:  # ran in this process
        _WORKER.pop("env").close()
    notes = [
        f"Training: {iterations} full-batch Adam iterations (eager torch, one thread, no `torch.compile`: its ≈ 75 s "
        f"of "
        f"compilation per model would exceed the training itself), window 8, on {train_trajectories} trajectories of "
        f"`data/pendulum.npz` (seed {seed}); short on purpose, so the errors are those of briefly trained models. "
        "`train_s` is the wall clock of the real training run (from the cached checkpoint's `training.wall_clock_s`; "
        "`trained_now` = False means an earlier run of this study trained it, on this kind of machine).",
        f"Rollout error: mean geodesic angle at the end of the {heldout.u.shape[1]}-step open-loop rollout "
        f"({heldout.u.shape[1] * 0.05:g} s) on {heldout.q.shape[0]} held-out MuJoCo trajectories. MPC: IPOPT, "
        f"Gauss–Newton, {'interpreted' if quick else 'compiled (cached)'}, primal–dual warm start, N = {horizon}, "
        f"swing-up from rest for {duration:g} s; `mpc_build_s` includes gcc on the first run.",
        NOISE_NOTE,
    ]
    if workers > 1:
        notes.insert(
            2,
            f"Rows ran concurrently on {workers} workers ({backend} backend): each row's timings (training, "
            "MPC solves) include the contention of the others; compare them with a `--workers 1` run "
            "only as ratios.",
        )
    if compile_failures:
        notes.insert(2, "**Compiling the MPC's functions failed** for " + "; ".join(compile_failures)
                     + " — that row's MPC ran interpreted (`mpc_compile` = none), so its solve time is not comparable "
                       "with the compiled rows (interpreted is ≈ 8× slower in the `solver` study).")

    def plot(figure: Any, rows_: list[dict[str, Any]]) -> None:
        left, right = figure.subplots(1, 2)
        plot_pareto(left, rows_, "mpc_ms_median", "rollout_angle_final_mean", "label", "MPC solve time, median (ms)",
                    "held-out rollout angle error (rad)", group="variant")
        plot_pareto(right, rows_, "train_s", "rollout_angle_final_mean", "label", "training wall clock (s)",
                    "held-out rollout angle error (rad)", group="variant")
        figure.suptitle("Network width and variant", fontsize=10)

    return StudyResult("width", rows,
                       ["variant", "width", "parameters", "rollout_angle_final_mean", "validation_loss", "train_s",
                        "train_s_per_iter", "trained_now", "mpc_compile", "mpc_ms_median", "mpc_ms_p95",
                        "iterations_mean", "success", "time_to_upright_s", "mpc_build_s"], plot, notes)


def add_arguments(parser: Any) -> None:
    parser.add_argument(
        "--iterations", type=int, default=200, help="training iterations per model (default: %(default)s)"
    )
    parser.add_argument("--train-trajectories", type=int, default=32,
                        help="trajectories of data/pendulum.npz used for training (default: %(default)s)")
    parser.add_argument("--horizon", type=int, default=30, help="MPC horizon N (default: %(default)s)")
    parser.add_argument("--duration", type=float, default=4.0, help="closed-loop seconds (default: %(default)s)")
    parser.add_argument("--widths", default=",".join(map(str, WIDTHS)), help="hidden widths (default: %(default)s)")
