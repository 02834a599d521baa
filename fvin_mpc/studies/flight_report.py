"""Fly the quadrotor with the real-time MPC: ``python -m fvin_mpc.fly``.

Scene ``quadrotor`` (a 0.5 kg craft, four rotors, thrust 0–2.5 N each, controlled at 20 ms; MuJoCo is
the plant). The controller is the real-time iteration MPC (:class:`fvin_mpc.control.rti.RealTimeMPC`
on ``(x, q, v, ω)`` states, :mod:`fvin_mpc.control.flight`'s settings: 0.6 s horizon, one
Gauss–Newton SQP iteration per period, a compiled Riccati interior-point QP, offset-free thrust
estimate), planning with the learned R³ × S³ model (``--model learned``, the scene's checkpoint) or
the closed-form craft read off the MJCF (``--model closed-form``).

``--scene X.xml`` flies any MJCF of one body on a free joint with site actuators (docs/flyers.md): the
state is its centre of mass's; the control period (when the MJCF names none), the figure-eight's size
and period and the MPC's control weight come from the craft's own scales; what the closed form leaves
out (fluid drag) is printed as a note.

Tasks:

* ``recovery`` — from ``--episodes`` seeded starts at the hover point (upside down at rest, upside
  down tumbling at 10 rad/s, then attitudes uniform on S³ tumbling at up to 10 rad/s) back to hover
  there, level; recovered = within 0.1 m and 0.1 rad from some time to the end of the episode.
* ``figure-eight`` — a 1 m × 0.5 m horizontal figure-eight at 1 m height, one loop per 3 s (up to
  1.5 m/s and 4.4 m/s², tilts up to 24°), joined from hover over a 1 s ramp; the RMS position error
  is taken after the first loop.

``--latency measured`` (the default) is the latency-aware closed loop
(:func:`fvin_mpc.control.closed_loop.run_episode`): each thrust acts from the first 2 ms MuJoCo
sub-step after the controller's measured compute time; deadline misses are counted.

``--report DIR`` runs both tasks with both models side by side and writes ``DIR/quadrotor.{json,md}``
and PNGs (the study in ``docs/quadrotor/``).
"""

from __future__ import annotations

import dataclasses
import shlex
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fvin_mpc.control.closed_loop import NOT_MEASURED, run_episode
from fvin_mpc.control.flight import (
    flight_metrics,
    hover_reference,
    quadrotor_model,
    quadrotor_mpc,
    quadrotor_mpc_settings,
    recovery_duration,
    recovery_starts,
    scaled_control_weight,
    scaled_figure_eight,
)
from fvin_mpc.envs.quadrotor_env import QuadrotorEnv
from fvin_mpc.studies.report import markdown_table, write_report

#: The scene.
SCENE = "quadrotor"
#: Figure-eight: loops flown after the ramp, and the loops left out of the RMS error (settling).
FIGURE_EIGHT_LOOPS = 3
FIGURE_EIGHT_SETTLE_LOOPS = 1
MODELS = ("learned", "closed-form")
#: The files :func:`side_by_side` writes into its folder.
REPORT_FILES = ("quadrotor.json", "quadrotor.md", "recovery.png", "figure_eight.png")


def make_env(render: bool = False, scene: Any = SCENE) -> Any:
    """The env of a free-body ``scene`` (built-in name or MJCF path; default the built-in ``quadrotor``)."""
    return QuadrotorEnv(scene, render_mode="rgb_array" if render else None)


def make_controller(env: Any, model_kind: str, checkpoint: Any = None, low_rank: int = 0, **overrides: Any) -> Any:
    """The MPC planning with ``model_kind`` (``"learned"`` or ``"closed-form"``) on ``env`` (the RTI unless
    ``overrides`` name another ``solver``); ``low_rank`` as :func:`~fvin_mpc.control.flight.quadrotor_model`'s."""

    if model_kind not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model_kind!r}")
    model = quadrotor_model(env, checkpoint, true_model=model_kind == "closed-form", low_rank=low_rank)
    base = env.unwrapped
    overrides.setdefault("control_weight", scaled_control_weight(base.scales))
    return quadrotor_mpc(env, model, quadrotor_mpc_settings(**overrides))


def figure_eight(env: Any) -> Any:
    """The task's figure-eight around the env's hover point, scaled to the craft (the built-in: 0.5 m, 3 s)."""

    base = env.unwrapped
    return scaled_figure_eight(base.hover_point, base.scales, float(np.linalg.norm(base.model.opt.gravity)))


