"""Training sweep: a grid of models trained as one job (the library behind ``python -m fvin_mpc.sweep``).

The grid is variants × hidden widths × data sizes × training seeds. Each run trains an S3FVIN with
:func:`fvin_mpc.learning.training.train` on the first ``n`` trajectories of a seeded permutation of
the data (the same subset for every variant, width and training seed), one torch thread per run,
no progress bar of its own; the runs go through :func:`fvin_mpc.studies.pool.run_tasks` (serial,
process pool or Ray actors), each worker receiving the data once. A run sends back its weights
and training report; this process writes every checkpoint
``<out-dir>/<scene stem>_<variant>_w<width>_n<trajectories>_s<seed>.{safetensors,json}``
(sidecar: variant, data, seed, training report, the sweep's grid entry) and one table,
``<out-dir>/sweep.md`` and ``sweep.json``: per run the final training and validation losses,
iterations, why it stopped and its wall clock; per configuration the mean and spread over seeds.
A run that fails is listed with its error; the others are written all the same.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fvin_mpc.core.checkpoint import save_checkpoint
from fvin_mpc.core.data import load_data
from fvin_mpc.core.networks import VARIANTS, ModelConfig
from fvin_mpc.learning.space_training import check_training_data
from fvin_mpc.learning.training import TrainSettings, package_versions, scene_has_joint_damping, scene_stem, train
from fvin_mpc.studies.pool import TasksFailed, run_tasks
from fvin_mpc.studies.report import json_text

#: Keys of :class:`~fvin_mpc.learning.training.TrainSettings` a sweep may set for all its runs.
TRAIN_OPTIONS: tuple[str, ...] = ("optimizer", "iterations", "patience", "window", "omega_weight", "learning_rate",
                                  "time_limit_s", "eval_every")


@dataclass(frozen=True)
class SweepConfig:
    """What to train.

    Attributes:
        data: trajectory file (``python -m fvin_mpc.collect``).
        variants: model variants (:data:`fvin_mpc.core.networks.VARIANTS`).
        widths: hidden widths.
        seeds: training seeds (initialization, validation split, LM samples).
        sizes: trajectories per run (``None``: all of the file).
        subset_seed: seeds which trajectories each size takes.
        hidden_layers: hidden layers per MLP.
        dissipation: learn a damping term; ``None``: when the data's scene declares joint damping.
        train: :class:`~fvin_mpc.learning.training.TrainSettings` fields (:data:`TRAIN_OPTIONS`)
            for every run, as ``(name, value)`` pairs; ``threads`` is always 1, ``seed`` the run's.
    """

    data: str
    variants: tuple[str, ...] = ("sign-invariant",)
    widths: tuple[int, ...] = (16,)
    seeds: tuple[int, ...] = (0,)
    sizes: tuple[int | None, ...] = (None,)
    subset_seed: int = 0
    hidden_layers: int = 2
    dissipation: bool | None = None
    train: tuple[tuple[str, Any], ...] = ()

    def __post_init__(self) -> None:
        unknown = [v for v in self.variants if v not in VARIANTS]
        if unknown or not self.variants:
            raise ValueError(f"unknown variants {unknown}; choose from {', '.join(VARIANTS)}")
        if not self.widths or min(self.widths) < 1:
            raise ValueError(f"widths must be >= 1, got {self.widths}")
        if not self.seeds or not self.sizes:
            raise ValueError("the grid needs at least one seed and one data size")
        if any(size is not None and size < 2 for size in self.sizes):
            raise ValueError(f"data sizes must be >= 2 trajectories (one is held out), got {self.sizes}")
        bad = [name for name, _ in self.train if name not in TRAIN_OPTIONS]
        if bad:
            raise ValueError(f"unknown training options {bad}; a sweep sets {', '.join(TRAIN_OPTIONS)}")
        TrainSettings(**dict(self.train))  # validates the values now, not in a worker

    def runs(self) -> list[tuple[str, int, int | None, int]]:
        """The grid, one ``(variant, width, size, seed)`` per run, seeds innermost."""
        return [(variant, width, size, seed) for variant in self.variants for width in self.widths
                for size in self.sizes for seed in self.seeds]


@dataclass
class SweepResult:
    """Per run: grid entry, losses, wall clock, checkpoint (or error); ``wall_clock_s`` the whole job's."""

    config: SweepConfig
    runs: list[dict[str, Any]]
    wall_clock_s: float
    backend: str = "process"
    workers: int = 1
    failures: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"config": asdict(self.config), "backend": self.backend, "workers": self.workers,
                "wall_clock_s": self.wall_clock_s, "runs": self.runs, "failures": self.failures,
                "summary": summarize(self.runs)}


