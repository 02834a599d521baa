"""Closed-loop episodes of a controller on a scene's Gymnasium environment, and their metrics.

Every controller in the package (:class:`~fvin_mpc.control.mpc.MPC`,
:class:`~fvin_mpc.control.energy_shaping.EnergyShapingController`, :class:`ZeroController`) is a
callable ``u, info = controller(x)`` with a ``reset()``; :func:`run_episode` drives
one on an :class:`envs.RigidBodyEnv` (MuJoCo is the plant) and records an :class:`Episode`;
:func:`episode_metrics` turns it into the numbers the CLIs report.

Latency (``run_episode(..., latency=...)``, see ``docs/realtime.md``). The env advances one
control period ``h`` per :meth:`step`, as ``frame_skip`` MuJoCo sub-steps of ``δ`` (5 ms in the
built-in scenes). With ``latency="none"`` (the *waiting* mode) the simulator waits for the
controller: the torque computed from the observation at ``t`` acts from ``t`` on, whatever the
compute time — right for studies that isolate model quality, not for claims of real time. With
``latency="measured"`` (or a fixed number of seconds ``c``, deterministic, for tests) the plant does
not wait: the torque computed from the observation at ``t`` with compute time ``c`` acts from the
first sub-step boundary at or after ``t + c``; the previous torque holds until then (the first
torque of an episode is preceded by zero). A controller with a ``prepare()`` method (the real-time
iteration's preparation phase) has it called right after its torque is delivered; its time adds to
the period's busy time but not to the latency of that torque. If the controller is still busy at the
next control instant (feedback + preparation ``> h``: a *deadline miss*), that observation is skipped
and the controller samples at the first control instant at which it is free.

Python's cyclic garbage collector is kept out of the controller's time, as a real-time loop in Python
must keep it: automatic collection is off from the observation until the preparation returns and runs,
if due, while the plant steps (the period's spare time); the objects that exist when the episode
starts are frozen (``gc.freeze``), so those collections scan only what the episode made. A full
collection of a large heap can take longer than a control period, and inside a controller call it is a
deadline miss (docs/adaptation.md measures both).
"""

from __future__ import annotations

import gc
import math
import time
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Iterator, Literal, Protocol, Union

import numpy as np

from fvin_mpc.core.errors import raise_if_interrupted

#: Upright means within this angle of the goal (rad) …
UPRIGHT_TOLERANCE = 0.1
#: … and holding means staying within this angle over the last :data:`HOLD_WINDOW_S` seconds.
HOLD_TOLERANCE = 0.05
HOLD_WINDOW_S = 3.0
#: A summary's deadline misses in waiting mode (latency "none"): the simulator waits for the
#: controller, so no period has a deadline, and a 0 would read as "kept real time".
NOT_MEASURED = "not measured"


#: The scalar entries of a controller's ``info`` an :class:`Episode` keeps per period (the plan
#: itself is left out: it would make episodes heavy).
RECORDED_INFO = (
    "status",
    "iterations",
    "solve_time_s",
    "step_residual",
    "fallback",
    "cold_start",
    "restarted",
    "disturbance",
    "qp_iterations",
)

#: ``run_episode``'s ``latency``: ``"none"`` (the simulator waits for the controller), ``"measured"``
#: (the controller's wall-clock compute time delays its torque) or a fixed delay in seconds.
Latency = Union[Literal["none", "measured"], float]


class Controller(Protocol):
    """``u, info = controller(x)`` from the measured state ``x`` (``(q, ω)`` ``(7,)``, or ``(x, q, v, ω)``
    ``(13,)`` for a free body); ``reset()`` between episodes."""

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, dict[str, Any]]: ...
    def reset(self) -> None: ...


class ZeroController:
    """Applies no torque — the baseline that shows the task is not trivial."""

    def __init__(self, control_dim: int) -> None:
        self.control_dim = control_dim

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, dict[str, Any]]:
        return np.zeros(self.control_dim), {"success": True}

    def reset(self) -> None:
        pass


