"""What a scene calls for: its plant, its planning model and its controllers, with settings
derived from the scene's own scales.

Every command, study and notebook builds these through the functions here, so that "the model
for a scene" and "the MPC for a scene" mean one thing:

* :func:`scene_env` — the scene's :class:`~fvin_mpc.envs.RigidBodyEnv`, its control period taken
  from ``control_period``, else the checkpoint's step, else the scene's;
* :func:`scene_model` — a checkpoint's model or the closed-form body read off the MJCF, checked
  against the env (step size, control dimension);
* :func:`scene_mpc_settings` / :func:`scene_mpc` — :class:`~fvin_mpc.control.mpc.MPC` with the
  scene's goal, rest and torque bounds, and settings derived from its scales;
* :func:`scene_energy_shaping` — energy pumping + LQR catch on the same model.

Defaults from scales (:func:`default_mpc_settings`). The MPC's cost weights were tuned on the
``pendulum`` scene (Pendulum-v1's rod: energy span 10 J, ``J = 1/3``, ``|u| ≤ 2``, ``h = 0.05``). A
new scene gets the same cost *in its own units*: angular velocities measured against the speed
scale ``ω_s = √(2 ΔE / J_max)`` (the speed that carries the body over the whole energy span ``ΔE``
between rest and goal), controls against the actuator bound, stage weights per second of horizon
(``∝ h``), and a horizon of the same number of natural periods (``∝ 1/ω_s``). The terminal
energy-deficit term is already relative to ``ΔE``. On the ``pendulum`` scene these are exactly
:class:`~fvin_mpc.control.mpc.MPCSettings`' numbers. The scales are the scene's physics (read off
its MJCF), so the learned and the closed-form model get the same settings on the same scene.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from fvin_mpc.control.energy_shaping import EnergyShapingController, EnergyShapingNotApplicable, EnergyShapingSettings
from fvin_mpc.control.model_export import ExportedModel, from_checkpoint, from_closed_form
from fvin_mpc.control.mpc import COLD_STARTS, MPC, MPCSettings
from fvin_mpc.control.presets import preset_for
from fvin_mpc.control.rti import RealTimeMPC
from fvin_mpc.core.checkpoint import Checkpoint, CheckpointError, load_checkpoint
from fvin_mpc.core.rigid_body import from_mujoco
from fvin_mpc.envs import RigidBodyEnv
from fvin_mpc.envs.scenes import resolve_scene


@dataclass(frozen=True)
class SceneScales:
    """The scales a scene's default MPC settings are derived from.

    Attributes:
        energy_span: ``|U(goal) − U(rest)|`` (J).
        speed: ``ω_s = √(2·energy_span / J_max)`` (rad/s), ``J_max`` the largest principal
            inertia about the pivot.
        torque: the largest actuator *torque* (N·m): control bound × the actuator's gear (the norm
            of its body-frame torque per unit control) — what a swing-up compares with gravity.
        step_size: the control period ``h`` (s).
        control: the largest actuator bound ``max |u|`` (the controls' own units): what the
            control weight is measured against. ``None``: the same as ``torque`` (unit gear).
    """

    energy_span: float
    speed: float
    torque: float
    step_size: float
    control: float | None = None

    @property
    def control_bound(self) -> float:
        return self.torque if self.control is None else self.control


#: The scales of the ``pendulum`` scene, on which :class:`MPCSettings`' numbers were tuned.
REFERENCE_SCALES = SceneScales(energy_span=10.0, speed=math.sqrt(60.0), torque=2.0, step_size=0.05)
#: The terminal energy-deficit weight a scene gets unless it declares otherwise (docs/evaluation.md:
#: with it a 1.5 s horizon swings the pendulum up from every start).
DEFAULT_TERMINAL_ENERGY_WEIGHT = 1000.0
#: A scene's real-time iteration restarts cold when the measured ω leaves the plan's prediction by more
#: than this fraction of the speed scale ``ω_s`` (``RTIOptions.restart_speed``): far above a model's
#: error over one period (the learned damped pendulum's nominal episodes: 2 restarts in 50), below a
#: knock (2 rad/s = 0.26 ω_s there: 50 of 50 knocked episodes recover, 25 without).
RESTART_SPEED_FRACTION = 0.13
#: The longest default horizon (steps), whatever the control period a caller forces: the horizon
#: follows the scene's natural period, but past this the terminal energy-deficit term does the
#: look-ahead (a scene at its own period, ``envs.rigid_body_env.scale_control_period``, gets about
#: the reference's 30 steps; a forced fine period would otherwise give hundreds, and solves of
#: hundreds of milliseconds).
MAX_DEFAULT_HORIZON = 60


def scene_scales(env: Any) -> SceneScales:
    """The :class:`SceneScales` of a scene's physics: read off its MJCF (the closed-form body of
    :func:`~fvin_mpc.core.rigid_body.from_mujoco`, through the env's ``energy_span`` and
    ``speed_scale``, which also choose its default control period), not off a planning model, so
    that a learned and the closed-form model get the same settings on the same scene.

    Raises:
        ValueError: the actuator bounds are not finite, goal and rest have the same potential, or
            the body is one ``from_mujoco`` cannot read (pass the settings explicitly then).
    """
    base = env.unwrapped
    bounds = np.maximum(np.abs(base.torque_low), np.abs(base.torque_high))
    if not np.all(np.isfinite(bounds)):
        raise ValueError("deriving MPC settings from the scene's scales needs finite actuator bounds "
                         "(declare actuator limits, or pass the MPC settings explicitly)")
    axes = np.asarray(from_mujoco(base.model, base.body_name).actuator_axes, dtype=float)
    torques = bounds * np.linalg.norm(axes, axis=0)
    return SceneScales(energy_span=base.energy_span, speed=base.speed_scale, torque=float(torques.max()),
                       step_size=float(base.dt), control=float(bounds.max()))


def goal_symmetry_axis(env: Any) -> tuple[float, float, float] | None:
    """The body-frame axis about which a scene's goal is a set (:attr:`MPCSettings.free_axis`), or ``None``.

    A ball joint whose actuators' gears span only two directions cannot act on the spin about the
    centre of mass's direction upright (that spin is left to gravity's symmetry, the same at every
    turn about the vertical): its goal is "centre of mass straight up", any turn about it. Every
    other pivoted body (a hinge, a ball with three independent actuators) and free bodies: ``None``.
    """
    base = env.unwrapped
    if getattr(base, "joint_type", None) != "ball":
        return None
    gears = np.asarray(base.model.actuator_gear[:, :3], dtype=float)
    if np.linalg.matrix_rank(gears, tol=1e-9) >= 3:
        return None
    center = np.asarray(from_mujoco(base.model, base.body_name).center_of_mass, dtype=float)
    if np.linalg.norm(center) < 1e-12:
        return None  # balanced on the pivot: no gravity, no symmetry axis to speak of
    return tuple(float(c) for c in center / np.linalg.norm(center))


def default_mpc_settings(scales: SceneScales) -> MPCSettings:
    """:class:`MPCSettings` whose costs mean on ``scales`` what the defaults mean on the pendulum.

    Multi-start cold solves (every guess of :data:`~fvin_mpc.control.mpc.COLD_STARTS`) and the
    terminal energy-deficit cost are on: the controller the evaluation reports. The horizon is at
    most :data:`MAX_DEFAULT_HORIZON` steps.
    """
    reference, base = REFERENCE_SCALES, MPCSettings()
    per_second = scales.step_size / reference.step_size  # stage weights are a rate × h
    speed = (reference.speed / scales.speed) ** 2  # weights on |ω|² in units of ω_s
    control = (reference.control_bound / scales.control_bound) ** 2  # weights on |u|² in units of u_max
    horizon_s = base.horizon * reference.step_size * reference.speed / scales.speed
    tidy = lambda value: float(f"{value:.10g}")  # noqa: E731  (the reference's own numbers, not 0.0999…)
    return replace(
        base,
        horizon=min(MAX_DEFAULT_HORIZON, max(1, round(horizon_s / scales.step_size))),
        orientation_weight=tidy(base.orientation_weight * per_second),
        omega_weight=tidy(base.omega_weight * speed * per_second),
        control_weight=tidy(base.control_weight * control * per_second),
        terminal_omega_weight=tidy(base.terminal_omega_weight * speed),
        terminal_energy_weight=DEFAULT_TERMINAL_ENERGY_WEIGHT,
        cold_starts=COLD_STARTS,
        rti=replace(base.rti, restart_speed=tidy(RESTART_SPEED_FRACTION * scales.speed)),
    )


#: MPCSettings fields a command line may set (``None`` leaves the scene's value).
SETTING_NAMES = frozenset(f.name for f in fields(MPCSettings))


def scene_mpc_settings(env: Any, **overrides: Any) -> MPCSettings:
    """The settings :func:`scene_mpc` uses: derived from the scene's scales
    (:func:`default_mpc_settings`), then a built-in scene's preset for the solver in use
    (:mod:`fvin_mpc.control.presets`), then ``overrides`` (``None`` values ignored, so CLI options
    can be passed through as they are)."""
    unknown = set(overrides) - SETTING_NAMES
    if unknown:
        raise ValueError(f"unknown MPC settings {sorted(unknown)}; expected some of {sorted(SETTING_NAMES)}")
    settings = replace(default_mpc_settings(scene_scales(env)), free_axis=goal_symmetry_axis(env))
    preset = preset_for(env.unwrapped.scene_spec)
    given = {k: v for k, v in overrides.items() if v is not None}
    solver = given.get("solver", preset.settings.get("solver", settings.solver))
    return settings.updated(**preset.fields_for(solver)).updated(**given)


def scene_env(scene: Any = "pendulum", checkpoint: Any = None, true_model: bool = False,
              control_period: float | None = None, **env_options: Any) -> Any:
    """The scene's env, stepping at ``control_period``, else at the step of the checkpoint that will
    plan on it (unless ``true_model``), else at the scene's period. ``env_options`` go to
    :class:`~fvin_mpc.envs.RigidBodyEnv` (``body``, ``goal``, ``render_mode``, …)."""

    spec = resolve_scene(scene)
    if control_period is None and not true_model:
        control_period = _checkpoint(checkpoint or spec.default_checkpoint).config.step_size
    return RigidBodyEnv(scene=spec, control_period=control_period, **env_options)


def scene_model(env: Any, checkpoint: Any = None, true_model: bool = False,
                newton_iters: int | None = None) -> ExportedModel:
    """The model a controller plans with on ``env``: ``checkpoint`` (object, shipped name or path;
    default: the scene's), or with ``true_model`` the closed-form body read off the scene's MJCF at
    the env's control period.

    Raises:
        CheckpointError: (a ``ValueError``) the model's states are not the env's (another
            configuration space's layout), its step differs from the env's control period, or its
            number of controls from the env's actuators.
    """
    base = env.unwrapped
    if true_model:
        body = base.space.closed_form(base.model, base.body_name)
        return from_closed_form(base.space, body, base.dt, newton_iters or 2, name=f"true_{base.scene_spec.name}")
    model = from_checkpoint(_checkpoint(checkpoint or base.scene_spec.default_checkpoint), newton_iters)
    if model.space.layout != base.space.layout:
        raise CheckpointError(f"model {model.name!r} is on {model.space.description}, states "
                              f"{model.space.layout.name}; scene {base.scene_spec.name!r} observes "
                              f"{base.space.layout.name}")
    if abs(model.step_size - base.dt) > 1e-9:
        raise CheckpointError(f"the model's step {model.step_size} s differs from the scene's control period "
                              f"{base.dt} s; make the env with scene_env(..., checkpoint=...) or pass a matching "
                              "control period")
    if model.control_dim != base.action_space.shape[0]:
        raise CheckpointError(f"the model has {model.control_dim} controls, the scene {base.action_space.shape[0]}")
    return model


def scene_mpc(env: Any, model: ExportedModel, settings: MPCSettings | None = None) -> MPC | RealTimeMPC:
    """An :class:`MPC` on the scene's task: its goal, rest and torque bounds; ``settings`` default
    to :func:`scene_mpc_settings`. With ``settings.solver == "rti"`` the real-time iteration
    :class:`~fvin_mpc.control.rti.RealTimeMPC` (same problem, bounded compute per call)."""
    base = env.unwrapped
    settings = scene_mpc_settings(env) if settings is None else settings
    if settings.solver == "rti":

        return RealTimeMPC(model, settings, base.goal, base.torque_low, base.torque_high, rest=base.rest,
                           goal_set=base.scene_spec.goal_set)
    return MPC(model, settings, base.goal, base.torque_low, base.torque_high, rest=base.rest,
               goal_set=base.scene_spec.goal_set)


def scene_energy_shaping(env: Any, model: ExportedModel,
                         settings: EnergyShapingSettings = EnergyShapingSettings()) -> EnergyShapingController:
    """Energy pumping + LQR catch on ``model`` (learned or closed form) for the scene's task.

    Raises:
        EnergyShapingNotApplicable: the scene's joint is not a hinge. On a ball joint, reaching
            the upright energy does not bring the body upright (the energy can sit in a conical
            swing or a spin about the vertical), so the swing-up law does not apply.
    """
    base = env.unwrapped
    if base.joint_type != "hinge":
        raise EnergyShapingNotApplicable(
            f"energy shaping needs a single hinge; the scene's joint is a {base.joint_type} joint, on which "
            "reaching the upright energy does not mean reaching upright (conical swings, spin)")
    return EnergyShapingController.from_model(model, base.goal, base.torque_low, base.torque_high, base.rest, settings)


def _checkpoint(checkpoint: Checkpoint | str | Path) -> Checkpoint:
    return checkpoint if isinstance(checkpoint, Checkpoint) else load_checkpoint(checkpoint)
