"""Swing a MuJoCo pendulum up with IPOPT MPC on the learned S3FVIN: ``python -m fvin_mpc.swingup``.

With no arguments: the shipped sign-invariant model of the ``pendulum`` scene, starting
hanging at rest, 10 s of closed loop in MuJoCo, a summary on stdout and a plot in
``swingup.png``. ``--true-model`` runs the same MPC on the closed-form rigid body read
off the scene's MJCF, for comparison.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any


from fvin_mpc.control.export import ExportedModel, from_checkpoint, from_rigid_body
from fvin_mpc.control.mpc import MPC, MPCSettings


#: MPCSettings fields a built-in scene changes from the defaults (the CLI's options override them).
#: ``spherical_pendulum``: 1.5 N·m against 6 N·m of gravity torque about a slower axis (J ≈ 0.5)
#: needs several pumps; with the default 1.5 s horizon the plan stalls near the bottom, with
#: 2.5 s it swings up (docs/spherical.md). Cold solves from rest take ≈ 130 IPOPT iterations,
#: so the default limit of 100 would leave the body hanging (the zero fallback at rest).
#: ``pendulum_damped``: at horizons 30 and 40 the plan settles on a local optimum that never
#: swings up, with the learned and the closed-form model alike; 2.5 s escapes it (docs/scenes.md).
#: ``pendulum``: the 1.5 s horizon is shorter than a swing-up from near hanging; without the
#: terminal energy cost 1 of 50 evaluation episodes (learned and closed-form alike) never pumps
#: (docs/evaluation.md). The weight makes a full energy deficit cost 1000, against ≤ 40 for the
#: terminal orientation: near upright its gradient vanishes (the deficit is quadratic there).
SCENE_SETTINGS: dict[str, dict[str, Any]] = {
    "pendulum": {"terminal_energy_weight": 1000.0},
    "pendulum_damped": {"horizon": 50},
    "spherical_pendulum": {"horizon": 50, "max_iter": 300},
}


def scene_settings(scene: str, **overrides: Any) -> MPCSettings:
    """:class:`MPCSettings` for ``scene``: the defaults, the scene's :data:`SCENE_SETTINGS`, then ``overrides``."""
    fields = {**SCENE_SETTINGS.get(str(scene), {}), **{k: v for k, v in overrides.items() if v is not None}}
    return replace(MPCSettings(), **fields)


def default_checkpoint(scene: str) -> str:
    """The shipped sign-invariant checkpoint of a built-in scene."""
    return f"{Path(scene).stem}_sign-invariant"


def scene_model(env: Any, checkpoint: str | None = None, true_model: bool = False,
                newton_iters: int | None = None) -> ExportedModel:
    """The model the MPC plans with: a checkpoint's, or the scene's closed-form rigid body.

    Raises ``ValueError`` if the model's step differs from the env's control period.
    """
    from fvin_mpc.core.rigid_body import from_mujoco

    base = env.unwrapped
    if true_model:
        body = from_mujoco(base.model, base.body_name)
        return from_rigid_body(body, base.dt, newton_iters or 2, name=f"true_{getattr(base.scene_spec, 'name', 'scene')}")
    model = from_checkpoint(checkpoint, newton_iters)
    if abs(model.step_size - base.dt) > 1e-9:
        raise ValueError(f"the model's step {model.step_size} s differs from the scene's control period {base.dt} s")
    if model.control_dim != base.action_space.shape[0]:
        raise ValueError(f"the model has {model.control_dim} controls, the scene {base.action_space.shape[0]}")
    return model


def scene_mpc(env: Any, model: ExportedModel, settings: MPCSettings = MPCSettings(), goal: Any = None) -> MPC:
    """An :class:`MPC` with the scene's goal and torque bounds."""
    base = env.unwrapped
    return MPC(model, settings, base.goal if goal is None else goal, base.torque_low, base.torque_high)