@dataclass(frozen=True)
class Episode:
    """One closed-loop run, sampled once per control period (``T`` periods).

    Attributes:
        time: ``(T+1,)`` seconds.
        q: ``(T+1, 4)`` observed orientation ``(w, x, y, z)``.
        omega: ``(T+1, 3)`` observed body-frame angular velocity.
        u: ``(T, m)`` applied controls.
        angle_from_goal: ``(T+1,)`` sign-invariant angle to the goal (rad).
        energy: ``(T+1,)`` MuJoCo's total energy (J).
        reward: ``(T,)`` the env's reward (minus its quadratic cost).
        controller_time_s: ``(T,)`` wall time of each controller call.
        controller_success: ``(T,)`` whether the controller solved (``info["success"]``).
        fallback: the controller's fallback per period (``None`` when it solved).
        control_period: seconds per period.
        controller_info: per period, the entries of :data:`RECORDED_INFO` the controller reported.
        latency: the mode the episode ran in: ``"none"``, ``"measured"`` or the fixed delay (s).
        compute_s: ``(T,)`` the delay charged to each period's torque (the controller's feedback
            time when measured, the fixed delay, or 0 in waiting mode); ``nan`` where the period's
            observation was skipped.
        busy_s: ``(T,)`` feedback plus preparation time per sampled period (``nan`` where skipped).
        feedback_s: ``(T,)`` wall time of the controller call alone, from the observation to the
            torque (``nan`` where skipped): the latency a real-time controller adds, in every mode.
        cpu_s: ``(T,)`` CPU time of the thread in the controller's call and preparation (``nan``
            where skipped): on a shared machine, wall time minus this is time spent waiting for a core.
        deadline_misses: periods whose busy time exceeded the control period.
        skipped: periods whose observation the controller could not take (still busy).
        states: ``(T+1, n)`` the whole observations (``(q, ω)``, or ``(x, q, v, ω)`` for a free body).
    """

    time: np.ndarray
    q: np.ndarray
    omega: np.ndarray
    u: np.ndarray
    angle_from_goal: np.ndarray
    energy: np.ndarray
    reward: np.ndarray
    controller_time_s: np.ndarray
    controller_success: np.ndarray
    fallback: list[str | None]
    control_period: float
    controller_info: list[dict[str, Any]]
    latency: Any = "none"
    compute_s: np.ndarray | None = None
    busy_s: np.ndarray | None = None
    cpu_s: np.ndarray | None = None
    feedback_s: np.ndarray | None = None
    deadline_misses: int = 0
    skipped: int = 0
    states: np.ndarray | None = None