def run_recovery(
    env: Any,
    controller: Any,
    episodes: int,
    seed: int,
    latency: Any,
    duration_s: float | None = None,
    progress: bool = True,
    render_first: bool = False,
) -> tuple[list[dict[str, Any]], list[Any], list[np.ndarray]]:
    """Recovery episodes from :func:`~fvin_mpc.control.flight.recovery_starts`, ``duration_s`` each (default
    the craft's, :func:`~fvin_mpc.control.flight.recovery_duration`); per-episode metrics, the episodes, and
    the first episode's frames when ``render_first``."""
    from tqdm.auto import tqdm

    if duration_s is None:
        duration_s = recovery_duration(env.unwrapped.scales)

    controller.set_reference(hover_reference(env))
    rows, kept, frames = [], [], []
    starts = recovery_starts(env.unwrapped.hover_point, episodes, seed)
    for index, (options, env_seed) in enumerate(tqdm(starts, desc=f"recovery {controller.model.name}",
                                                      disable=not progress)):
        episode, episode_frames = run_episode(env, controller, duration_s, options, seed=env_seed,
                                              render=render_first and index == 0, latency=latency)
        if index == 0:
            frames = episode_frames
        metrics = flight_metrics(episode, hover_reference(env))
        state = episode.states[0]
        rows.append({"index": index, "seed": env_seed, "initial_angle_rad": float(episode.angle_from_goal[0]),
                     "initial_omega_rad_s": float(np.linalg.norm(state[env.unwrapped.space.layout.angular_rates])),
                     **metrics})
        kept.append(episode)
    return rows, kept, frames


def run_figure_eight(env: Any, controller: Any, latency: Any, progress: bool = True,
                     render: bool = False) -> tuple[dict[str, Any], Any, list[np.ndarray]]:
    """One figure-eight flight from hover at the centre: metrics, the episode and its frames."""

    reference = figure_eight(env)
    controller.set_reference(reference)
    duration = reference.ramp_s + FIGURE_EIGHT_LOOPS * reference.period
    episode, frames = run_episode(env, controller, duration, {"hover": True}, render=render, progress=progress,
                                  description=f"figure-eight {controller.model.name}", latency=latency)
    settle = reference.ramp_s + FIGURE_EIGHT_SETTLE_LOOPS * reference.period
    metrics = flight_metrics(episode, reference, settle_s=settle)
    return (
        {**metrics, "settle_s": settle, "amplitude_m": reference.amplitude, "period_s": reference.period},
        episode,
        frames,
    )


def summarize(model_kind: str, recovery: list[dict[str, Any]] | None, tracking: dict[str, Any] | None,
              episodes: list[Any]) -> dict[str, Any]:
    """One table row: recoveries, time to recover, figure-eight RMS, controller time over every period."""

    times = np.concatenate([e.controller_time_s for e in episodes]) * 1e3
    times = times[np.isfinite(times)]
    cpu = np.concatenate([e.cpu_s for e in episodes]) * 1e3
    row: dict[str, Any] = {"model": model_kind,
                           "call_ms_median": float(np.median(times)), "call_ms_p99": float(np.percentile(times, 99)),
                           "call_ms_max": float(times.max()), "cpu_ms_median": float(np.nanmedian(cpu)),
                           "cpu_ms_p99": float(np.nanpercentile(cpu, 99)),
                           "deadline_misses": (NOT_MEASURED if any(e.latency == "none" for e in episodes)
                                               else int(sum(e.deadline_misses for e in episodes))),
                           "failures": int(sum((~e.controller_success).sum() for e in episodes)),
                           "periods": int(times.size)}
    if recovery is not None:
        recovered = [r["time_to_recover_s"] for r in recovery if r["recovered"]]
        row.update(recovered=f"{len(recovered)}/{len(recovery)}", recovered_count=len(recovered),
                   recover_s_median=float(np.median(recovered)) if recovered else float("nan"),
                   recover_s_max=float(np.max(recovered)) if recovered else float("nan"))
    if tracking is not None:
        row.update(figure_eight_rms_m=tracking["rms_position_m"], figure_eight_max_m=tracking["max_position_m"])
    return row


COLUMNS = ("model", "recovered", "recover_s_median", "recover_s_max", "figure_eight_rms_m", "figure_eight_max_m",
           "call_ms_median", "call_ms_p99", "call_ms_max", "cpu_ms_median", "cpu_ms_p99", "deadline_misses", "failures")


