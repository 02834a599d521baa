"""Which random scenes (:mod:`fvin_mpc.envs.families`) enter a family: the closed-form controller
must swing them up.

:func:`feasible` runs the MPC on the closed-form body read off the MJCF (what
``python -m fvin_mpc.swingup --scene PATH --true-model`` runs: :func:`~fvin_mpc.control.scene.scene_env`,
``scene_model(true_model=True)``, :func:`~fvin_mpc.control.scene.scene_mpc` with the scene's default
settings) from hanging at rest, for the duration the swing-up command derives from the scene's
scales (:func:`swingup_duration`), and judges it by the evaluation's criterion:
within 0.1 rad of upright from some time on, and within 0.05 rad over the last 3 s. It never looks
at a learned model. It runs in **waiting mode** (``latency="none"``) by default: it asks whether
the physics can be swung up by this controller, not whether the controller keeps real time.

A ball scene with 2 actuators cannot act on the spin about its long axis when upright, so it is
judged on *tilt* (the angle between the centre of mass's direction and straight up) instead of the
whole orientation; so is every run :func:`judged_angles` is asked to judge that way.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from fvin_mpc.control.closed_loop import (
    HOLD_TOLERANCE,
    HOLD_WINDOW_S,
    UPRIGHT_TOLERANCE,
    Episode,
    episode_metrics,
    run_episode,
    time_inside_for_good,
)
from fvin_mpc.control.scene import goal_symmetry_axis
from fvin_mpc.core.rigid_body import from_mujoco
from fvin_mpc.core.s3 import axis_angle
from fvin_mpc.envs.families import write_family


def judged_on(env: Any) -> str:
    """``"tilt"`` for a ball joint whose actuators span only two directions (nothing acts on the spin
    about the long axis upright), else ``"orientation"``."""
    return "orientation" if goal_symmetry_axis(env) is None else "tilt"


def tilt_angles(env: Any, quaternions: np.ndarray) -> np.ndarray:
    """Angle (rad) between the centre of mass's direction at each orientation and at the goal."""

    base = env.unwrapped
    c = np.asarray(from_mujoco(base.model, base.body_name).center_of_mass, dtype=float)
    axis = tuple(c / np.linalg.norm(c))
    return np.array([axis_angle(tuple(q), tuple(base.goal), axis) for q in quaternions])


def judged_angles(env: Any, episode: Episode, how: str | None = None) -> np.ndarray:
    """The angle series a run is judged on: the episode's angle to the goal, or the tilt."""
    how = how or judged_on(env)
    return episode.angle_from_goal if how == "orientation" else tilt_angles(env, episode.q)


def judge(times: np.ndarray, angles: np.ndarray) -> dict[str, Any]:
    """The evaluation's criterion on an angle series: upright (within :data:`UPRIGHT_TOLERANCE`) from
    some time on to the end, and within :data:`HOLD_TOLERANCE` over the last :data:`HOLD_WINDOW_S`."""
    reached = time_inside_for_good(times, angles >= UPRIGHT_TOLERANCE)
    hold = float(angles[times >= times[-1] - HOLD_WINDOW_S].max())
    return {
        "swung_up": reached is not None and hold <= HOLD_TOLERANCE,
        "time_to_upright_s": reached,
        "hold_error_rad": hold,
    }


class StopWhenHeld:
    """A Gymnasium wrapper that ends an episode (``terminated``) once the judged angle has stayed within
    :data:`HOLD_TOLERANCE` for :data:`HOLD_WINDOW_S` (plus one period): from there the criterion is met
    on the episode so far, and a filter need not spend the rest of the duration confirming it."""

    def __init__(self, env: Any, how: str) -> None:
        self.env, self.how, self._since = env, how, None

    def __getattr__(self, name: str) -> Any:
        return getattr(self.env, name)

    @property
    def unwrapped(self) -> Any:
        return self.env.unwrapped

    def reset(self, **kwargs: Any) -> Any:
        self._since = None
        return self.env.reset(**kwargs)

    def step(self, action: Any) -> Any:
        observation, reward, terminated, truncated, info = self.env.step(action)
        base = self.env.unwrapped
        angle = (
            info["angle_from_goal"] if self.how == "orientation"
            else float(tilt_angles(base, [base.state()[base.space.layout.attitude(by="tilt").quaternion]])[0])
        )
        if angle <= HOLD_TOLERANCE:
            self._since = info["time"] if self._since is None else self._since
            if info["time"] - self._since >= HOLD_WINDOW_S + base.dt:
                terminated = True
        else:
            self._since = None
        return observation, reward, terminated, truncated, info