# ---------------------------------------------------------------------- one run (in a worker)
_WORKER: dict[str, Any] = {}


def _init_worker(data: Any, config: SweepConfig, model_base: dict[str, Any]) -> None:
    _WORKER.clear()
    _WORKER.update(data=data, config=config, model_base=model_base)


def subset(data: Any, size: int | None, seed: int) -> Any:
    """The first ``size`` trajectories of a ``seed``-ed permutation, in file order (all for ``None``)."""
    if size is None or size >= data.num_trajectories:
        return data
    order = np.random.default_rng(seed).permutation(data.num_trajectories)
    return data.subset(np.sort(order[:size]))


def train_run(variant: str, width: int, size: int | None, seed: int) -> dict[str, Any]:
    """Train one grid entry in this worker (one torch thread); weights and report."""

    config: SweepConfig = _WORKER["config"]
    data = subset(_WORKER["data"], size, config.subset_seed)
    model_config = ModelConfig(variant=variant, hidden_width=width, **_WORKER["model_base"])
    settings = TrainSettings(**dict(config.train), seed=seed, threads=1)
    start = time.perf_counter()
    model, report = train(data, model_config, settings, progress=False)
    return {"weights": model.numpy_weights(), "report": report, "model": model_config.to_dict(),
            "trajectories": data.num_trajectories, "transitions": data.num_transitions,
            "task_s": time.perf_counter() - start}


# ---------------------------------------------------------------------- the sweep
def checkpoint_stem(out_dir: Path, scene: str, variant: str, width: int, trajectories: int, seed: int) -> Path:
    return Path(out_dir) / f"{scene_stem(scene)}_{variant}_w{width}_n{trajectories}_s{seed}"


def run_sweep(config: SweepConfig, out_dir: Path, workers: int = 1, progress: bool = True, backend: str = "process",
              address: str | None = None) -> SweepResult:
    """Train every run of ``config``, write the checkpoints under ``out_dir``; failed runs are in
    :attr:`SweepResult.failures` and their rows carry the error (the others are written)."""

    data = load_data(config.data)
    check_training_data(data, None)
    sizes = [size for size in config.sizes if size is not None]
    if sizes and max(sizes) > data.num_trajectories:
        raise ValueError(f"{config.data} has {data.num_trajectories} trajectories, a run asks for {max(sizes)}")
    dissipation = config.dissipation
    if dissipation is None:
        dissipation = bool(scene_has_joint_damping(data.metadata))
    model_base = {"control_dim": int(data.u.shape[2]), "hidden_layers": config.hidden_layers,
                  "step_size": data.control_period, "dissipation": dissipation}
    runs = config.runs()
    start = time.perf_counter()
    failures: list[str] = []
    errors: dict[int, str] = {}
    try:
        results = run_tasks(train_run, runs, _init_worker, (data, config, model_base), workers, progress,
                            "training runs", backend=backend, address=address)
    except TasksFailed as error:
        results = error.results
        failures = [failure.describe() for failure in error.failures]
        errors = {failure.index: failure.error for failure in error.failures}
    wall = time.perf_counter() - start
    scene = data.metadata.get("scene", "unknown")
    versions = package_versions()
    rows = []
    for i, ((variant, width, size, seed), result) in enumerate(zip(runs, results)):
        row: dict[str, Any] = {"variant": variant, "width": width, "size": size, "seed": seed}
        if result is None:
            row.update(status="failed", error=errors[i])
            rows.append(row)
            continue
        report = result["report"]
        stem = save_checkpoint(
            checkpoint_stem(out_dir, scene, variant, width, result["trajectories"], seed),
            ModelConfig.from_dict(result["model"]), result["weights"], scene=scene, body=data.metadata.get("body"),
            data={"path": str(config.data), "trajectories": result["trajectories"],
                  "transitions": result["transitions"], "subset_seed": config.subset_seed,
                  "seed": data.metadata.get("seed"), "control_period": data.control_period},
            training=report, versions=versions,
            sweep={"variant": variant, "width": width, "size": size, "seed": seed, "backend": backend},
        )
        row.update(status="ok", trajectories=result["trajectories"], iterations=report["iterations"],
                   stopped=report["stopped"], final_train_loss=report["final_train_loss"],
                   final_validation_loss=report["final_validation_loss"], wall_clock_s=report["wall_clock_s"],
                   task_s=result["task_s"], checkpoint=str(stem))
        rows.append(row)
    return SweepResult(config, rows, wall, backend, workers, failures)


