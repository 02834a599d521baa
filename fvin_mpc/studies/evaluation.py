"""Closed-loop evaluation of the controllers over seeded episodes: ``python -m fvin_mpc.evaluate``.

Runs every requested controller from the same initial states on a scene's MuJoCo env and
compares them:

* ``mpc-learned`` — IPOPT MPC on the learned S3FVIN (the checkpoint);
* ``mpc-true`` — the same MPC on the closed-form rigid body read off the scene's MJCF;
* ``energy-learned`` — energy-shaping swing-up + LQR catch from the learned ``J``, ``U``, ``g``;
* ``energy-true`` — the same law from the closed-form body;
* ``zero`` — no torque (shows the task is not trivial).

Episode 0 starts hanging at rest (the hard start); episodes ``i ≥ 1`` start from the env's
seeded random reset (``{"random": True, "max_omega": …}``, seed ``seed + i``): orientation
uniform over the joint's range, angular velocity uniform in ``|ω| ≤ max_omega``.

Per controller: success rate (upright within 0.1 rad from some time on to the end of the
episode, :func:`fvin_mpc.control.closed_loop.episode_metrics`), time to upright (median, p90 over
the successful episodes), accumulated cost (the env's Pendulum-v1-style cost), largest
torque, controller time per call (median, p95 over all calls) and controller failures
(solves IPOPT did not accept). A per-seed table puts learned and true model side by side.

Outputs in ``--out-dir``: ``evaluation.json``, ``evaluation.md`` (tables + command),
``time_to_upright.png`` (distribution) and, for a hinge, ``phase_portraits.png``
(angle from upright vs angular rate). ``--workers N`` runs episodes in N processes (or, with
``--backend ray``, N Ray actors, docs/ray.md); each builds its controllers once (the MPC's
compiled library comes from the on-disk cache).

A **free body** (``--scene`` of one body on a free joint: the built-in ``quadrotor``, any craft's MJCF,
a Menagerie robot) is judged as ``python -m fvin_mpc.fly --report`` judges it — its recovery starts
and criterion (within 0.1 m of the hover point and 0.1 rad of level from some time to the end of an
episode as long as the craft's rotation time scales ask, docs/flyers.md) and the craft's figure-eight,
the RTI MPC on the learned model (when a checkpoint is there) beside the closed form;
``quadrotor.{json,md}`` and plots go to ``--out-dir``. ``--duration``, ``--controllers``,
``--max-omega`` and the MPC options are then not used.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fvin_mpc.control.closed_loop import NOT_MEASURED, ZeroController, check_latency, episode_metrics, run_episode
from fvin_mpc.control.energy_shaping import EnergyShapingNotApplicable
from fvin_mpc.control.mpc import MPCSettings
from fvin_mpc.control.scene import scene_energy_shaping, scene_env, scene_model, scene_mpc, scene_mpc_settings
from fvin_mpc.core.checkpoint import checkpoint_exists, resolve_checkpoint_path
from fvin_mpc.envs.scenes import resolve_scene
from fvin_mpc.studies import starts
from fvin_mpc.studies.pool import run_tasks
from fvin_mpc.studies.report import write_report as write_report_files
from fvin_mpc.studies.starts import EpisodeStart

#: Every controller the evaluation knows, in report order.
CONTROLLERS: tuple[str, ...] = ("mpc-learned", "mpc-true", "energy-learned", "energy-true", "zero")
#: Largest |ω| (rad/s) of the random initial states unless ``--max-omega`` says otherwise.
DEFAULT_MAX_OMEGA = 2.0


class ControllerSkipped(Exception):
    """A controller does not apply to the scene (or its model is missing); the message says why."""


@dataclass(frozen=True)
class EvaluationConfig:
    """What to evaluate.

    Attributes:
        scene: built-in scene name or MJCF path.
        checkpoint: learned model (shipped name or path); ``None`` = the scene's shipped default.
        episodes: number of episodes per controller (episode 0 starts hanging at rest).
        duration_s: seconds per episode.
        controllers: names from :data:`CONTROLLERS`.
        seed: base seed; episode ``i`` resets the env with seed ``seed + i``.
        max_omega: largest initial |ω| (rad/s) of the random starts.
        control_period: seconds per step; ``None`` = the checkpoint's step if it exists, else the scene's.
        mpc: :class:`~fvin_mpc.control.mpc.MPCSettings` fields changed from the scene's
            (:func:`fvin_mpc.control.scene.scene_mpc_settings`), as ``(name, value)`` pairs.
        latency: :func:`~fvin_mpc.control.closed_loop.run_episode`'s ``latency``: ``"none"`` (the
            simulator waits for the controller), ``"measured"`` or a fixed delay in seconds.
    """

    scene: str = "pendulum"
    checkpoint: str | None = None
    episodes: int = 50
    duration_s: float = 10.0
    controllers: tuple[str, ...] = CONTROLLERS
    seed: int = 0
    max_omega: float = DEFAULT_MAX_OMEGA
    control_period: float | None = None
    mpc: tuple[tuple[str, Any], ...] = ()
    latency: Any = "none"

    def __post_init__(self) -> None:
        if self.episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {self.episodes}")
        if not (math.isfinite(self.duration_s) and self.duration_s > 0):
            raise ValueError(f"duration must be > 0 s, got {self.duration_s}")
        unknown = [name for name in self.controllers if name not in CONTROLLERS]
        if unknown or not self.controllers:
            raise ValueError(f"unknown controllers {unknown}; choose from {', '.join(CONTROLLERS)}")
        if not (math.isfinite(self.max_omega) and self.max_omega >= 0):
            raise ValueError(f"max_omega must be finite and >= 0, got {self.max_omega}")

        check_latency(self.latency)
        try:  # validate the overrides (names and values) now, not in a worker
            MPCSettings().updated(**dict(self.mpc))  # rti and ipopt as mappings of their fields
        except TypeError as error:
            raise ValueError(f"unknown MPC setting in {dict(self.mpc)}: {error}") from None

    @property
    def checkpoint_name(self) -> str:
        return self.checkpoint or resolve_scene(self.scene).default_checkpoint


def episode_starts(config: EvaluationConfig) -> list[EpisodeStart]:
    """Episode 0 hanging at rest, then seeded random states (:func:`fvin_mpc.studies.starts.episode_starts`)."""
    return starts.episode_starts(config.episodes, config.seed, (config.max_omega,))


# ---------------------------------------------------------------------- controllers
def make_env(config: EvaluationConfig) -> Any:
    """The scene's env at the configuration's control period (:func:`fvin_mpc.control.scene.scene_env`)."""

    learned = any(name.endswith("-learned") for name in config.controllers)
    has_checkpoint = learned and _checkpoint_exists(config)
    return scene_env(config.scene, config.checkpoint_name if has_checkpoint else None, true_model=not has_checkpoint,
                     control_period=config.control_period)


def build_controller(name: str, env: Any, config: EvaluationConfig) -> Any:
    """The controller called ``name`` for ``env``; :class:`ControllerSkipped` if it does not apply."""

    learned = name.endswith("-learned")
    if learned:
        _check_checkpoint(config)
    if name == "zero":
        return ZeroController(env.unwrapped.action_space.shape[0])
    model = scene_model(env, config.checkpoint_name if learned else None, true_model=not learned)
    if name.startswith("mpc-"):
        return scene_mpc(env, model, mpc_settings(config, env))
    if name.startswith("energy-"):
        try:
            return scene_energy_shaping(env, model)
        except EnergyShapingNotApplicable as error:
            raise ControllerSkipped(str(error)) from None
    raise ValueError(f"unknown controller {name!r}")


def mpc_settings(config: EvaluationConfig, env: Any = None) -> Any:
    """The MPC settings of the scene (:func:`fvin_mpc.control.scene.scene_mpc_settings`), ``config.mpc`` applied."""

    return scene_mpc_settings(make_env(config) if env is None else env, **dict(config.mpc))


def _checkpoint_exists(config: EvaluationConfig) -> bool:
    return checkpoint_exists(config.checkpoint_name)


def _check_checkpoint(config: EvaluationConfig) -> None:
    """A missing *default* checkpoint skips the learned controllers; a missing explicit one is an error."""

    if _checkpoint_exists(config):
        return
    stem = resolve_checkpoint_path(config.checkpoint_name)
    if config.checkpoint is None:
        raise ControllerSkipped(f"no learned model: the default checkpoint {config.checkpoint_name!r} is not shipped "
                                f"(train one with python -m fvin_mpc.train and pass --checkpoint)")
    raise FileNotFoundError(f"checkpoint not found: {config.checkpoint} (looked for {stem.name}.json in {stem.parent})")


def signed_angle_from_goal(q: np.ndarray, goal: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Planar case: the signed rotation (rad, in (−π, π]) about ``axis`` from ``goal`` to ``q`` (..., 4)."""
    def angle(quaternion: np.ndarray) -> np.ndarray:
        return 2.0 * np.arctan2(quaternion[..., 1:] @ axis, quaternion[..., 0])

    difference = angle(np.asarray(q, float)) - angle(np.asarray(goal, float))
    return -np.mod(-difference + np.pi, 2 * np.pi) + np.pi