def run_judged(
    env: Any,
    controller: Any,
    duration_s: float,
    reset_options: dict[str, Any] | None = None,
    latency: Any = "none",
    seed: int | None = None,
    stop_when_held: bool = False,
) -> tuple[Episode, dict[str, Any]]:
    """One episode and its summary: :func:`episode_metrics` with ``swung_up``, ``time_to_upright_s`` and
    ``hold_error_rad`` taken on the angle the scene is judged on (:func:`judged_on`). With
    ``stop_when_held`` the episode ends early once the hold criterion is met (:class:`StopWhenHeld`)."""
    how = judged_on(env)
    plant = StopWhenHeld(env, how) if stop_when_held else env
    episode, _ = run_episode(plant, controller, duration_s, reset_options, seed=seed, latency=latency)
    metrics = episode_metrics(episode)
    metrics.update(judge(episode.time, judged_angles(env, episode, how)), judged_on=how)
    return episode, metrics


#: The longest closed loop the filter runs (s): a scene the closed form cannot swing up and hold within it
#: is rejected.
MAX_FILTER_DURATION_S = 40.0


#: The swing-up command's shortest default episode (``fvin_mpc.swingup.MIN_DEFAULT_DURATION_S``).
MIN_DURATION_S = 10.0


def swingup_duration(env: Any) -> float:
    """The swing-up command's default duration on the scene's scales, with the actuators' torque counted
    through their gear (``scene_scales().torque``): ``(1 + peak gravity torque / motor torque)`` natural periods
    plus the hold window, at least 10 s — ``fvin_mpc.swingup.default_duration``'s rule, restated here
    because a library module does not import a command (tests check the two agree)."""
    from fvin_mpc.control.scene import scene_scales

    scales = scene_scales(env)
    natural_period = 4.0 * math.pi / scales.speed
    swing_up_s = (1.0 + scales.energy_span / 2.0 / scales.torque) * natural_period
    return max(MIN_DURATION_S, swing_up_s + HOLD_WINDOW_S)


def feasible(
    scene_path: str | Path,
    duration_s: float | None = None,
    latency: Any = "none",
    max_duration_s: float = MAX_FILTER_DURATION_S,
    **settings: Any,
) -> tuple[bool, dict[str, Any]]:
    """Whether the closed-form MPC swings the scene up from hanging at rest; ``(ok, facts)``.

    Args:
        scene_path: the MJCF.
        duration_s: seconds of closed loop; ``None``: the swing-up command's default for the scene's
            scales (:func:`swingup_duration`), at most ``max_duration_s``. The episode stops early once
            the hold criterion is met (:class:`StopWhenHeld`).
        latency: :func:`~fvin_mpc.control.closed_loop.run_episode`'s mode; the waiting mode by default.
        settings: MPC setting overrides (``None`` values ignored), e.g. ``compile="none"``.

    A scene the package refuses (``ValueError``: an unsupported feature, no task) is infeasible, the
    error's first line in ``facts["error"]``.
    """
    from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings, scene_scales

    start = time.perf_counter()
    facts: dict[str, Any] = {"scene": str(scene_path), "latency": latency}
    try:
        env = scene_env(str(scene_path), true_model=True)
        scales = scene_scales(env)
        model = scene_model(env, true_model=True)
        controller = scene_mpc(env, model, scene_mpc_settings(env, **settings))
    except ValueError as error:
        facts.update(ok=False, error=str(error).splitlines()[0], wall_s=time.perf_counter() - start)
        return False, facts
    wanted = swingup_duration(env) if duration_s is None else float(duration_s)
    duration = min(wanted, max_duration_s)
    build_s = time.perf_counter() - start
    _, metrics = run_judged(env, controller, duration, latency=latency, stop_when_held=True)
    env.close()
    facts.update(
        ok=bool(metrics["swung_up"]),
        swung_up=bool(metrics["swung_up"]),
        judged_on=metrics["judged_on"],
        time_to_upright_s=metrics["time_to_upright_s"],
        hold_error_rad=metrics["hold_error_rad"],
        duration_s=duration,
        duration_wanted_s=wanted,
        simulated_s=metrics["duration_s"],
        control_period_s=metrics["control_period_s"],
        horizon=controller.settings.horizon,
        solve_time_ms_median=metrics["solve_time_ms"]["median"],
        controller_failures=metrics["controller_failures"],
        accumulated_cost=metrics["accumulated_cost"],
        energy_span=scales.energy_span,
        speed_scale=scales.speed,
        torque_bound=scales.torque,
        build_s=build_s,
        wall_s=time.perf_counter() - start,
    )
    return facts["ok"], facts


def filter_family(kind: str, seeds: Iterable[int], directory: str | Path, **options: Any) -> dict[str, Any]:
    """Write each seed's scene into ``directory`` and run :func:`feasible` on it: ``{"members": [seeds
    that entered], "rejected": [...], "rejection_rate": …, "facts": {seed: facts}}``."""

    members, rejected, per_seed = [], [], {}
    for seed in seeds:
        (path,) = write_family(kind, [seed], directory)
        ok, facts = feasible(path, **options)
        per_seed[int(seed)] = facts
        (members if ok else rejected).append(int(seed))
    total = len(members) + len(rejected)
    return {
        "family": kind,
        "members": members,
        "rejected": rejected,
        "rejection_rate": len(rejected) / total if total else float("nan"),
        "facts": per_seed,
    }
