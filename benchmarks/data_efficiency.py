"""``data-efficiency``: how much data does control need? (docs/data-efficiency.md)

Models are trained on growing numbers of transitions (``--sizes``), several draws each
(``--seeds``), and every trained model is judged three ways:

- **held-out rollout error** — open-loop rollouts of 1 s (``TEST_STEPS`` periods) from the
  initial states of a test set collected with another seed, under its recorded controls; the
  geodesic angle error at the end (rad, mean over trajectories) and the 8-step rollout loss the
  training minimizes;
- **closed loop** — the scene's IPOPT MPC (the evaluation's controller: scene settings, terminal
  energy-deficit cost, multi-start cold solves) on the MuJoCo ``pendulum`` scene from the same
  starts for every model (:func:`fvin_mpc.studies.starts.episode_starts`: hanging at rest, then
  seeded random states, ``|ω₀| ≤ 2``), 10 s each; success and accumulated cost as
  :func:`fvin_mpc.control.closed_loop.episode_metrics` defines them;
- **Pendulum-v1** — the benchmark's MPC (:func:`benchmarks.pendulum_v1_mpc.benchmark_settings`)
  on ``gymnasium.make("Pendulum-v1")``, mean return over seeds ``0 … v1_episodes − 1``.

The closed-form model (the rod read off the MJCF, same step, same MPC) runs on the same starts:
costs are reported relative to it. Closed loops run in the *waiting* latency mode
(``latency="none"``): these are model-quality figures, not real-time ones.

Models: the S3FVIN variants (``sign-invariant``, ``fixed-inertia``, ``plain``) and ``mlp``, the
unstructured baseline of :mod:`benchmarks.mlp_baseline` (increment of ``(q, ω)``,
sign-equivariant, hidden width 16: 535 parameters against the S3FVIN's 590), trained by the same
loop on the same windows with the same settings. The MLP has no energy: its MPC's terminal
energy-deficit term uses the closed-form energy (privileged information that favours it).

Data: one pool of ``--pool`` transitions (default 20,000) in trajectories of 10 periods (seed
``--seed``; the package's collector and its defaults otherwise), collected once; the training set of
``n`` transitions for draw ``r`` is the
first ``n / steps`` *whole* trajectories of a permutation seeded by ``(seed, r)`` — whole
trajectories keep every window valid, and the sets of one draw are nested. Draw ``r`` also seeds
the training. Everything is cached per cell (model × size × draw) under ``--cache-dir``: a run
that is stopped resumes where it was. A run with other evaluation settings (``--episodes``,
``--v1-episodes``, ``--episode-budget``) caches its cells beside the others, never over them, and
evaluates the same trained models; ``--report-suffix`` writes its report beside the main one.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.mlp_baseline import MLPConfig, check_mlp_weights, load_mlp, mlp_step_function, save_mlp, train_mlp
from benchmarks.pendulum_v1_mpc import ZOO_BEST, benchmark_settings, run_v1_episode
from benchmarks.study import StudyResult
from fvin_mpc.control.closed_loop import episode_metrics, run_episode
from fvin_mpc.control.model_export import CA, NP, ExportedModel, energy_function, from_checkpoint
from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings
from fvin_mpc.core import s3
from fvin_mpc.core.checkpoint import save_checkpoint
from fvin_mpc.core.data import load_data, save_data
from fvin_mpc.core.networks import ModelConfig
from fvin_mpc.core.rigid_body import from_mujoco
from fvin_mpc.learning.collection import collect
from fvin_mpc.learning.training import TrainSettings, train
from fvin_mpc.studies.evaluation import DEFAULT_MAX_OMEGA
from fvin_mpc.studies.starts import episode_starts

S3FVIN_VARIANTS: tuple[str, ...] = ("sign-invariant", "fixed-inertia", "plain")
MLP = "mlp"
#: The same trained MLP under the MPC with the exact Lagrangian Hessian instead of the Gauss–Newton
#: one: IPOPT does not converge on the MLP with the Gauss–Newton Hessian (which leaves out the
#: dynamics' second derivatives — harmless for the S3FVIN's step, not for this network).
MLP_EXACT = "mlp-exact-hessian"
CLOSED_FORM = "closed-form"
MODELS: tuple[str, ...] = (*S3FVIN_VARIANTS, MLP, MLP_EXACT)
#: MPCSettings a model's MPCs get beyond the study's (both the scene's and the Pendulum-v1 one).
MODEL_MPC_OVERRIDES: dict[str, dict[str, Any]] = {MLP_EXACT: {"ipopt": {"hessian": "exact"}}}
DEFAULT_SIZES = "250,500,1000,2000,5000,10000,20000"
DEFAULT_MODELS = "sign-invariant,mlp"
#: Periods of the held-out rollouts (1 s at h = 0.05).
TEST_STEPS = 20
TEST_TRAJECTORIES = 100
#: The test set's collection seed is the study's seed plus this (a different stream from the pool's).
TEST_SEED_OFFSET = 10_000
#: A learned model's closed-loop cost "matches" the closed form's within this relative excess.
COST_TOLERANCE = 0.02
#: Controller compute (wall-clock seconds) one episode may spend before the controller is declared
#: failed for the rest of it (zero torque; the episode still runs to its end and counts). A model
#: whose NLPs IPOPT cannot solve makes every call a cold multi-start of up to 3 × 500 iterations —
#: hours per episode; a good model's episode needs a few seconds here. Not binding for any episode
#: of a good model (the cells record whether it bound).
EPISODE_BUDGET_S = 20.0
#: Training settings shared by every model. Patience 5 (the package default is 2): the MLP's
#: first Levenberg–Marquardt iterations often improve the validation loss by less than 1 %, and
#: the default would stop it after three; the S3FVIN gets the same patience.
PATIENCE = 5


@dataclass(frozen=True)
class StudyConfig:
    """One study run (see the module docstring)."""

    sizes: tuple[int, ...]
    draws: tuple[int, ...]
    models: tuple[str, ...]
    seed: int = 0
    episodes: int = 10
    duration_s: float = 10.0
    v1_episodes: int = 10
    trajectory_steps: int = 10
    pool_transitions: int | None = None  # None: max(sizes)
    test_trajectories: int = TEST_TRAJECTORIES
    compile: str = "cached"
    horizon: int | None = None  # None: the scene's
    iterations: int | None = None  # None: the optimizer's default bound (early stopping ends sooner)
    jacobian_windows: int = 128
    cache_dir: Path = Path("data/data-efficiency")
    #: MPCSettings fields changed for both MPCs (the quick path caps IPOPT's iterations).
    mpc_overrides: tuple[tuple[str, Any], ...] = ()
    episode_budget_s: float = EPISODE_BUDGET_S

    def __post_init__(self) -> None:
        unknown = [m for m in self.models if m not in MODELS]
        if unknown or not self.models:
            raise ValueError(f"unknown models {unknown}; choose from {', '.join(MODELS)}")
        if not self.sizes or not self.draws:
            raise ValueError("need at least one size and one seed")
        for size in self.sizes:
            if size <= 0 or size % self.trajectory_steps:
                raise ValueError(f"size {size} is not a positive multiple of the trajectory length "
                                 f"{self.trajectory_steps} (training sets are whole trajectories)")
        if self.pool_size < max(self.sizes) or self.pool_size % self.trajectory_steps:
            raise ValueError(
                f"the pool ({self.pool_size} transitions) must hold the largest size and be whole trajectories"
            )
        if self.trajectory_steps < 8:
            raise ValueError("trajectories need at least 8 periods (the training windows' length)")
        if self.episodes < 1 or self.v1_episodes < 0 or self.duration_s <= 0:
            raise ValueError("need episodes >= 1, v1_episodes >= 0 and a positive duration")
        if self.compile not in ("cached", "none"):
            raise ValueError(f"unknown compile mode {self.compile!r}")
        if not self.episode_budget_s > 0:
            raise ValueError(f"the episode budget must be positive seconds, got {self.episode_budget_s}")

    @property
    def pool_size(self) -> int:
        return max(self.sizes) if self.pool_transitions is None else self.pool_transitions

    def evaluation_fingerprint(self) -> dict[str, Any]:
        """What a cached cell's closed-loop and Pendulum-v1 figures depend on (besides its model)."""
        fingerprint = {"seed": self.seed, "episodes": self.episodes, "duration_s": self.duration_s,
                       "v1_episodes": self.v1_episodes, "horizon": self.horizon,
                       "test_trajectories": self.test_trajectories}
        if self.mpc_overrides:
            fingerprint["mpc_overrides"] = [list(pair) for pair in self.mpc_overrides]
        if self.episode_budget_s != EPISODE_BUDGET_S:
            fingerprint["episode_budget_s"] = self.episode_budget_s
        return fingerprint

    def training_fingerprint(self) -> dict[str, Any]:
        return {"seed": self.seed, "trajectory_steps": self.trajectory_steps, "pool": self.pool_size,
                "iterations": self.iterations, "jacobian_windows": self.jacobian_windows, "patience": PATIENCE}