def side_by_side(out_dir: Path, argv: Sequence[str], episodes: int = 20, seed: int = 0, latency: Any = "measured",
                 checkpoint: Any = None, models: Sequence[str] = MODELS, progress: bool = True,
                 scene: Any = SCENE, program: str = "python -m fvin_mpc.fly") -> dict[str, Any]:
    """Both tasks with each model under the same controller; writes ``out_dir/quadrotor.{json,md}``
    and ``recovery.png``, ``figure_eight.png``; returns the data."""

    env = make_env(scene=scene)
    loop = figure_eight(env)
    results: dict[str, Any] = {"episodes": episodes, "seed": seed, "latency": latency, "models": {}}
    flights: dict[str, tuple[list[Any], Any]] = {}
    rows = []
    for kind in models:
        controller = make_controller(env, kind, checkpoint)
        recovery, recovery_episodes, _ = run_recovery(env, controller, episodes, seed, latency, progress=progress)
        tracking, tracking_episode, _ = run_figure_eight(env, controller, latency, progress=progress)
        row = summarize(kind, recovery, tracking, [*recovery_episodes, tracking_episode])
        row["model_name"] = controller.model.name
        rows.append(row)
        results["models"][kind] = {"model": controller.model.name, "summary": row, "recovery": recovery,
                                   "figure_eight": tracking,
                                   "settings": dataclasses.asdict(controller.settings)}
        flights[kind] = (recovery_episodes, tracking_episode)
    out_dir.mkdir(parents=True, exist_ok=True)
    plot_recovery(flights, out_dir / "recovery.png")
    plot_figure_eight(flights, figure_eight(env), out_dir / "figure_eight.png")
    command = program + " " + " ".join(shlex.quote(a) for a in argv)
    body = "\n".join([
        f"Latency mode: `{latency}`; {episodes} recovery starts (seed {seed}), "
        f"{recovery_duration(env.unwrapped.scales):g} s each; one "
        f"figure-eight flight ({FIGURE_EIGHT_LOOPS} loops of {loop.period:g} s, {2 * loop.amplitude:g} m wide, after a "
        f"{loop.ramp_s:g} s ramp, RMS after the first loop). "
        "Controller times are over every period of every episode of that model (wall clock, the whole call: "
        f"feedback + preparation); the control period is {env.unwrapped.dt * 1e3:g} ms."
        + ("" if latency == "measured" else
           " With a fixed delay the thrust acts after that delay whatever the compute time, and a period's busy"
           " time is the delay: deadline misses cannot occur and are not judged; the times are measured all the same."),
        "",
        markdown_table(rows, COLUMNS), "",
        "![recovery](recovery.png)", "", "![figure-eight](figure_eight.png)", "",
        "Per start (recovered, time to recover in s, initial |ω| in rad/s):", "",
        markdown_table([{"index": r["index"], **{f"{kind} {key}": results['models'][kind]['recovery'][i][key]
                                                  for kind in models for key in ("recovered", "time_to_recover_s")},
                         "initial_omega": r["initial_omega_rad_s"], "initial_angle": r["initial_angle_rad"]}
                        for i, r in enumerate(results["models"][models[0]]["recovery"])],
                       ["index", *[f"{kind} {key}" for kind in models for key in ("recovered", "time_to_recover_s")],
                        "initial_omega", "initial_angle"]),
    ])
    write_report(
        out_dir / "quadrotor",
        "Quadrotor: recovery and figure-eight with the real-time MPC, learned vs closed form",
        results,
        body,
        command,
    )
    env.close()
    return results


def plot_recovery(flights: dict[str, tuple[list[Any], Any]], path: Path) -> None:
    """Position error and angle to level over time, every recovery episode, one column per model."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(2, len(flights), figsize=(5 * len(flights), 6), sharex=True, squeeze=False)
    for column, (kind, (episodes, _)) in enumerate(flights.items()):
        for episode in episodes:
            error = np.linalg.norm(episode.states[:, :3] - episodes[0].states[0, :3], axis=1)
            axes[0, column].plot(episode.time, error, lw=0.8)
            axes[1, column].plot(episode.time, episode.angle_from_goal, lw=0.8)
        axes[0, column].set_title(kind)
        axes[0, column].set_yscale("log")
        axes[0, column].axhline(0.1, color="tab:gray", ls=":")
        axes[1, column].axhline(0.1, color="tab:gray", ls=":")
        axes[1, column].set_xlabel("time (s)")
    axes[0, 0].set_ylabel("|x − hover point| (m)")
    axes[1, 0].set_ylabel("angle to level (rad)")
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def plot_figure_eight(flights: dict[str, tuple[list[Any], Any]], reference: Any, path: Path) -> None:
    """The flown paths over the reference (top view) and the position error over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    t = np.linspace(0.0, reference.ramp_s + FIGURE_EIGHT_LOOPS * reference.period, 2000)
    wanted, _ = reference(t)
    axes[0].plot(wanted[:, 0], wanted[:, 1], "k--", lw=1, label="reference")
    for kind, (_, episode) in flights.items():
        axes[0].plot(episode.states[:, 0], episode.states[:, 1], lw=1, label=kind)
        target, _ = reference(episode.time)
        axes[1].plot(episode.time, np.linalg.norm(episode.states[:, :3] - target[:, :3], axis=1), lw=1, label=kind)
    axes[0].set_aspect("equal")
    axes[0].set_xlabel("x (m)")
    axes[0].set_ylabel("y (m)")
    axes[0].legend()
    axes[1].axvline(reference.ramp_s + FIGURE_EIGHT_SETTLE_LOOPS * reference.period, color="tab:gray", ls=":")
    axes[1].set_xlabel("time (s)")
    axes[1].set_ylabel("|x − x_ref| (m)")
    axes[1].legend()
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def write_still(frames: list[np.ndarray], path: Path, count: int = 5) -> None:
    """``count`` frames spread over the first half of the flight, side by side, as a PNG."""
    import imageio.v2 as imageio

    picks = np.linspace(0, max(len(frames) // 2, 1), count).astype(int)
    imageio.imwrite(str(path), np.concatenate([frames[i] for i in picks if i < len(frames)], axis=1))


def print_rows(rows: list[dict[str, Any]], file: Any = None) -> None:
    # sys.stdout read at the call, not at import: a caller (or a test) may have replaced it since.
    print(markdown_table(rows, [c for c in COLUMNS if any(c in row for row in rows)]), file=file or sys.stdout)
