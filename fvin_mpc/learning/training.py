"""Train an S3FVIN on trajectory data: ``python -m fvin_mpc.train``.

Loss: multi-step rollout over windows of ``--window`` steps, the sign-invariant
orientation error ``4(1 − ⟨q̂, q⟩²)`` (≈ squared angle error in rad²) plus
``--omega-weight``·‖ω̂ − ω‖², averaged over windows and steps. Full-batch Adam;
trajectories are split into train/validation sets before windowing.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fvin_mpc.core.data import TrajectoryData
from fvin_mpc.core.networks import ModelConfig

DEFAULT_DATA = Path("data/pendulum.npz")


@dataclass(frozen=True)
class TrainSettings:
    """Optimization settings.

    Attributes:
        iterations: full-batch Adam steps.
        learning_rate: initial Adam learning rate (cosine-decayed to 5 % of it).
        window: rollout length in steps of every training window.
        omega_weight: weight of ‖ω̂ − ω‖² against the orientation error.
        validation_fraction: share of trajectories held out.
        seed: seeds the initialization and the split.
        eval_every: iterations between validation evaluations.
        compile: ``torch.compile`` the step (≈ 75 s of compilation once, then ≈ 3× faster
            iterations; see ``docs/training.md``).
    """

    iterations: int = 1500
    learning_rate: float = 1e-2
    window: int = 8
    omega_weight: float = 0.1
    validation_fraction: float = 0.1
    seed: int = 0
    eval_every: int = 50
    compile: bool = False


def rollout_loss(model: Any, q: Any, omega: Any, u: Any, omega_weight: float, step: Any = None) -> Any:
    """Mean multi-step loss of ``model`` on windows ``q (W, T+1, 4)``, ``ω (W, T+1, 3)``, ``u (W, T, m)``.

    ``step`` replaces ``model.step`` (e.g. by a compiled version of it)."""
    q_hat, omega_hat = model.rollout(q[:, 0], omega[:, 0], u, step=step)
    alignment = (q_hat[:, 1:] * q[:, 1:]).sum(-1)
    orientation = 4.0 * (1.0 - alignment**2)
    velocity = ((omega_hat[:, 1:] - omega[:, 1:]) ** 2).sum(-1)
    return orientation.mean() + omega_weight * velocity.mean()


def split_data(data: TrajectoryData, validation_fraction: float, seed: int) -> tuple[TrajectoryData, TrajectoryData]:
    order = np.random.default_rng(seed).permutation(data.num_trajectories)
    n_val = max(1, int(round(validation_fraction * data.num_trajectories)))
    return data.subset(np.sort(order[n_val:])), data.subset(np.sort(order[:n_val]))


def train(data: TrajectoryData, config: ModelConfig, settings: TrainSettings, progress: bool = True) -> tuple[Any, dict[str, Any]]:
    """Train a model; returns ``(model, report)`` with losses and timings."""
    import torch
    from tqdm.auto import tqdm

    from fvin_mpc.learning.model import DTYPE, S3FVIN

    if abs(data.control_period - config.step_size) > 1e-12:
        raise ValueError(f"model step {config.step_size} differs from the data's control period {data.control_period}")
    if data.u.shape[2] != config.control_dim:
        raise ValueError(f"data has {data.u.shape[2]} controls, the model config {config.control_dim}")
    torch.manual_seed(settings.seed)
    train_set, validation_set = split_data(data, settings.validation_fraction, settings.seed)
    tensors = lambda arrays: tuple(torch.as_tensor(a, dtype=DTYPE) for a in arrays)  # noqa: E731
    train_windows = tensors(train_set.windows(settings.window))
    validation_windows = tensors(validation_set.windows(settings.window))

    model = S3FVIN(config, seed=settings.seed)
    # One step is compiled (not the whole rollout): compile time grows steeply with graph size.
    step = torch.compile(model.step, dynamic=False) if settings.compile else None
    optimizer = torch.optim.Adam(model.parameters(), lr=settings.learning_rate)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, settings.iterations, eta_min=0.05 * settings.learning_rate)
    history: list[dict[str, float]] = []
    validation_loss = float("nan")
    start = time.perf_counter()
    bar = tqdm(range(settings.iterations), desc=f"train {config.variant}", disable=not progress)
    for iteration in bar:
        optimizer.zero_grad()
        loss = rollout_loss(model, *train_windows, settings.omega_weight, step)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"training loss became {loss.item()} at iteration {iteration}")
        loss.backward()
        optimizer.step()
        schedule.step()
        if iteration % settings.eval_every == 0 or iteration == settings.iterations - 1:
            with torch.no_grad():
                validation_loss = rollout_loss(model, *validation_windows, settings.omega_weight).item()
            history.append({"iteration": iteration, "train": loss.item(), "validation": validation_loss})
        bar.set_postfix(train=f"{loss.item():.2e}", val=f"{validation_loss:.2e}")
    seconds = time.perf_counter() - start
    with torch.no_grad():
        final_train = rollout_loss(model, *train_windows, settings.omega_weight).item()
        final_validation = rollout_loss(model, *validation_windows, settings.omega_weight).item()
    report = {
        "iterations": settings.iterations,
        "settings": settings.__dict__,
        "train_windows": int(train_windows[0].shape[0]),
        "validation_windows": int(validation_windows[0].shape[0]),
        "final_train_loss": final_train,
        "final_validation_loss": final_validation,
        "wall_clock_s": seconds,
        "seconds_per_iteration": seconds / settings.iterations,
        "history": history,
    }
    return model, report


def package_versions() -> dict[str, str]:
    import importlib.metadata as md

    versions = {}
    for name in ("fvin_mpc", "torch", "numpy", "casadi", "mujoco", "gymnasium"):
        try:
            versions[name] = md.version(name)
        except md.PackageNotFoundError:
            versions[name] = "not installed"
    return versions