@contextmanager
def _without_collection() -> Iterator[None]:
    """No automatic cyclic garbage collection inside (module docstring); one that came due runs at the
    first allocation after."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


@contextmanager
def _setup_frozen() -> Iterator[None]:
    """The objects that exist now out of the collector's scans until the end (module docstring); a caller's
    own freeze is left as it was."""
    ours = gc.get_freeze_count() == 0
    gc.freeze()
    try:
        yield
    finally:
        if ours:
            gc.unfreeze()


def run_episode(env: Any, controller: Controller, duration_s: float, reset_options: dict[str, Any] | None = None,
                seed: int | None = None, render: bool = False, progress: bool = False,
                description: str = "closed loop", latency: Latency = "none") -> tuple[Episode, list[np.ndarray]]:
    """Run ``controller`` on ``env`` for ``duration_s`` seconds; returns the episode and frames.

    Args:
        env: an :class:`envs.RigidBodyEnv` (or a wrapper of one).
        controller: see :class:`Controller`; reset before the episode. An optional ``prepare()``
            is called after each delivered torque (module docstring); an optional ``set_time(t)`` is
            told the time of each observation it takes (s since the episode's start: a controller
            tracking a time-varying reference); an optional ``observe_applied(u)`` is told, after each
            period, the torque the plant received over it (sub-step-weighted mean: with a latency, the
            previous torque acts for the period's first sub-steps) — what an estimator of the plant needs.
        duration_s: rounded to whole control periods.
        reset_options: passed to ``env.reset`` (``{"qpos": …, "qvel": …}`` or ``{"random": True}``).
        seed: passed to ``env.reset``.
        render: collect ``env.render()`` frames (the env needs ``render_mode="rgb_array"``).
        progress: show a progress bar.
        latency: ``"none"`` (waiting mode: the simulator waits for the controller), ``"measured"``
            (the measured compute time delays the torque, to the next MuJoCo sub-step) or a fixed
            delay in seconds ``≥ 0`` (deterministic; ``0.0`` is the waiting mode's dynamics).
    """
    from tqdm.auto import tqdm

    fixed_delay = check_latency(latency)
    base = env.unwrapped
    periods = int(round(duration_s / base.dt))
    frame_skip = int(base.frame_skip)
    substep = float(base.dt) / frame_skip
    observation, info = env.reset(seed=seed, options=reset_options)
    controller.reset()
    prepare = getattr(controller, "prepare", None)
    set_time = getattr(controller, "set_time", None)
    observe_applied = getattr(controller, "observe_applied", None)
    frames = [env.render()] if render else []
    attitude = base.space.layout.attitude(by="an episode's record (q, ω)")
    observations = [observation]
    angle, energy, times = [info["angle_from_goal"]], [info["energy"]], [info["time"]]
    controls, rewards, wall, success, fallback, recorded = [], [], [], [], [], []
    compute, busy, cpu, feedbacks = [], [], [], []
    applied = np.zeros(base.action_space.shape[0])  # the torque acting on the plant
    pending: tuple[int, np.ndarray] | None = None  # (global sub-step from which it acts, torque)
    free_at = 0  # global sub-step from which the controller can take an observation
    misses = skipped = 0
    bar = tqdm(range(periods), desc=description, disable=not progress, leave=False)
    with _setup_frozen():
        for k in bar:
            raise_if_interrupted()
            first = k * frame_skip
            if first >= free_at:
                if set_time is not None:
                    set_time(times[-1] - times[0])
                with _without_collection():  # a collection due runs while the plant steps
                    cpu_start = time.thread_time()
                    start = time.perf_counter()
                    u, controller_info = controller(observation)
                    feedback = time.perf_counter() - start
                    preparation = 0.0
                    if prepare is not None:
                        start = time.perf_counter()
                        prepare()
                        preparation = time.perf_counter() - start
                    cpu.append(time.thread_time() - cpu_start)
                feedbacks.append(feedback)
                u = np.asarray(u, dtype=float)
                if latency == "none":
                    delay, busy_time = 0.0, 0.0
                elif fixed_delay is None:  # measured
                    delay, busy_time = feedback, feedback + preparation
                else:
                    delay = busy_time = fixed_delay
                if busy_time > base.dt:
                    misses += 1
                pending = (first + _substeps(delay, substep), u)
                free_at = first + _substeps(busy_time, substep)
                wall.append(feedback + preparation)
                compute.append(delay)
                busy.append(feedback + preparation if fixed_delay is None else busy_time)
                success.append(bool(controller_info.get("success", True)))
                fallback.append(controller_info.get("fallback"))
                recorded.append({key: controller_info[key] for key in RECORDED_INFO if key in controller_info})
            else:  # still busy with an earlier observation: this one is lost
                skipped += 1
                wall.append(np.nan)
                compute.append(np.nan)
                busy.append(np.nan)
                cpu.append(np.nan)
                feedbacks.append(np.nan)
                success.append(True)
                fallback.append(None)
                recorded.append({"skipped": True})
            segments: list[tuple[int, np.ndarray]] = []
            if pending is not None and pending[0] < first + frame_skip:
                held = max(pending[0] - first, 0)
                if held > 0:
                    segments.append((held, applied))
                applied, pending = pending[1], None
                segments.append((frame_skip - held, applied))
            else:
                segments.append((frame_skip, applied))
            observation, reward, terminated, info = _step_segments(env, segments, frame_skip)
            if observe_applied is not None:
                observe_applied(sum(count * np.asarray(torque, dtype=float) for count, torque in segments) / frame_skip)
            observations.append(observation)
            controls.append(applied.copy())
            rewards.append(reward)
            angle.append(info["angle_from_goal"])
            energy.append(info["energy"])
            times.append(info["time"])
            if render:
                frames.append(env.render())
            bar.set_postfix(angle=f"{angle[-1]:.2f}", ms=f"{1e3 * wall[-1]:.1f}")
            if terminated:
                break
    states = np.array(observations)
    episode = Episode(
        time=np.asarray(times) - times[0],
        q=states[:, attitude.quaternion],
        omega=states[:, attitude.omega],
        u=np.array(controls),
        angle_from_goal=np.array(angle),
        energy=np.array(energy),
        reward=np.array(rewards),
        controller_time_s=np.array(wall),
        controller_success=np.array(success),
        fallback=fallback,
        control_period=float(base.dt),
        controller_info=recorded,
        latency=latency,
        compute_s=np.array(compute),
        busy_s=np.array(busy),
        cpu_s=np.array(cpu),
        feedback_s=np.array(feedbacks),
        deadline_misses=misses,
        skipped=skipped,
        states=states,
    )
    return episode, frames


def check_latency(latency: Any) -> float | None:
    """``None`` for ``"none"``/``"measured"``, else the fixed delay in seconds; ``ValueError`` if invalid."""
    if isinstance(latency, str):
        if latency not in ("none", "measured"):
            raise ValueError(f"latency must be 'none', 'measured' or seconds >= 0, got {latency!r}")
        return None
    delay = float(latency)
    if not (math.isfinite(delay) and delay >= 0.0):
        raise ValueError(f"a fixed latency must be finite seconds >= 0, got {latency!r}")
    return delay


def _substeps(seconds: float, substep: float) -> int:
    """Sub-steps of ``substep`` seconds until ``seconds`` have passed (the first boundary at or after)."""
    return int(math.ceil(seconds / substep - 1e-9)) if seconds > 0.0 else 0


def _step_segments(env: Any, segments: list[tuple[int, np.ndarray]], frame_skip: int) -> tuple[Any, float, bool, dict]:
    """Advance the plant one control period under piecewise-constant torques ``[(sub-steps, u), …]``.

    One segment is ``env.step(u)``. Several are calls of the plant's ``step(u, substeps=n)`` (MuJoCo
    integrates the same sub-steps, the torque changes between them); the reward is the
    sub-step-weighted mean of the segments' rewards, the observation the last one's.
    """
    if len(segments) == 1:
        observation, reward, terminated, _, info = env.step(segments[0][1])
        return observation, float(reward), terminated, info
    base = env.unwrapped
    total, terminated = 0.0, False
    for count, u in segments:
        observation, reward, done, _, info = base.step(u, substeps=count)
        total += reward * count / frame_skip
        terminated = terminated or done
    return observation, total, terminated, info


def time_inside_for_good(times: np.ndarray, outside: np.ndarray) -> float | None:
    """"Within tolerance from some time on", the rule every success criterion here is judged by: the first of
    ``times`` from which no sample is ``outside`` (a boolean per time) to the end; ``times[0]`` when none is,
    ``None`` when the last one is."""
    late = np.flatnonzero(outside)
    if late.size == 0:
        return float(times[0])
    first_inside_for_good = int(late[-1]) + 1
    if first_inside_for_good >= len(times):
        return None
    return float(times[first_inside_for_good])


def time_to_upright(episode: Episode, tolerance: float = UPRIGHT_TOLERANCE) -> float | None:
    """First time the angle to the goal is below ``tolerance`` and stays below it to the end."""
    return time_inside_for_good(episode.time, episode.angle_from_goal >= tolerance)


def episode_metrics(episode: Episode, upright_tolerance: float = UPRIGHT_TOLERANCE,
                    hold_tolerance: float = HOLD_TOLERANCE, hold_window_s: float = HOLD_WINDOW_S) -> dict[str, Any]:
    """Summary numbers of an episode.

    ``success``: upright (within ``upright_tolerance``) from some time on to the end.
    ``swung_up``: ``success`` and the largest angle over the last ``hold_window_s``
    (``hold_error_rad``) within ``hold_tolerance``. ``solve_time_ms`` is the whole controller call
    per sampled period (feedback plus any ``prepare()``); ``latency`` the mode the episode ran in,
    ``deadline_misses`` the periods whose compute exceeded the control period (:data:`NOT_MEASURED`
    in waiting mode), ``first_period_missed`` whether the first of them was one: the cold start,
    which a robot runs before its clock starts (:data:`NOT_MEASURED` in waiting mode).
    """
    reached = time_to_upright(episode, upright_tolerance)
    hold_mask = episode.time >= episode.time[-1] - hold_window_s
    hold_error = float(episode.angle_from_goal[hold_mask].max())
    times_ms = 1e3 * episode.controller_time_s
    times_ms = times_ms[np.isfinite(times_ms)]
    return {
        "success": reached is not None,
        "swung_up": reached is not None and hold_error <= hold_tolerance,
        "time_to_upright_s": reached,
        "hold_error_rad": hold_error,
        "solve_time_ms": {"median": float(np.median(times_ms)), "p95": float(np.percentile(times_ms, 95)),
                          "p99": float(np.percentile(times_ms, 99)), "max": float(times_ms.max())},
        "cpu_time_ms_median": float(np.nanmedian(1e3 * episode.cpu_s)) if episode.cpu_s is not None else None,
        "latency": episode.latency,
        "deadline_misses": NOT_MEASURED if episode.latency == "none" else int(episode.deadline_misses),
        "first_period_missed": NOT_MEASURED if episode.latency == "none" else first_period_missed(episode),
        "skipped_observations": int(episode.skipped),
        "controller_failures": int((~episode.controller_success).sum()),
        "max_abs_torque": float(np.abs(episode.u).max()),
        "accumulated_cost": float(-episode.reward.sum()),
        "control_period_s": episode.control_period,
        "duration_s": float(episode.time[-1]),
    }


def first_period_missed(episode: Episode) -> bool:
    """Whether the episode's first period — the cold call after ``reset()`` — ran past the control period."""
    busy = episode.busy_s
    return bool(busy is not None and busy.size > 0 and busy[0] > episode.control_period)


def plot_episode(episode: Episode, path: Any, title: str = "", torque_bound: float | None = None) -> None:
    """Angle to the goal, angular velocity, torque, energy and controller time per period, to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t, tc = episode.time, episode.time[:-1]
    figure, axes = plt.subplots(5, 1, figsize=(8, 10), sharex=True)
    axes[0].plot(t, episode.angle_from_goal)
    axes[0].axhline(UPRIGHT_TOLERANCE, color="tab:gray", ls=":", label=f"{UPRIGHT_TOLERANCE} rad")
    axes[0].set_ylabel("angle to goal (rad)")
    axes[0].legend(loc="upper right")
    for i, name in enumerate("xyz"):
        axes[1].plot(t, episode.omega[:, i], label=f"ω_{name}")
    axes[1].set_ylabel("ω (rad/s)")
    axes[1].legend(loc="upper right", ncol=3)
    for j in range(episode.u.shape[1]):
        axes[2].step(tc, episode.u[:, j], where="post", label=f"u_{j}")
    if torque_bound is not None:
        for sign in (-1, 1):
            axes[2].axhline(sign * torque_bound, color="tab:gray", ls=":")
    axes[2].set_ylabel("torque (N·m)")
    axes[3].plot(t, episode.energy)
    axes[3].set_ylabel("energy (J, MuJoCo)")
    axes[4].plot(tc[:episode.controller_time_s.size], 1e3 * episode.controller_time_s, ".", ms=3)
    axes[4].axhline(1e3 * episode.control_period, color="tab:red", ls="--", label="control period")
    axes[4].set_yscale("log")
    axes[4].set_ylabel("controller time (ms)")
    axes[4].set_xlabel("time (s)")
    axes[4].legend(loc="upper right")
    if title:
        axes[0].set_title(title)
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def write_video(frames: list[np.ndarray], path: Any, fps: float) -> None:
    """Write ``frames`` as an MP4 (H.264 through imageio's ffmpeg)."""
    import imageio.v2 as imageio

    imageio.mimwrite(str(path), frames, fps=fps, macro_block_size=1)
