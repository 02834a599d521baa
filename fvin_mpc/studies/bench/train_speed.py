"""``train-speed``: seconds per training iteration on the reference workload.

The reference implementation (hanyang-hu/S3FVIN, sign-invariant variant) takes ≈ 1.5 s
per full-batch iteration on 3,520 rollout windows of 9 steps with hidden width 10 in
float64 on this kind of 2-core machine (``DESIGN.md``). We time the same workload —
forward rollout, loss, backward and an Adam step — eagerly and with the step compiled.

"At equal loss": both modes train on the real data (``data/pendulum.npz``) from the same
seed, and the study reports the wall clock each needs to reach a common validation loss
(``torch.compile``'s one-off cost included), plus the shipped checkpoint's own training
wall clock (``training.wall_clock_s`` in its JSON sidecar).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from fvin_mpc.studies.report import StudyResult, median_time

REFERENCE_SECONDS_PER_ITERATION = 1.5


def _equal_loss(seed: int, iterations: int, eval_every: int) -> list[dict[str, Any]]:
    """Train on ``data/pendulum.npz`` eagerly and compiled from the same seed, recording the wall
    clock at every validation; returns one row per mode with the time to reach a common loss.

    The loop is :func:`fvin_mpc.learning.training.train`'s (same split, windows, Adam, cosine schedule)."""
    import torch

    from fvin_mpc.learning.model import DTYPE, S3FVIN
    from fvin_mpc.core.networks import ModelConfig
    from fvin_mpc.learning.training import TrainSettings, rollout_loss, split_data
    from fvin_mpc.studies.bench.width import _training_data

    data = _training_data(seed)
    settings = TrainSettings(iterations=iterations, seed=seed)
    train_set, validation_set = split_data(data, settings.validation_fraction, seed)
    tensors = lambda arrays: tuple(torch.as_tensor(a, dtype=DTYPE) for a in arrays)  # noqa: E731
    train_windows = tensors(train_set.windows(settings.window))
    validation_windows = tensors(validation_set.windows(settings.window))
    curves = {}
    for mode in ("eager", "compiled"):
        torch.manual_seed(seed)
        config = ModelConfig(variant="sign-invariant", control_dim=data.u.shape[2], step_size=data.control_period)
        model = S3FVIN(config, seed=seed)
        step = torch.compile(model.step, dynamic=False) if mode == "compiled" else None
        optimizer = torch.optim.Adam(model.parameters(), lr=settings.learning_rate)
        schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, iterations, eta_min=0.05 * settings.learning_rate)
        curve, evaluation_s = [], 0.0
        start = time.perf_counter()
        for iteration in range(iterations):
            optimizer.zero_grad()
            rollout_loss(model, *train_windows, settings.omega_weight, step).backward()
            optimizer.step()
            schedule.step()
            if (iteration + 1) % eval_every == 0:
                pause = time.perf_counter()
                with torch.no_grad():
                    loss = rollout_loss(model, *validation_windows, settings.omega_weight).item()
                evaluation_s += time.perf_counter() - pause
                # Time spent training only (validation excluded), the same for both modes.
                curve.append((iteration + 1, time.perf_counter() - start - evaluation_s, loss))
        curves[mode] = curve
    # The common target: the loss the eager run reaches at two thirds of the budget.
    eager = curves["eager"]
    target = eager[max(0, (2 * len(eager)) // 3 - 1)][2]
    rows = []
    for mode, curve in curves.items():
        reached = next(((it, t) for it, t, loss in curve if loss <= target), (None, None))
        rows.append({"mode": mode, "variant": "sign-invariant", "windows": int(train_windows[0].shape[0]),
                     "steps": settings.window, "target_validation_loss": target, "iterations_to_target": reached[0],
                     "s_to_target": reached[1], "final_validation_loss": curve[-1][2], "part": "equal loss"})
    return rows


def run(quick: bool = False, seed: int = 0, repeats: int = 5, threads: int = 1, equal_loss: bool = True,
        equal_loss_iterations: int = 100, **_: Any) -> StudyResult:
    from fvin_mpc.learning.timing import torch_threads
    from fvin_mpc.studies.bench.common import NOISE_NOTE

    with torch_threads(threads):
        result = _run(quick, seed, repeats)
        if equal_loss and not quick:
            rows = _equal_loss(seed, equal_loss_iterations, 10)
            result.rows.extend(rows)
            eager, compiled = rows
            if eager["s_to_target"] and compiled["s_to_target"]:
                result.notes.append(
                    f"**At equal loss** (real data `data/pendulum.npz`, {eager['windows']} windows, sign-invariant, "
                    f"same seed): validation loss {eager['target_validation_loss']:.3g} is reached after "
                    f"{eager['s_to_target']:.1f} s eager ({eager['iterations_to_target']} iterations) and "
                    f"{compiled['s_to_target']:.1f} s compiled ({compiled['iterations_to_target']} iterations, "
                    "`torch.compile` included — but with inductor's on-disk cache warm from the per-iteration rows "
                    "above; a cold compile adds about `compile_s`, so from a cold start compiling pays off only once "
                    "the run is longer than that).")
            result.columns = list(result.columns) + ["target_validation_loss", "iterations_to_target", "s_to_target"]
    from fvin_mpc.studies.bench.common import checkpoint_or_none

    shipped = checkpoint_or_none("pendulum_sign-invariant")
    if shipped is not None and "training" in shipped.metadata:
        training = shipped.metadata["training"]
        result.notes.append(
            f"The shipped `pendulum_sign-invariant` checkpoint trained in {training.get('wall_clock_s', float('nan')):.0f} s "
            f"({training.get('iterations')} iterations, compile = {training.get('settings', {}).get('compile')}; "
            "`training.wall_clock_s` of its JSON sidecar).")
    result.notes.append(f"torch ran with {threads} intra-op thread(s). " + NOISE_NOTE)
    return result


def _run(quick: bool, seed: int, repeats: int) -> StudyResult:
    import torch

    from fvin_mpc.learning.model import DTYPE, S3FVIN
    from fvin_mpc.core.networks import ModelConfig
    from fvin_mpc.learning.training import rollout_loss

    torch.manual_seed(seed)
    windows, steps = (352, 9) if quick else (3520, 9)
    repeats = 2 if quick else repeats
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(windows, steps + 1, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    batch = tuple(torch.as_tensor(a, dtype=DTYPE) for a in (q, rng.normal(size=(windows, steps + 1, 3)),
                                                          rng.uniform(-2, 2, size=(windows, steps, 1))))
    rows = []
    modes = ["eager"] if quick else ["eager", "compiled"]
    for mode in modes:
        for variant in ("sign-invariant", "fixed-inertia"):
            model = S3FVIN(ModelConfig(variant=variant, hidden_width=10), seed=seed)
            optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
            step = None
            compile_s = 0.0
            if mode == "compiled":
                step = torch.compile(model.step, dynamic=False)

            def iteration() -> None:
                optimizer.zero_grad()
                rollout_loss(model, *batch, 0.1, step).backward()
                optimizer.step()

            if mode == "compiled":
                start = time.perf_counter()
                iteration()  # triggers compilation of forward and backward
                compile_s = time.perf_counter() - start
            median, p95 = median_time(iteration, repeats)
            rows.append({"part": "per iteration", "mode": mode, "variant": variant, "windows": windows, "steps": steps,
                         "s_per_iter_median": median, "s_per_iter_p95": p95, "compile_s": compile_s,
                         # Only the full workload is comparable with the reference figure.
                         "speedup_vs_reference": None if quick else REFERENCE_SECONDS_PER_ITERATION / median})

    def plot(figure: Any, rows: list[dict[str, Any]]) -> None:
        axis = figure.add_subplot()
        rows = [r for r in rows if r.get("part") == "per iteration"]
        labels = [f"{r['mode']}\n{r['variant']}" for r in rows]
        axis.bar(labels, [r["s_per_iter_median"] for r in rows], color="tab:blue")
        axis.axhline(REFERENCE_SECONDS_PER_ITERATION, color="tab:red", ls="--", label="reference (DESIGN.md)")
        axis.axhline(REFERENCE_SECONDS_PER_ITERATION / 10, color="tab:green", ls=":", label="10× target")
        axis.set_yscale("log")
        axis.set_ylabel("s / iteration (median)")
        axis.legend()

    notes = [f"Workload: {windows} windows × {steps} steps, hidden width 10, float64, K = 2, full batch; "
             f"reference ≈ {REFERENCE_SECONDS_PER_ITERATION} s/iteration (DESIGN.md, measured on this machine kind). "
             "`compile_s` is the one-off cost of `torch.compile` on the first iteration."]
    return StudyResult("train-speed", rows, ["part", "mode", "variant", "windows", "s_per_iter_median", "s_per_iter_p95",
                                             "compile_s", "speedup_vs_reference"], plot, notes)


def add_arguments(parser: Any) -> None:
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default: %(default)s)")
    parser.add_argument("--no-equal-loss", dest="equal_loss", action="store_false",
                        help="skip the time-to-equal-loss comparison on real data")
    parser.add_argument("--equal-loss-iterations", type=int, default=100,
                        help="training iterations per mode in the equal-loss comparison (default: %(default)s)")
