"""``train-speed``: seconds per training iteration, and seconds to a shipped checkpoint's loss.

Two parts, one run:

- **per iteration** — the reference workload: the reference implementation
  (hanyang-hu/S3FVIN, sign-invariant) takes ≈ 1.5 s per full-batch iteration on 3,520 rollout
  windows of 9 steps with hidden width 10 in float64 on this kind of 2-core machine
  (``DESIGN.md``). We time the same workload (rollout, loss, backward, an Adam step), eagerly
  and with the step compiled (``--modes``).
- **to target** — time to a shipped validation loss from a fresh process: for each optimizer/
  execution mode (``--optimizers``), ``python -m fvin_mpc.train`` runs with its defaults
  (early stopping included) in a subprocess on (a) ``data/pendulum.npz``, target: the shipped
  ``pendulum_sign-invariant`` checkpoint's validation loss, and (b) 10,000 transitions of the
  ``pendulum_damped`` scene (``data/pendulum_damped_10k.npz``, collected here if absent) with
  learned dissipation, target: the shipped ``pendulum_damped_sign-invariant`` checkpoint's
  loss on that data's validation split. ``s_to_target`` counts from the subprocess's launch (interpreter start,
  imports, data, ``torch.compile`` included) to the first validation evaluation at or below
  the target; ``launch_to_exit_s`` to the checkpoint written and the process gone.

torch code lives in :mod:`fvin_mpc.learning.training`; this module only times it.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.common import checkpoint_or_none
from benchmarks.study import StudyResult, median_time
from fvin_mpc.core.data import load_data
from fvin_mpc.learning.timing import torch_threads
from fvin_mpc.learning.training import reference_iteration, split_losses

REFERENCE_SECONDS_PER_ITERATION = 1.5
DAMPED_DATA = Path("data/pendulum_damped_10k.npz")
#: optimizer/execution modes of the "to target" part: name → extra ``fvin_mpc.train`` arguments.
MODES: dict[str, list[str]] = {
    "lm": ["--optimizer", "lm"],
    "lbfgs": ["--optimizer", "lbfgs"],
    "adam": ["--optimizer", "adam"],
    "adam-compiled": ["--optimizer", "adam", "--compile"],
}


def _shipped_validation_loss(name: str, data: Path) -> float | None:
    """The shipped checkpoint ``name``'s validation loss on ``data``'s validation split (as
    ``fvin_mpc.train`` splits it with default settings); ``None`` without the checkpoint."""

    checkpoint = checkpoint_or_none(name)
    if checkpoint is None:
        return None
    return split_losses(checkpoint.weights, checkpoint.config, load_data(data))[1]


def _damped_data(seed: int) -> Path:
    """10,000 transitions (500 trajectories × 20 steps) of ``pendulum_damped``, collected once."""
    if not DAMPED_DATA.exists():
        subprocess.run([sys.executable, "-m", "fvin_mpc.collect", "--scene", "pendulum_damped", "--trajectories", "500",
                        "--steps", "20", "--seed", str(seed + 1), "--out", str(DAMPED_DATA), "--quiet"], check=True)
    return DAMPED_DATA


def _fresh_process(data: Path, mode: str, target: float, threads: int, seed: int, time_limit_s: float,
                   out_dir: Path) -> dict[str, Any]:
    """Run ``python -m fvin_mpc.train`` in a new interpreter; time it and read its report."""
    out = out_dir / f"{data.stem}_{mode}"
    command = [sys.executable, "-m", "fvin_mpc.train", "--data", str(data), "--out", str(out), "--quiet",
               "--threads", str(threads), "--seed", str(seed), "--time-limit", str(time_limit_s), *MODES[mode]]
    environment = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    load = os.getloadavg()[0]
    start = time.perf_counter()
    subprocess.run(command, check=True, env=environment, stdout=subprocess.DEVNULL)
    launch_to_exit = time.perf_counter() - start
    training = json.loads(out.with_suffix(".json").read_text())["training"]
    setup_s = launch_to_exit - training["wall_clock_s"]  # interpreter, imports, data, saving
    reached = next((h for h in training["history"] if h["validation"] <= target), None)
    # CPU seconds (this process's, all threads) — the figure to compare while the machine is loaded.
    process_cpu = training.get("process_cpu_to_train_end_s")
    setup_cpu = process_cpu - training["cpu_s"] if process_cpu is not None and "cpu_s" in training else None
    cpu_to_target = setup_cpu + reached["cpu_s"] if reached and setup_cpu is not None and "cpu_s" in reached else None
    return {"part": "to target", "data": data.name, "mode": mode, "windows": training["train_windows"],
            "target_validation_loss": target, "final_validation_loss": training["final_validation_loss"],
            "iterations": training["iterations"], "iterations_to_target": reached and reached["iteration"],
            "s_to_target": reached and setup_s + reached["elapsed_s"], "launch_to_exit_s": launch_to_exit,
            "cpu_s_to_target": cpu_to_target, "cpu_s_to_train_end": process_cpu,
            "stopped": training["stopped"], "threads": training["threads"], "load_1min": load}


def run(quick: bool = False, seed: int = 0, repeats: int = 5, threads: int = 1, modes: str = "eager,compiled",
        optimizers: str = ",".join(MODES), to_target: bool = True, time_limit: float = 600.0, **_: Any) -> StudyResult:

    with torch_threads(threads):
        result = _per_iteration(quick, seed, repeats, ["eager"] if quick else modes.split(","))
    if to_target and not quick:
        pendulum, damped = Path("data/pendulum.npz"), _damped_data(seed)
        targets = [(pendulum, _shipped_validation_loss("pendulum_sign-invariant", pendulum)),
                   (damped, _shipped_validation_loss("pendulum_damped_sign-invariant", damped))]
        jobs = [
            (data, target, mode) for data, target in targets if target is not None for mode in optimizers.split(",")
        ]
        from tqdm.auto import tqdm

        with tempfile.TemporaryDirectory() as scratch:
            for data, target, mode in tqdm(jobs, desc="train-speed: fresh processes"):
                result.rows.append(_fresh_process(data, mode, target, threads, seed, time_limit, Path(scratch)))
        result.columns = list(result.columns) + [
            "data",
            "target_validation_loss",
            "final_validation_loss",
            "iterations_to_target",
            "s_to_target",
            "launch_to_exit_s",
            "cpu_s_to_target",
            "cpu_s_to_train_end",
            "load_1min",
        ]
        result.notes.append(
            "**To target**: each row is one `python -m fvin_mpc.train --data <data> --optimizer <mode> --threads "
            f"{threads} --time-limit {time_limit:g}` in a fresh interpreter (defaults otherwise, early stopping on). "
            "`s_to_target`: launch → first validation loss ≤ the target, `torch.compile` included; empty if never "
            "reached. Target: the shipped checkpoint's loss on the same validation split (`pendulum_sign-invariant` "
            "for `pendulum.npz`: its own training data; `pendulum_damped_sign-invariant`, trained on 6,400 other "
            "transitions, for `pendulum_damped_10k.npz`). "
            "`launch_to_exit_s`: launch → checkpoint written. `cpu_s_to_target`, `cpu_s_to_train_end`: the "
            "training process's CPU seconds from its start to the target and to the end of training (what to "
            "compare on a loaded machine; wall clock ≈ CPU with one thread on an idle one). `load_1min`: the "
            "1-minute load average at launch.")
    result.notes.append(f"torch ran with {threads} intra-op thread(s); 1-minute load average at the end "
                        f"{os.getloadavg()[0]:.2f} on {os.cpu_count()} cores. "
                        "Timings are from a machine shared with other jobs: compare rows by ratios within this run.")
    return result


def _per_iteration(quick: bool, seed: int, repeats: int, modes: list[str]) -> StudyResult:
    windows, steps = (352, 9) if quick else (3520, 9)
    repeats = 2 if quick else repeats
    rows = []
    for mode in modes:
        for variant in ("sign-invariant", "fixed-inertia"):
            iteration, compile_s = reference_iteration(variant, windows, steps, compile=mode == "compiled", seed=seed)
            median, p95 = median_time(iteration, repeats)
            rows.append({"part": "per iteration", "mode": mode, "variant": variant, "windows": windows, "steps": steps,
                         "s_per_iter_median": median, "s_per_iter_p95": p95, "compile_s": compile_s,
                         # Only the full workload is comparable with the reference figure.
                         "speedup_vs_reference": None if quick else REFERENCE_SECONDS_PER_ITERATION / median})

    def plot(figure: Any, rows: list[dict[str, Any]]) -> None:
        per_iteration = [r for r in rows if r.get("part") == "per iteration"]
        to_target = [r for r in rows if r.get("part") == "to target"]
        left = figure.add_subplot(1, 2 if to_target else 1, 1)
        left.bar(
            [f"{r['mode']}\n{r['variant']}" for r in per_iteration],
            [r["s_per_iter_median"] for r in per_iteration],
            color="tab:blue",
        )
        left.axhline(REFERENCE_SECONDS_PER_ITERATION, color="tab:red", ls="--", label="reference (DESIGN.md)")
        left.set_yscale("log")
        left.set_ylabel("s / iteration (median)")
        left.set_title("reference workload, per iteration")
        left.legend()
        if to_target:
            right = figure.add_subplot(1, 2, 2)
            labels = [f"{r['mode']}\n{r['data'].removesuffix('.npz')}" for r in to_target]
            reached = [r["s_to_target"] if r["s_to_target"] is not None else r["launch_to_exit_s"] for r in to_target]
            colors = ["tab:green" if r["s_to_target"] is not None else "tab:gray" for r in to_target]
            right.barh(labels, reached, color=colors)
            right.set_xscale("log")
            right.set_xlabel("s from launch to the shipped validation loss (gray: not reached; bar = run length)")
            right.set_title("fresh process, to target")
        figure.set_size_inches(13, 5)
        figure.tight_layout()

    notes = [
        f"**Per iteration**: {windows} windows × {steps} steps, hidden width 10, float64, K = 2, full batch, one Adam "
        f"iteration; reference ≈ {REFERENCE_SECONDS_PER_ITERATION} s/iteration (DESIGN.md, measured on this machine "
        "kind). `compile_s` is the one-off cost of `torch.compile` on the first iteration."
    ]
    return StudyResult(
        "train-speed",
        rows,
        [
            "part",
            "mode",
            "variant",
            "windows",
            "s_per_iter_median",
            "s_per_iter_p95",
            "compile_s",
            "speedup_vs_reference",
        ],
        plot,
        notes,
    )


def add_arguments(parser: Any) -> None:
    parser.add_argument("--threads", type=int, default=1,
                        help="torch intra-op threads, here and in every training subprocess (default: %(default)s)")
    parser.add_argument("--modes", default="eager,compiled",
                        help="execution modes of the per-iteration part, comma-separated (default: %(default)s)")
    parser.add_argument("--optimizers", default=",".join(MODES),
                        help="optimizer/execution modes of the to-target part, comma-separated, from "
                             f"{', '.join(MODES)} (default: %(default)s)")
    parser.add_argument("--no-to-target", dest="to_target", action="store_false",
                        help="skip the time-to-target runs in fresh processes")
    parser.add_argument("--time-limit", type=float, default=600.0,
                        help="seconds of training per to-target run before it is stopped (default: %(default)s)")