# ---------------------------------------------------------------------- episodes (also run in workers)
_WORKER: dict[str, Any] = {}


def _init_worker(config: EvaluationConfig) -> None:
    _WORKER.clear()
    _WORKER.update(config=config, env=make_env(config), controllers={})


def _worker_controller(name: str) -> Any:
    controllers = _WORKER["controllers"]
    if name not in controllers:
        controllers[name] = build_controller(name, _WORKER["env"], _WORKER["config"])
    return controllers[name]


def run_task(name: str, start: EpisodeStart) -> dict[str, Any]:
    """One episode of controller ``name`` (in the current worker's env); metrics and a light trajectory."""

    env, config = _WORKER["env"], _WORKER["config"]
    controller = _worker_controller(name)
    episode, _ = run_episode(env, controller, config.duration_s, start.reset_options, seed=start.seed,
                             latency=config.latency)
    metrics = episode_metrics(episode)
    axis = env.unwrapped.joint_axis
    goal = env.unwrapped.goal
    trajectory = None
    if axis is not None:
        trajectory = {"angle": signed_angle_from_goal(episode.q, goal, axis), "rate": episode.omega @ axis}
    return {"controller": name, "index": start.index, "metrics": metrics,
            "controller_time_s": episode.controller_time_s, "feedback_time_s": episode.feedback_s,
            "trajectory": trajectory,
            "initial": {"q": episode.q[0].tolist(), "omega": episode.omega[0].tolist()}}