# ---------------------------------------------------------------------------- data
def pool_path(config: StudyConfig) -> Path:
    return config.cache_dir / f"pool_seed{config.seed}_{config.pool_size}x{config.trajectory_steps}.npz"


def test_path(config: StudyConfig) -> Path:
    return config.cache_dir / f"test_seed{config.seed + TEST_SEED_OFFSET}_{config.test_trajectories}x{TEST_STEPS}.npz"


def _collected(path: Path, trajectories: int, steps: int, seed: int, progress: bool) -> Any:
    """The data at ``path``, collected on the ``pendulum`` scene (the package's collector and its
    defaults: uniform states, ``|ω₀| ≤ 6``, constant or piecewise-constant torques) if absent."""

    if not path.exists():
        save_data(path, collect("pendulum", trajectories=trajectories, steps=steps, seed=seed, progress=progress))
    return load_data(path)


def training_pool(config: StudyConfig, progress: bool = True) -> Any:
    return _collected(pool_path(config), config.pool_size // config.trajectory_steps, config.trajectory_steps,
                      config.seed, progress)


def test_set(config: StudyConfig, progress: bool = True) -> Any:
    return _collected(test_path(config), config.test_trajectories, TEST_STEPS, config.seed + TEST_SEED_OFFSET, progress)