def summarize(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (variant, width, size): runs, validation loss mean / min / max over seeds, mean wall clock."""
    groups: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault((row["variant"], row["width"], row["size"]), []).append(row)
    summary = []
    for (variant, width, size), members in groups.items():
        ok = [r for r in members if r["status"] == "ok"]
        losses = np.array([r["final_validation_loss"] for r in ok], dtype=float)
        summary.append({
            "variant": variant, "width": width, "size": size, "runs": len(members), "ok": len(ok),
            "validation_loss_mean": float(losses.mean()) if ok else None,
            "validation_loss_min": float(losses.min()) if ok else None,
            "validation_loss_max": float(losses.max()) if ok else None,
            "wall_clock_s_mean": float(np.mean([r["wall_clock_s"] for r in ok])) if ok else None,
        })
    return summary


def _fmt(value: Any, spec: str = ".3g") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    return format(value, spec) if isinstance(value, float) else str(value)


def sweep_table(result: SweepResult) -> str:
    """Markdown: one row per run, then one per configuration (over seeds)."""
    lines = ["| variant | width | trajectories | seed | iterations | stopped | train loss | validation loss "
             "| wall clock (s) | checkpoint |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in result.runs:
        if r["status"] != "ok":
            lines.append(f"| {r['variant']} | {r['width']} | {_fmt(r['size'])} | {r['seed']} | — | **failed**: "
                         f"{r['error'][:120]} | — | — | — | — |")
            continue
        lines.append(f"| {r['variant']} | {r['width']} | {r['trajectories']} | {r['seed']} | {r['iterations']} "
                     f"| {r['stopped']} | {_fmt(r['final_train_loss'])} | {_fmt(r['final_validation_loss'])} "
                     f"| {r['wall_clock_s']:.1f} | `{Path(r['checkpoint']).name}` |")
    lines += [
        "",
        "| variant | width | trajectories | runs ok | validation loss mean | min | max | wall clock mean (s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for s in summarize(result.runs):
        lines.append(f"| {s['variant']} | {s['width']} | {_fmt(s['size']) if s['size'] else 'all'} "
                     f"| {s['ok']}/{s['runs']} | {_fmt(s['validation_loss_mean'])} | {_fmt(s['validation_loss_min'])} "
                     f"| {_fmt(s['validation_loss_max'])} | {_fmt(s['wall_clock_s_mean'], '.1f')} |")
    return "\n".join(lines)


def write_report(result: SweepResult, out_dir: Path, command: str) -> list[Path]:
    """``sweep.md`` and ``sweep.json`` in ``out_dir``; returns their paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    md, js = out_dir / "sweep.md", out_dir / "sweep.json"
    js.write_text(json_text(result.to_json(), indent=1) + "\n")
    settings = ", ".join(f"{k} = {v}" for k, v in result.config.train) or "the defaults"
    failed = "".join(f"\n- {line}" for line in result.failures)
    md.write_text(f"""# Training sweep: `{result.config.data}`

Produced by `{command}`

{len(result.runs)} runs ({result.backend} backend, {result.workers} workers, one torch thread each) in
{result.wall_clock_s:.1f} s wall clock; training settings: {settings}. Losses are the final ones of the
best (early-stopped) weights; wall clock is each run's training loop.{failed}

{sweep_table(result)}
""")
    return [md, js]
