"""Closed-loop episodes of a controller on a scene's Gymnasium environment, and their metrics.

Every controller in the package (:class:`~fvin_mpc.control.mpc.MPC`,
:class:`~fvin_mpc.control.energy_shaping.EnergyShapingController`, :class:`ZeroController`) is a
callable ``u, info = controller(x)`` with a ``reset()``; :func:`run_episode` drives
one on an :class:`envs.RigidBodyEnv` (MuJoCo is the plant) and records an :class:`Episode`;
:func:`episode_metrics` turns it into the numbers the CLIs report.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

#: Upright means within this angle of the goal (rad) …
UPRIGHT_TOLERANCE = 0.1
#: … and holding means staying within this angle over the last :data:`HOLD_WINDOW_S` seconds.
HOLD_TOLERANCE = 0.05
HOLD_WINDOW_S = 3.0


#: The scalar entries of a controller's ``info`` an :class:`Episode` keeps per period (the plan
#: itself is left out: it would make episodes heavy).
RECORDED_INFO = ("status", "iterations", "solve_time_s", "step_residual", "fallback", "cold_start")


class Controller(Protocol):
    """``u, info = controller(x)`` from the measured state ``x = (q, ω)`` ``(7,)``; ``reset()`` between episodes."""

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


def run_episode(env: Any, controller: Controller, duration_s: float, reset_options: dict[str, Any] | None = None,
                seed: int | None = None, render: bool = False, progress: bool = False,
                description: str = "closed loop") -> tuple[Episode, list[np.ndarray]]:
    """Run ``controller`` on ``env`` for ``duration_s`` seconds; returns the episode and frames.

    Args:
        env: an :class:`envs.RigidBodyEnv` (or a wrapper of one).
        controller: see :class:`Controller`; reset before the episode.
        duration_s: rounded to whole control periods.
        reset_options: passed to ``env.reset`` (``{"qpos": …, "qvel": …}`` or ``{"random": True}``).
        seed: passed to ``env.reset``.
        render: collect ``env.render()`` frames (the env needs ``render_mode="rgb_array"``).
        progress: show a progress bar.
    """
    from tqdm.auto import tqdm

    base = env.unwrapped
    periods = int(round(duration_s / base.dt))
    observation, info = env.reset(seed=seed, options=reset_options)
    controller.reset()
    frames = [env.render()] if render else []
    q, omega = [observation[:4]], [observation[4:]]
    angle, energy, times = [info["angle_from_goal"]], [info["energy"]], [info["time"]]
    controls, rewards, wall, success, fallback, recorded = [], [], [], [], [], []
    bar = tqdm(range(periods), desc=description, disable=not progress, leave=False)
    for _ in bar:
        start = time.perf_counter()
        u, controller_info = controller(observation)
        wall.append(time.perf_counter() - start)
        observation, reward, terminated, truncated, info = env.step(u)
        q.append(observation[:4])
        omega.append(observation[4:])
        controls.append(np.asarray(u, dtype=float))
        rewards.append(reward)
        angle.append(info["angle_from_goal"])
        energy.append(info["energy"])
        times.append(info["time"])
        success.append(bool(controller_info.get("success", True)))
        fallback.append(controller_info.get("fallback"))
        recorded.append({key: controller_info[key] for key in RECORDED_INFO if key in controller_info})
        if render:
            frames.append(env.render())
        bar.set_postfix(angle=f"{angle[-1]:.2f}", ms=f"{1e3 * wall[-1]:.1f}")
        if terminated:
            break
    episode = Episode(
        time=np.asarray(times) - times[0], q=np.array(q), omega=np.array(omega), u=np.array(controls),
        angle_from_goal=np.array(angle), energy=np.array(energy), reward=np.array(rewards),
        controller_time_s=np.array(wall), controller_success=np.array(success), fallback=fallback,
        control_period=float(base.dt), controller_info=recorded,
    )
    return episode, frames


def time_to_upright(episode: Episode, tolerance: float = UPRIGHT_TOLERANCE) -> float | None:
    """First time the angle to the goal is below ``tolerance`` and stays below it to the end."""
    outside = np.flatnonzero(episode.angle_from_goal >= tolerance)
    if outside.size == 0:
        return float(episode.time[0])
    first_inside_for_good = int(outside[-1]) + 1
    if first_inside_for_good >= episode.time.size:
        return None
    return float(episode.time[first_inside_for_good])


def episode_metrics(episode: Episode, upright_tolerance: float = UPRIGHT_TOLERANCE,
                    hold_tolerance: float = HOLD_TOLERANCE, hold_window_s: float = HOLD_WINDOW_S) -> dict[str, Any]:
    """Summary numbers of an episode.

    ``success``: upright (within ``upright_tolerance``) from some time on to the end.
    ``swung_up``: ``success`` and the largest angle over the last ``hold_window_s``
    (``hold_error_rad``) within ``hold_tolerance``.
    """
    reached = time_to_upright(episode, upright_tolerance)
    hold_mask = episode.time >= episode.time[-1] - hold_window_s
    hold_error = float(episode.angle_from_goal[hold_mask].max())
    times_ms = 1e3 * episode.controller_time_s
    return {
        "success": reached is not None,
        "swung_up": reached is not None and hold_error <= hold_tolerance,
        "time_to_upright_s": reached,
        "hold_error_rad": hold_error,
        "solve_time_ms": {"median": float(np.median(times_ms)), "p95": float(np.percentile(times_ms, 95)),
                          "max": float(times_ms.max())},
        "controller_failures": int((~episode.controller_success).sum()),
        "max_abs_torque": float(np.abs(episode.u).max()),
        "accumulated_cost": float(-episode.reward.sum()),
        "control_period_s": episode.control_period,
        "duration_s": float(episode.time[-1]),
    }


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
    axes[4].plot(tc, 1e3 * episode.controller_time_s, ".", ms=3)
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