def training_subset(pool: Any, transitions: int, draw: int, seed: int) -> Any:
    """``transitions`` transitions of ``pool`` as whole trajectories: the first ``transitions / T``
    of a permutation seeded by ``(seed, draw)`` (nested over sizes for one draw)."""
    steps = pool.u.shape[1]
    if transitions % steps or not 0 < transitions <= pool.num_transitions:
        raise ValueError(f"{transitions} transitions are not whole trajectories of {steps} periods within the "
                         f"pool's {pool.num_transitions}")
    order = np.random.default_rng([seed, draw]).permutation(pool.num_trajectories)
    return pool.subset(np.sort(order[: transitions // steps]))


# ---------------------------------------------------------------------------- models
def train_settings(config: StudyConfig, draw: int) -> Any:
    return TrainSettings(seed=draw, threads=1, patience=PATIENCE, iterations=config.iterations,
                         jacobian_windows=config.jacobian_windows)


def train_cell_model(model: str, data: Any, config: StudyConfig, draw: int, stem: Path,
                     progress: bool = False) -> dict[str, Any]:
    """Train ``model`` on ``data``, save it at ``stem`` (checkpoint, or the MLP's files); the training report."""
    if model == MLP:
        trained, report = train_mlp(
            data,
            MLPConfig(hidden_width=16, step_size=data.control_period),
            train_settings(config, draw),
            progress=progress,
        )
        save_mlp(stem, trained.config, trained.numpy_weights(), transitions=data.num_transitions)
    else:

        trained, report = train(data, ModelConfig(variant=model, step_size=data.control_period),
                                train_settings(config, draw), progress=progress)
        save_checkpoint(stem, trained.config, trained.numpy_weights(), scene="pendulum", body="pendulum",
                        data={"transitions": data.num_transitions, "draw": draw})
    return {key: report[key] for key in ("iterations", "stopped", "final_train_loss", "final_validation_loss",
                                         "wall_clock_s", "train_windows", "validation_windows")}


def export_cell_model(model: str, stem: Path | None, env: Any) -> Any:
    """The :class:`~fvin_mpc.control.model_export.ExportedModel` of a cell (``closed-form``: the MJCF's rod)."""

    if model == CLOSED_FORM:
        return scene_model(env, true_model=True)
    if model == MLP:

        mlp_config, weights = load_mlp(stem)
        base = env.unwrapped
        return export_mlp(weights, mlp_config, from_mujoco(base.model, base.body_name), name=stem.name)

    return from_checkpoint(stem)


# ---------------------------------------------------------------------------- measurements
def rollout_errors(model: Any, test: Any) -> dict[str, float]:
    """Open-loop rollouts of ``model`` (an ExportedModel) over the test trajectories: the geodesic
    angle error (rad) after all steps (mean, max over trajectories), the angular-velocity error
    there (RMS, rad/s), and the training loss (8-step windows, ``ω`` weight 0.1) on the test set."""
    finals, speeds, window_losses = [], [], []
    states = np.concatenate([test.q, test.omega], axis=-1)
    for x_true, controls in zip(states, test.u):
        predicted = model.rollout(x_true[0], controls)
        finals.append(float(s3.geodesic_angles(predicted[-1, :4], x_true[-1, :4])))
        speeds.append(float(np.sum((predicted[-1, 4:] - x_true[-1, 4:]) ** 2)))
        # the training loss on the windows of 8 steps starting every 4 periods
        for start in range(0, controls.shape[0] - 8 + 1, 4):
            window = model.rollout(x_true[start], controls[start:start + 8])
            truth = x_true[start:start + 9]
            cos = np.sum(window[1:, :4] * truth[1:, :4], axis=-1)
            window_losses.append(
                float(np.mean(4.0 * (1.0 - cos**2) + 0.1 * np.sum((window[1:, 4:] - truth[1:, 4:]) ** 2, -1)))
            )
    finals_array = np.array(finals)
    finite = np.isfinite(finals_array)
    return {"angle_error_1s_mean_rad": float(finals_array[finite].mean()) if finite.any() else math.nan,
            "angle_error_1s_max_rad": float(finals_array.max()),
            "omega_error_1s_rms": float(math.sqrt(np.mean(speeds))),
            "test_window_loss": float(np.mean(window_losses)) if window_losses else math.nan}


class BudgetedController:
    """Passes calls to ``controller`` until they have used ``budget_s`` seconds since ``reset()``;
    from then on returns zero torque, marked as a failed call (``fallback = "budget"``)."""

    def __init__(self, controller: Any, control_dim: int, budget_s: float) -> None:
        self.controller, self.control_dim, self.budget_s = controller, control_dim, budget_s
        self.spent_s, self.exhausted = 0.0, False

    def reset(self) -> None:
        self.controller.reset()
        self.spent_s, self.exhausted = 0.0, False

    def __call__(self, x: Any) -> tuple[np.ndarray, dict[str, Any]]:
        if self.spent_s > self.budget_s:
            self.exhausted = True
            return np.zeros(self.control_dim), {"success": False, "fallback": "budget"}
        start = time.perf_counter()
        try:
            return self.controller(x)
        finally:
            self.spent_s += time.perf_counter() - start


def scene_settings(env: Any, config: StudyConfig, overrides: dict[str, Any] | None = None) -> Any:
    """The MPCSettings of the study's closed loops on ``env``: the scene's, with the study's
    compile mode, horizon and ``mpc_overrides``, then ``overrides`` (a model's own)."""

    return scene_mpc_settings(env, **{"compile": config.compile, "horizon": config.horizon,
                                      **dict(config.mpc_overrides)}).updated(**(overrides or {}))


def study_starts(config: StudyConfig, count: int | None = None) -> list[Any]:
    """The study's first ``count`` (default ``config.episodes``) closed-loop starts."""

    return episode_starts(config.episodes if count is None else count, config.seed, (DEFAULT_MAX_OMEGA,))


def closed_loop(model: Any, env: Any, config: StudyConfig, progress: bool = False,
                overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The scene's MPC on ``model`` over the study's starts (waiting latency mode); ``overrides``:
    MPCSettings fields of this model's MPC."""

    start = time.perf_counter()
    controller = BudgetedController(scene_mpc(env, model, scene_settings(env, config, overrides)), model.control_dim,
                                    config.episode_budget_s)
    build_s = time.perf_counter() - start
    episodes = []
    for episode_start in study_starts(config):
        episode, _ = run_episode(env, controller, config.duration_s, episode_start.reset_options,
                                 seed=episode_start.seed, latency="none")
        metrics = episode_metrics(episode)
        episodes.append({"index": episode_start.index, "success": metrics["success"],
                         "cost": metrics["accumulated_cost"], "time_to_upright_s": metrics["time_to_upright_s"],
                         "failures": metrics["controller_failures"], "controller_s": controller.spent_s,
                         "budget_exhausted": controller.exhausted})
    costs = np.array([e["cost"] for e in episodes])
    return {"build_s": build_s, "successes": int(sum(e["success"] for e in episodes)), "episodes": len(episodes),
            "cost_mean": float(costs.mean()), "failures": int(sum(e["failures"] for e in episodes)),
            "budget_exhausted": int(sum(e["budget_exhausted"] for e in episodes)), "per_episode": episodes}


def pendulum_v1_returns(
    model: Any, env: Any, config: StudyConfig, overrides: dict[str, Any] | None = None
) -> dict[str, Any]:
    """The Pendulum-v1 benchmark's MPC on ``model`` on ``gymnasium.make("Pendulum-v1")``, seeds
    ``0 … v1_episodes − 1``."""
    if config.v1_episodes == 0:
        return {"episodes": 0, "return_mean": None, "returns": []}
    import gymnasium

    settings = benchmark_settings() if config.horizon is None else benchmark_settings(config.horizon)
    controller = BudgetedController(scene_mpc(env, model, settings.updated(
        compile=config.compile, **dict(config.mpc_overrides)).updated(**(overrides or {}))),
                                    model.control_dim, config.episode_budget_s)
    v1 = gymnasium.make("Pendulum-v1")
    returns, exhausted = [], 0
    try:
        for seed in range(config.v1_episodes):
            returns.append(run_v1_episode(v1, controller, seed)["return"])
            exhausted += controller.exhausted
    finally:
        v1.close()
    return {"episodes": len(returns), "return_mean": float(np.mean(returns)), "returns": returns,
            "budget_exhausted": exhausted}


# ---------------------------------------------------------------------------- cells
def cell_name(model: str, size: int, draw: int) -> str:
    return CLOSED_FORM if model == CLOSED_FORM else f"{model}_n{size}_r{draw}"


def _read_record(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def cell_path(cells_dir: Path, name: str, key: str) -> Path:
    """Where the cell ``name`` made with settings ``key`` is (or goes): ``<name>.json`` unless that
    file holds the cell made with other settings (say, another number of starts), then
    ``<name>@<key>.json`` — so a run with other evaluation settings never overwrites a cached cell."""
    plain = cells_dir / f"{name}.json"
    if plain.exists() and (_read_record(plain) or {}).get("key") != key:
        return cells_dir / f"{name}@{key}.json"
    return plain


def model_files(model: str, stem: Path) -> tuple[Path, ...]:
    """The files a trained cell model is saved in (the MLP's weights, or the S3FVIN checkpoint)."""
    return (stem.parent / f"{stem.name}.npz" if model == MLP else stem.parent / f"{stem.name}.safetensors",
            stem.parent / f"{stem.name}.json")


def weights_digest(model: str, stem: Path) -> str:
    return hashlib.sha256(model_files(model, stem)[0].read_bytes()).hexdigest()


def trained_before(trained_as: str, size: int, draw: int, config: StudyConfig, stem: Path) -> dict[str, Any] | None:
    """The training report of the model at ``stem`` if a cached cell (any evaluation settings, and
    for the MLP either MPC) recorded training it with this run's training settings and the files on
    disk are still those weights — then a run with other evaluation settings (more starts, say)
    evaluates the *same* model instead of retraining it. The weights' digest is checked where the
    cell recorded one; older cells did not, and count only if written after the weights."""
    if not all(path.exists() for path in model_files(trained_as, stem)):
        return None
    names = [cell_name(trained_as, size, draw)] + ([cell_name(MLP_EXACT, size, draw)] if trained_as == MLP else [])
    cells_dir = config.cache_dir / "cells"
    for name in names:
        for path in sorted(cells_dir.glob(f"{name}.json")) + sorted(cells_dir.glob(f"{name}@*.json")):
            record = _read_record(path)
            if not record or record.get("fingerprint", {}).get("training") != config.training_fingerprint():
                continue
            training = record.get("training")
            if not training:
                continue
            digest = training.get("weights_sha256")
            if digest is not None:
                if digest == weights_digest(trained_as, stem):
                    return training
            elif path.stat().st_mtime >= model_files(trained_as, stem)[0].stat().st_mtime:
                return training
    return None


def run_cell(model: str, size: int, draw: int, config: StudyConfig, pool: Any, test: Any, env: Any,
             progress: bool = False, cached_only: bool = False) -> dict[str, Any] | None:
    """One cell, from its cache when the cache was made with the same settings; with
    ``cached_only``, ``None`` instead of computing a cell that is not cached."""
    name = cell_name(model, size, draw)
    fingerprint = {"evaluation": config.evaluation_fingerprint(),
                   "training": None if model == CLOSED_FORM else config.training_fingerprint()}
    key = hashlib.sha256(json.dumps(fingerprint, sort_keys=True).encode()).hexdigest()[:16]
    path = cell_path(config.cache_dir / "cells", name, key)
    if path.exists():
        cached = _read_record(path)
        if cached is not None and cached.get("key") == key:
            return cached
    if cached_only:
        return None
    start = time.perf_counter()
    record: dict[str, Any] = {"key": key, "model": model, "size": size, "draw": draw, "fingerprint": fingerprint}
    stem = None
    trained_as = MLP if model == MLP_EXACT else model  # the same network, another MPC
    if model != CLOSED_FORM:
        stem = config.cache_dir / "models" / cell_name(trained_as, size, draw)
        data = training_subset(pool, size, draw, config.seed)
        record["transitions"] = data.num_transitions
        record["trajectories"] = data.num_trajectories
        earlier = trained_before(trained_as, size, draw, config, stem)
        if earlier is not None:  # its weights are at ``stem``
            record["training"] = {**earlier, "reused": True}
        else:
            record["training"] = train_cell_model(trained_as, data, config, draw, stem, progress=False)
            record["training"]["weights_sha256"] = weights_digest(trained_as, stem)
    exported = export_cell_model(trained_as, stem, env)
    overrides = MODEL_MPC_OVERRIDES.get(model, {})
    record["mpc_overrides"] = overrides
    record["rollout"] = rollout_errors(exported, test)
    record["closed_loop"] = closed_loop(exported, env, config, overrides=overrides)
    record["pendulum_v1"] = pendulum_v1_returns(exported, env, config, overrides=overrides)
    record["cell_s"] = time.perf_counter() - start
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=1, default=float) + "\n")
    return record


def run_cells(config: StudyConfig, progress: bool = True,
              cached_only: bool = False) -> tuple[dict[str, Any], list[dict[str, Any]], list[str]]:
    """The closed-form cell, then every (draw, size, model) cell — draws outermost, so that a run
    cut short still holds whole sweeps over the sizes. Returns the closed form's record, the
    cells' records and (``cached_only``) the names of the cells left out because not cached."""
    from tqdm.auto import tqdm

    pool, test = training_pool(config, progress), test_set(config, progress)
    env = scene_env("pendulum", true_model=True)
    try:
        reference = run_cell(CLOSED_FORM, 0, 0, config, pool, test, env)
        cells = [(model, size, draw) for draw in config.draws for size in config.sizes for model in config.models]
        records, missing = [], []
        bar = tqdm(cells, desc="data-efficiency cells", disable=not progress)
        for model, size, draw in bar:
            bar.set_postfix(cell=cell_name(model, size, draw))
            record = run_cell(model, size, draw, config, pool, test, env, cached_only=cached_only)
            if record is None:
                missing.append(cell_name(model, size, draw))
            else:
                records.append(record)
    finally:
        env.close()
    return reference, records, missing


# ---------------------------------------------------------------------------- summary
def summarize(reference: dict[str, Any], records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per (model, size) over its draws, then the closed form's row."""
    reference_cost = reference["closed_loop"]["cost_mean"]
    rows = []
    for model in dict.fromkeys(r["model"] for r in records):
        for size in sorted({r["size"] for r in records if r["model"] == model}):
            mine = [r for r in records if r["model"] == model and r["size"] == size]
            loops = [r["closed_loop"] for r in mine]
            excess = [loop["cost_mean"] / reference_cost - 1.0 for loop in loops]
            v1 = [r["pendulum_v1"]["return_mean"] for r in mine if r["pendulum_v1"]["return_mean"] is not None]
            successes, episodes = sum(loop["successes"] for loop in loops), sum(loop["episodes"] for loop in loops)
            rows.append({
                "model": model, "transitions": size, "seeds": len(mine),
                "angle_error_1s_rad": float(np.mean([r["rollout"]["angle_error_1s_mean_rad"] for r in mine])),
                "test_loss": float(np.mean([r["rollout"]["test_window_loss"] for r in mine])),
                "success": f"{successes}/{episodes}",
                "success_rate": successes / episodes,
                "all_succeed": successes == episodes,
                "cost_mean": float(np.mean([loop["cost_mean"] for loop in loops])),
                "cost_excess_pct_median": 100.0 * float(np.median(excess)),
                "cost_excess_pct_max": 100.0 * float(np.max(excess)),
                "cost_excess_pct_min": 100.0 * float(np.min(excess)),
                "cost_within_2pct_all_seeds": bool(max(excess) <= COST_TOLERANCE),
                "v1_return_mean": float(np.mean(v1)) if v1 else None,
                "v1_return_worst_seed": float(np.min(v1)) if v1 else None,
                "failed_solves": int(sum(loop["failures"] for loop in loops)),
                "budget_exhausted": int(sum(loop.get("budget_exhausted", 0) for loop in loops)
                                        + sum(r["pendulum_v1"].get("budget_exhausted", 0) for r in mine)),
                "train_s_mean": float(np.mean([r["training"]["wall_clock_s"] for r in mine])),
                "per_seed": [{"draw": r["draw"], "successes": r["closed_loop"]["successes"],
                              "episodes": r["closed_loop"]["episodes"], "cost_mean": r["closed_loop"]["cost_mean"],
                              "cost_excess_pct": 100.0 * (r["closed_loop"]["cost_mean"] / reference_cost - 1.0),
                              "v1_return_mean": r["pendulum_v1"]["return_mean"],
                              "angle_error_1s_rad": r["rollout"]["angle_error_1s_mean_rad"],
                              "validation_loss": r["training"]["final_validation_loss"],
                              "iterations": r["training"]["iterations"]} for r in mine],
            })
    loop = reference["closed_loop"]
    rows.append(
        {
            "model": CLOSED_FORM,
            "transitions": None,
            "seeds": None,
            "angle_error_1s_rad": reference["rollout"]["angle_error_1s_mean_rad"],
            "test_loss": reference["rollout"]["test_window_loss"],
            "success": f"{loop['successes']}/{loop['episodes']}",
            "success_rate": loop["successes"] / loop["episodes"],
            "all_succeed": loop["successes"] == loop["episodes"],
            "cost_mean": loop["cost_mean"],
            "cost_excess_pct_median": 0.0,
            "cost_excess_pct_max": 0.0,
            "cost_within_2pct_all_seeds": True,
            "v1_return_mean": reference["pendulum_v1"]["return_mean"],
            "v1_return_worst_seed": (
                float(np.min(reference["pendulum_v1"]["returns"])) if reference["pendulum_v1"]["returns"] else None
            ),
            "failed_solves": loop["failures"],
            "budget_exhausted": loop.get("budget_exhausted", 0) + reference["pendulum_v1"].get("budget_exhausted", 0),
        }
    )
    return rows


def smallest(rows: list[dict[str, Any]], model: str, key: str) -> int | None:
    """The smallest size from which on ``key`` holds for ``model`` at every larger size too (``None``: never)."""
    sizes = sorted((r["transitions"], bool(r[key])) for r in rows if r["model"] == model)
    answer = None
    for size, holds in reversed(sizes):
        if not holds:
            break
        answer = size
    return answer


def per_draw_rows(rows: list[dict[str, Any]], model: str) -> dict[int, list[dict[str, Any]]]:
    """``model``'s rows split by draw: per draw, one row per size that draw was run at, with that
    draw's ``all_succeed`` and ``cost_within_2pct_all_seeds`` (from the rows' ``per_seed``)."""
    out: dict[int, list[dict[str, Any]]] = {}
    for row in rows:
        if row["model"] != model:
            continue
        for seed in row.get("per_seed", []):
            out.setdefault(seed["draw"], []).append({
                "model": model, "transitions": row["transitions"],
                "all_succeed": seed["successes"] == seed["episodes"],
                "cost_within_2pct_all_seeds": seed["cost_excess_pct"] <= 100.0 * COST_TOLERANCE})
    return {draw: sorted(mine, key=lambda r: r["transitions"]) for draw, mine in sorted(out.items())}


def _claims(rows: list[dict[str, Any]], model: str) -> dict[str, Any]:
    mine = sorted((r for r in rows if r["model"] == model), key=lambda r: r["transitions"])
    return {
        "full_success_from": smallest(rows, model, "all_succeed"),
        "full_success_first": next((r["transitions"] for r in mine if r["all_succeed"]), None),
        "cost_within_2pct_from": smallest(rows, model, "cost_within_2pct_all_seeds"),
        "cost_within_2pct_first": next((r["transitions"] for r in mine if r["cost_within_2pct_all_seeds"]), None),
    }


def headline(rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per model: the smallest amount of data for full closed-loop success (every start, every
    seed) and for a closed-loop cost within 2 % of the closed form's (every seed) — each counted
    from where it holds at every larger size too — and the first size where it holds at all; and
    (``per_draw``, where the rows carry ``per_seed``) the same four figures for each draw alone,
    over the sizes that draw was run at."""
    out = {}
    for model in dict.fromkeys(r["model"] for r in rows if r["model"] != CLOSED_FORM):
        out[model] = _claims(rows, model)
        draws = per_draw_rows(rows, model)
        if draws:
            out[model]["per_draw"] = {draw: {"sizes": [r["transitions"] for r in mine], **_claims(mine, model)}
                                      for draw, mine in draws.items()}
    return out


def plot(figure: Any, rows: list[dict[str, Any]]) -> None:
    """Four panels against the number of transitions: rollout error, success, cost excess, Pendulum-v1."""

    figure.set_size_inches(11, 7.5)
    axes = figure.subplots(2, 2)
    reference = next(r for r in rows if r["model"] == CLOSED_FORM)
    learned = [r for r in rows if r["model"] != CLOSED_FORM]
    for model in dict.fromkeys(r["model"] for r in learned):
        mine = sorted((r for r in learned if r["model"] == model), key=lambda r: r["transitions"])
        sizes = [r["transitions"] for r in mine]
        style = {"marker": "o", "label": model}
        line = axes[0, 0].plot(sizes, [r["angle_error_1s_rad"] for r in mine], **style)[0]
        color = line.get_color()
        axes[0, 1].plot(sizes, [100 * r["success_rate"] for r in mine], color=color, **style)
        axes[1, 0].plot(sizes, [max(r["cost_excess_pct_median"], 1e-2) for r in mine], color=color, **style)
        axes[1, 0].vlines(sizes, [max(r["cost_excess_pct_min"], 1e-2) for r in mine],
                          [max(r["cost_excess_pct_max"], 1e-2) for r in mine], color=color, alpha=0.5)
        v1 = [(r["transitions"], r["v1_return_mean"]) for r in mine if r["v1_return_mean"] is not None]
        if v1:
            axes[1, 1].plot(*zip(*v1), color=color, **style)
            for r in mine:
                seeds = [p["v1_return_mean"] for p in r["per_seed"] if p["v1_return_mean"] is not None]
                axes[1, 1].scatter([r["transitions"]] * len(seeds), seeds, color=color, s=10, alpha=0.5)
    axes[0, 0].axhline(reference["angle_error_1s_rad"], color="k", ls=":", label="closed form (h = 0.05 step)")
    axes[0, 0].set(xscale="log", yscale="log", ylabel="held-out angle error after 1 s (rad)",
                   title="open-loop prediction (test set, mean over seeds)")
    axes[0, 1].set(xscale="log", ylabel="closed-loop success (%)", ylim=(-5, 105), title="swing-up success (all seeds)")
    axes[1, 0].axhline(100 * COST_TOLERANCE, color="k", ls="--", label="2 %")
    axes[1, 0].set(xscale="log", yscale="log", ylabel="cost above the closed form (%)",
                   title="closed-loop cost excess (median; bar: seed range)")
    if reference["v1_return_mean"] is not None:
        axes[1, 1].axhline(reference["v1_return_mean"], color="k", ls=":", label="closed-form model")
    axes[1, 1].axhline(ZOO_BEST["mean"], color="tab:red", ls="--",
                       label=f"rl-zoo {ZOO_BEST['algorithm']}, 20k steps (750 episodes, not our seeds)")
    axes[1, 1].set(xscale="log", ylabel="Pendulum-v1 mean return", title="Pendulum-v1 (our seeds; dots: per draw)")
    for axis in axes.flat:
        axis.set_xlabel("training transitions")
        axis.grid(alpha=0.3, which="both")
        axis.legend(fontsize=7)


COLUMNS = ("model", "transitions", "seeds", "angle_error_1s_rad", "test_loss", "success", "cost_mean",
           "cost_excess_pct_median", "cost_excess_pct_max", "v1_return_mean", "v1_return_worst_seed",
           "failed_solves", "budget_exhausted", "train_s_mean")


def _parse_ints(text: str, name: str) -> tuple[int, ...]:
    try:
        values = tuple(int(v) for v in str(text).split(",") if v.strip())
    except ValueError:
        raise ValueError(f"--{name} must be comma-separated integers, got {text!r}") from None
    if not values:
        raise ValueError(f"--{name} is empty")
    return values


def study_config(quick: bool, seed: int, sizes: str, seeds: str, models: str, episodes: int, v1_episodes: int,
                 cache_dir: Path, compile: str, duration: float, pool: int | None = None,
                 episode_budget: float = EPISODE_BUDGET_S, torque_reserve: float = 0.0) -> StudyConfig:
    model_names = tuple(m.strip() for m in models.split(",") if m.strip())
    if (
        quick
    ):  # the test suite's path: tiny sets, a short horizon, uncompiled functions, capped IPOPT, one Pendulum-v1 episode
        quick_sizes = _parse_ints(sizes, "sizes") if sizes != DEFAULT_SIZES else (40, 80)
        return StudyConfig(sizes=quick_sizes, draws=(0,), models=model_names, seed=seed, episodes=1, duration_s=1.0,
                           v1_episodes=min(v1_episodes, 1), trajectory_steps=10, test_trajectories=4,
                           # a fixed pool (not max(sizes)): runs with other sizes share its cells
                           pool_transitions=max(100, *quick_sizes), compile="none", horizon=10, iterations=2,
                           jacobian_windows=8, cache_dir=cache_dir / "quick",
                           mpc_overrides=(("ipopt", (("max_iter", 10), ("cold_max_iter", 20))),
                                          ("cold_starts", ("rollout+",)))
                           + ((("torque_reserve", torque_reserve),) if torque_reserve else ()))
    return StudyConfig(sizes=_parse_ints(sizes, "sizes"), draws=_parse_ints(seeds, "seeds"), models=model_names,
                       seed=seed, episodes=episodes, duration_s=duration, v1_episodes=v1_episodes, compile=compile,
                       cache_dir=cache_dir, pool_transitions=pool, episode_budget_s=episode_budget,
                       # only when set: the default's cells keep their fingerprint (and their cache)
                       mpc_overrides=(("torque_reserve", torque_reserve),) if torque_reserve else ())


def run(quick: bool = False, seed: int = 0, repeats: int = 1, sizes: str = DEFAULT_SIZES, seeds: str = "0,1",
        models: str = DEFAULT_MODELS, episodes: int = 10, v1_episodes: int = 10,
        cache_dir: Path = Path("data/data-efficiency"), compile: str = "cached", duration: float = 10.0,
        pool: int | None = 20000, cached_only: bool = False, progress: bool = True, report_suffix: str | None = None,
        episode_budget: float = EPISODE_BUDGET_S, torque_reserve: float = 0.0, **_: Any) -> StudyResult:
    """Run the study (``repeats`` is unused: nothing here is timed); ``report_suffix``: the report
    is ``data-efficiency.<suffix>.{json,md,png}`` (a run with other evaluation settings beside the
    main report)."""
    if report_suffix is not None and not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_-]*", report_suffix):
        raise ValueError(f"--report-suffix must be letters, digits, '-' and '_', got {report_suffix!r}")
    if not 0.0 <= torque_reserve < 1.0:
        raise ValueError(f"--torque-reserve must be in [0, 1), got {torque_reserve}")
    config = study_config(quick, seed, sizes, seeds, models, episodes, v1_episodes, Path(cache_dir), compile, duration,
                          pool, episode_budget, torque_reserve)
    reference, records, missing = run_cells(config, progress, cached_only)
    rows = summarize(reference, records)
    best = headline(rows)
    notes = [
        f"Settings: {json.dumps({k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(config).items()})}. "
        f"Closed loop: {config.episodes} starts (hanging at rest, then seeded random states), {config.duration_s:g} s "
        "each, the scene's MPC, waiting latency mode (`latency=\"none\"`: model quality, not real time). "
        + (f"Pendulum-v1: seeds 0–{config.v1_episodes - 1}, the benchmark's MPC. " if config.v1_episodes
           else "Pendulum-v1: not run (`--v1-episodes 0`). ")
        + "`cost_excess_pct`: the seeds' mean "
        "closed-loop cost over the closed form's on the same starts, minus 1 (median and worst seed).",
        "Smallest data (transitions; from there on at every larger size, and the first size where it holds): "
        + "; ".join(f"**{model}**: full success from {v['full_success_from']} (first {v['full_success_first']}), "
                    f"cost within 2 % from {v['cost_within_2pct_from']} (first {v['cost_within_2pct_first']})"
                    for model, v in best.items()) + ". `None`: not at any size measured.",
        "The MLP's MPC uses the closed-form energy in its terminal energy-deficit term (it has no energy of its "
        "own); the S3FVIN's uses its learned energy.",
    ]
    per_draw = [f"**{model}** draw {draw} (sizes {', '.join(map(str, d['sizes']))}): full success from "
                f"{d['full_success_from']} (first {d['full_success_first']}), cost within 2 % from "
                f"{d['cost_within_2pct_from']} (first {d['cost_within_2pct_first']})"
                for model, v in best.items() for draw, d in v.get("per_draw", {}).items()]
    if per_draw:
        notes.insert(
            2, "Per draw (each over the sizes that draw was run at; same definitions): " + "; ".join(per_draw) + "."
        )
    if missing:
        notes.append(f"Not run (`--cached-only`; not in the cache): {', '.join(missing)}. The `seeds` column "
                     "says how many draws each row has.")
    name = f"data-efficiency.{report_suffix}" if report_suffix else "data-efficiency"
    return StudyResult(name=name, rows=rows, columns=COLUMNS, plot=plot, notes=notes)


def add_arguments(parser: Any) -> None:
    parser.add_argument("--sizes", default=DEFAULT_SIZES,
                        help="training-set sizes in transitions, comma-separated (default: %(default)s)")
    parser.add_argument("--seeds", default="0,1",
                        help="draws per size (data subset and training seed), comma-separated (default: %(default)s)")
    parser.add_argument("--models", default=DEFAULT_MODELS,
                        help=f"comma-separated from {', '.join(MODELS)} (default: %(default)s)")
    parser.add_argument("--episodes", type=int, default=10,
                        help="closed-loop starts per model, the same for all (default: %(default)s)")
    parser.add_argument("--v1-episodes", type=int, default=10,
                        help="Pendulum-v1 seeds 0..N-1 per model; 0 skips it (default: %(default)s)")
    parser.add_argument(
        "--duration", type=float, default=10.0, help="seconds per closed-loop episode (default: %(default)s)"
    )
    parser.add_argument(
        "--compile",
        choices=("cached", "none"),
        default="cached",
        help="the MPC's functions compiled to C (cached on disk) or run in CasADi's VM (default: %(default)s)",
    )
    parser.add_argument("--cached-only", action="store_true",
                        help="report only the cells already in the cache (a partial grid), list the others as not run")
    parser.add_argument("--pool", type=int, default=20000,
                        help="transitions collected once; every training set is drawn from them, so runs with "
                             "other --sizes share data and cells (default: %(default)s)")
    parser.add_argument(
        "--cache-dir",
        type=Path,
        default=Path("data/data-efficiency"),
        help="data, trained models and per-cell results; a rerun resumes from it (default: %(default)s)",
    )
    parser.add_argument("--episode-budget", type=float, default=EPISODE_BUDGET_S,
                        help="controller compute (wall-clock s) per episode before it is declared failed (zero torque "
                             "for the rest); another value evaluates beside the default's cells (default: %(default)s)")
    parser.add_argument("--torque-reserve", type=float, default=0.0,
                        help="MPCSettings.torque_reserve of every model's MPC (and the closed form's): the plan's "
                             "controls after the first keep this fraction of the torque range in reserve; cells "
                             "evaluated with it are cached beside the default's (default: %(default)s)")
    parser.add_argument("--report-suffix", default=None,
                        help="write data-efficiency.<suffix>.{json,md,png} instead of data-efficiency.*: for a run "
                             "with other evaluation settings (e.g. more --episodes) beside the main report. Its cells "
                             "are cached beside the others (never over them) and evaluate the same trained models")


def export_mlp(weights: Any, config: Any, energy_body: Any, name: str = "mlp") -> Any:
    """The MLP baseline (:mod:`benchmarks.mlp_baseline`) as an
    :class:`~fvin_mpc.control.model_export.ExportedModel` (``newton_iters = 0``).

    Args:
        energy_body: a closed-form :class:`~fvin_mpc.core.rigid_body.PivotedRigidBody` (e.g.
            ``from_mujoco`` of the scene) whose energy stands in for the model's own in the MPC's
            terminal energy-deficit cost (the MLP has none; module docstring). The name gets a
            ``+true-energy`` suffix so that no report can miss it.
    """

    check_mlp_weights(weights, config)
    return ExportedModel(step=mlp_step_function(weights, config), step_size=config.step_size, newton_iters=0,
                         control_dim=config.control_dim, numpy_terms=energy_body.terms(NP),
                         name=f"{name}+true-energy", energy_function=energy_function(energy_body.terms(CA)))