# ---------------------------------------------------------------------- the evaluation
@dataclass
class EvaluationResult:
    """Everything :func:`evaluate` measured.

    Attributes:
        config: what was run.
        summary: controller → aggregate metrics (see :func:`summarize`).
        episodes: per episode: index, seed, initial state and controller → metrics.
        skipped: controller → reason it was not run.
        trajectories: controller → per-episode ``{"angle", "rate"}`` (hinge only; not in JSON).
        build: controller → seconds to build it in the main process (and whether compiled from cache).
    """

    config: EvaluationConfig
    summary: dict[str, dict[str, Any]]
    episodes: list[dict[str, Any]]
    skipped: dict[str, str]
    trajectories: dict[str, list[dict[str, np.ndarray] | None]] = field(default_factory=dict)
    build: dict[str, dict[str, Any]] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"config": {**asdict(self.config), "checkpoint": self.config.checkpoint_name},
                "summary": self.summary, "skipped": self.skipped, "build": self.build, "episodes": self.episodes}


def summarize(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Aggregate one controller's episode records."""

    metrics = [r["metrics"] for r in records]
    successes = [m for m in metrics if m["success"]]
    times = np.array([m["time_to_upright_s"] for m in successes], dtype=float)
    costs = np.array([m["accumulated_cost"] for m in metrics])
    calls_ms = 1e3 * np.concatenate([r["controller_time_s"] for r in records])
    calls_ms = calls_ms[np.isfinite(calls_ms)]  # skipped observations (latency-aware runs) have none
    feedback_ms = 1e3 * np.concatenate([r["feedback_time_s"] for r in records])
    feedback_ms = feedback_ms[np.isfinite(feedback_ms)]
    return {
        "episodes": len(metrics),
        "successes": len(successes),
        "success_rate": len(successes) / len(metrics),
        "time_to_upright_median_s": float(np.median(times)) if times.size else None,
        "time_to_upright_p90_s": float(np.percentile(times, 90)) if times.size else None,
        "accumulated_cost_mean": float(costs.mean()),
        "accumulated_cost_median": float(np.median(costs)),
        "max_abs_torque": float(max(m["max_abs_torque"] for m in metrics)),
        "controller_time_median_ms": float(np.median(calls_ms)),
        "controller_time_p95_ms": float(np.percentile(calls_ms, 95)),
        "controller_time_p99_ms": float(np.percentile(calls_ms, 99)),
        # the call alone (observation → torque): the delay the plant sees; the time above adds the
        # preparation a real-time iteration does after the torque is sent
        "feedback_time_median_ms": float(np.median(feedback_ms)),
        "feedback_time_p99_ms": float(np.percentile(feedback_ms, 99)),
        "deadline_misses": (NOT_MEASURED if any(m["deadline_misses"] == NOT_MEASURED for m in metrics)
                            else int(sum(m["deadline_misses"] for m in metrics))),
        "controller_failures": int(sum(m["controller_failures"] for m in metrics)),
        "episodes_with_failures": int(sum(m["controller_failures"] > 0 for m in metrics)),
        "failed_episodes": [r["index"] for r in records if not r["metrics"]["success"]],
    }


def evaluate(config: EvaluationConfig, workers: int = 1, progress: bool = True,
             log: Any = None, backend: str = "process", address: str | None = None) -> EvaluationResult:
    """Run ``config.controllers`` over :func:`episode_starts`; ``workers > 1`` uses a process pool,
    ``backend="ray"`` Ray actors (``address``: the cluster; :func:`fvin_mpc.studies.pool.run_tasks`).

    Controllers that do not apply (or whose default checkpoint is missing) are skipped with a
    message in :attr:`EvaluationResult.skipped` (and on ``log``).
    """
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    log = log or (lambda message: print(message, file=sys.stderr))
    _init_worker(config)
    skipped: dict[str, str] = {}
    build: dict[str, dict[str, Any]] = {}
    names = []
    # Build each controller once here: reports what does not apply, and compiles the MPC's
    # library into the disk cache before any worker needs it.
    for name in config.controllers:
        start = time.perf_counter()
        try:
            controller = _worker_controller(name)
        except ControllerSkipped as reason:
            skipped[name] = str(reason)
            log(f"skipping {name}: {reason}")
            continue
        report = getattr(controller, "compile_report", None)
        build[name] = {"build_s": time.perf_counter() - start,
                       "compiled_from_cache": None if report is None else report.cached}
        names.append(name)
    episode_list = episode_starts(config)
    tasks = [(name, start) for start in episode_list for name in names]
    records = run_tasks(run_task, tasks, _init_worker, (config,), workers, progress, f"evaluate {config.scene}",
                        backend=backend, address=address)
    summary = {name: summarize([r for r in records if r["controller"] == name]) for name in names}
    episodes = []
    for start in episode_list:
        mine = [r for r in records if r["index"] == start.index]
        episodes.append({
            "index": start.index, "seed": start.seed,
            "init": "rest" if start.reset_options is None else "random",
            "q0": mine[0]["initial"]["q"] if mine else None, "omega0": mine[0]["initial"]["omega"] if mine else None,
            "results": {r["controller"]: r["metrics"] for r in mine},
        })
    trajectories = {name: [r["trajectory"] for r in records if r["controller"] == name] for name in names}
    return EvaluationResult(config, summary, episodes, skipped, trajectories, build)


# ---------------------------------------------------------------------- reports
def _fmt(value: Any, digits: int = 2) -> str:
    if value is None:
        return "—"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def summary_table(result: EvaluationResult) -> str:
    """Markdown table: one row per controller."""
    lines = ["| controller | success | time to upright median (s) | p90 (s) | cost mean | cost median "
             "| max torque | controller ms median | p95 | p99 | feedback ms median | p99 | failed solves |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, s in result.summary.items():
        lines.append(
            f"| {name} | {100 * s['success_rate']:.0f} % ({s['successes']}/{s['episodes']}) "
            f"| {_fmt(s['time_to_upright_median_s'])} | {_fmt(s['time_to_upright_p90_s'])} "
            f"| {_fmt(s['accumulated_cost_mean'], 1)} | {_fmt(s['accumulated_cost_median'], 1)} "
            f"| {_fmt(s['max_abs_torque'])} | {_fmt(s['controller_time_median_ms'], 2)} "
            f"| {_fmt(s['controller_time_p95_ms'], 2)} | {_fmt(s['controller_time_p99_ms'], 2)} "
            f"| {_fmt(s['feedback_time_median_ms'], 2)} | {_fmt(s['feedback_time_p99_ms'], 2)} "
            f"| {s['controller_failures']} |")
    return "\n".join(lines)


def per_seed_table(result: EvaluationResult, axis: np.ndarray | None, goal: np.ndarray) -> str:
    """Markdown table: one row per episode, time to upright / cost of every controller on that seed."""
    names = list(result.summary)
    head = "| # | seed | start | " + " | ".join(f"{n}: t↑ (s) / cost" for n in names) + " |"
    lines = [head, "|" + "---|" * (3 + len(names))]
    for episode in result.episodes:
        if axis is not None and episode["q0"] is not None:
            angle = float(signed_angle_from_goal(np.array(episode["q0"]), goal, axis))
            start = f"φ={angle:+.2f}, φ̇={float(np.array(episode['omega0']) @ axis):+.2f}"
        else:
            start = episode["init"]
        cells = []
        for name in names:
            m = episode["results"].get(name)
            if m is None:
                cells.append("—")
            elif m["success"]:
                cells.append(f"{m['time_to_upright_s']:.2f} / {m['accumulated_cost']:.1f}")
            else:
                cells.append(f"**fail** / {m['accumulated_cost']:.1f}")
        lines.append(f"| {episode['index']} | {episode['seed']} | {start} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot_time_to_upright(result: EvaluationResult, path: Path) -> None:
    """Empirical distribution (ECDF) of time to upright per controller; failures never reach 1."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(7, 4))
    for name in result.summary:
        times = np.sort([e["results"][name]["time_to_upright_s"] for e in result.episodes
                         if name in e["results"] and e["results"][name]["success"]])
        total = sum(name in e["results"] for e in result.episodes)
        if times.size:
            axis.step(np.r_[0.0, times], np.arange(times.size + 1) / total, where="post", label=name)
        else:
            axis.plot([], [], label=f"{name} (no success)")
    axis.set_xlabel("time to upright (s), held to the end")
    axis.set_ylabel("fraction of episodes")
    axis.set_xlim(0, result.config.duration_s)
    axis.set_ylim(0, 1.02)
    axis.grid(alpha=0.3)
    axis.legend(loc="lower right")
    axis.set_title(f"{result.config.scene}: {result.config.episodes} episodes")
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def plot_phase_portraits(result: EvaluationResult, path: Path) -> None:
    """Hinge only: angle from upright vs angular rate, every episode, one panel per controller."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [n for n in result.summary if any(t is not None for t in result.trajectories.get(n, []))]
    columns = min(3, len(names))
    rows = math.ceil(len(names) / columns)
    figure, axes = plt.subplots(rows, columns, figsize=(4.5 * columns, 3.8 * rows), squeeze=False)
    for ax, name in zip(axes.ravel(), names):
        for i, trajectory in enumerate(result.trajectories[name]):
            angle, rate = trajectory["angle"], trajectory["rate"]
            # Break the line where the angle wraps around ±π.
            jumps = np.flatnonzero(np.abs(np.diff(angle)) > np.pi) + 1
            for a, r in zip(np.split(angle, jumps), np.split(rate, jumps)):
                ax.plot(a, r, lw=0.6, alpha=0.6, color=f"C{i % 10}")
            ax.plot(angle[0], rate[0], "k.", ms=3)
        ax.plot(0, 0, "r*", ms=10)
        ax.set_xlim(-np.pi, np.pi)
        ax.set_title(f"{name} ({100 * result.summary[name]['success_rate']:.0f} % success)")
        ax.set_xlabel("angle from upright φ (rad)")
        ax.set_ylabel("φ̇ (rad/s)")
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[len(names):]:
        ax.set_visible(False)
    figure.tight_layout()
    figure.savefig(path, dpi=90)
    plt.close(figure)


def _settings_text(config: EvaluationConfig) -> str:
    settings = mpc_settings(config)
    return (
        f"solver {settings.solver}, horizon {settings.horizon}, Hessian {settings.ipopt.hessian}, max_iter "
        f"{settings.ipopt.max_iter}, "
        f"terminal energy weight {settings.terminal_energy_weight:g}, cold starts {', '.join(settings.cold_starts)}"
    )


def write_report(result: EvaluationResult, out_dir: Path, command: str) -> list[Path]:
    """``evaluation.json``, ``evaluation.md`` and the plots in ``out_dir``; returns the paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    env = make_env(result.config)
    axis, goal = env.unwrapped.joint_axis, env.unwrapped.goal
    written = [out_dir / "evaluation.json", out_dir / "evaluation.md", out_dir / "time_to_upright.png"]
    plot_time_to_upright(result, written[2])
    images = [f"![time to upright]({written[2].name})"]
    if axis is not None and result.summary:
        written.append(out_dir / "phase_portraits.png")
        plot_phase_portraits(result, written[-1])
        images.append(f"![phase portraits]({written[-1].name})")
    config = result.config
    skipped = "".join(f"\n- `{name}` skipped: {reason}" for name, reason in result.skipped.items())
    text = f"""{config.episodes} episodes of {config.duration_s:g} s per controller; episode 0 starts hanging at rest,
the others from the env's seeded random reset (seed {config.seed} + i; |ω₀| ≤ {config.max_omega:g} rad/s).
Learned model: `{config.checkpoint_name}`; MPC settings: {_settings_text(config)}; latency mode: `{config.latency}`
(`none`: the simulator waits for the controller; `measured`: each torque acts from the first MuJoCo
sub-step after the controller's measured compute time). Success: within 0.1 rad of upright from some time on
to the end of the episode. Time to upright over the successful episodes; controller ms = the whole
controller time per period (wall clock: the call and, for the real-time iteration, its preparation after
the torque is sent; median, p95, p99 over all periods); feedback ms = the call alone, observation to
torque (the delay the plant sees); failed solves = the solver did not accept the solve (the
controller then applied its fallback).{skipped}

{summary_table(result)}

{chr(10).join(images)}

## Per seed

{per_seed_table(result, axis, goal)}
"""
    write_report_files(
        out_dir / "evaluation", f"Closed-loop evaluation: `{config.scene}`", result.to_json(), text, command
    )
    env.close()
    return written


# ---------------------------------------------------------------------- CLI
