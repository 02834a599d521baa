"""What training knows per configuration space: defaults, the training layout's scales, reports.

``python -m fvin_mpc.train`` trains every space with one loop (:func:`fvin_mpc.learning.training.train`)
and one command; :func:`training_for` gives what differs by space (:class:`SpaceTraining`): the
optimization settings that differ from :class:`~fvin_mpc.learning.training.TrainSettings`'
defaults, the scales of the training layout's ``rest`` (a free body's loss
``4(1 − ⟨q̂, q⟩²) + omega_weight·(s_x²|x̂ − x|² + s_v²|v̂ − v|² + |ω̂ − ω|²)``) and a report of a
trained model. A space without an entry trains with the generic defaults.

The free body's report: the held-out open-loop error over 1 s of the learned model against the
closed-form model through the same integrator (:func:`open_loop_errors`) and the recovered mass and
inertia (:func:`recovered_parameters`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Callable, Mapping

import numpy as np

from fvin_mpc.core import fvin_r3s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.data import Trajectories
from fvin_mpc.core.errors import DataFileError
from fvin_mpc.core.networks_r3s3 import LearnedCombinedTerms, R3S3Config, physical_scale
from fvin_mpc.core.quadrotor import from_mujoco
from fvin_mpc.core.space import R3S3, ConfigurationSpace, space_for_variant, space_of_config
from fvin_mpc.envs import QuadrotorEnv
from fvin_mpc.envs.scenes import load_model, resolve_scene
from fvin_mpc.learning.training import scene_has_joint_damping, scene_hinge_axis, scene_vertical, train

#: Position and velocity scales of the free body's loss (1/m, s/m): 1 mm of position error weighs as 0.03 rad/s.
POSITION_SCALE, VELOCITY_SCALE = 30.0, 10.0


@dataclass(frozen=True)
class SpaceTraining:
    """How the training command treats the models of one configuration space.

    Attributes:
        settings: :class:`~fvin_mpc.learning.training.TrainSettings` fields that differ from its defaults.
        rest_scale: per-entry scales of the training layout's ``rest`` (``None``: all 1).
        report: ``(weights, config, data, test_data or None) → dict``, written to the checkpoint's
            ``evaluation`` and printed; ``None``: no report.
        evaluate: ``(checkpoint, test_data) → dict``, the command's ``--evaluate`` (no training);
            ``None``: the space has none.
        optimizers: the optimizers the space's models train with (``None``: any).
    """

    settings: Mapping[str, Any] = field(default_factory=dict)
    rest_scale: tuple[float, ...] | None = None
    report: Callable[[Mapping[str, Any], Any, Trajectories, Trajectories | None], dict[str, Any]] | None = None
    evaluate: Callable[[Any, Trajectories], dict[str, Any]] | None = None
    optimizers: tuple[str, ...] | None = None


def free_body_report(weights: Mapping[str, Any], config: R3S3Config, data: Trajectories,
                     test: Trajectories | None) -> dict[str, Any]:
    """The recovered mass and inertia against the scene's closed form, and with held-out ``test``
    data the open-loop errors of the learned and the closed-form model; for a craft the closed form
    cannot read (:func:`~fvin_mpc.core.quadrotor.from_mujoco` refuses its actuators), the reason instead."""
    try:
        scene_quadrotor(str(data.metadata.get("scene", "quadrotor")))
    except ValueError as error:
        return {"closed_form": f"not compared: {error}"}
    report: dict[str, Any] = {
        "recovered": recovered_parameters(
            weights, config, scene_quadrotor(str(data.metadata.get("scene", "quadrotor")))
        )
    }
    if test is not None:
        report.update(compare_open_loop(weights, config, test, str(test.metadata.get("scene", "quadrotor"))))
    return report


def free_body_evaluation(checkpoint: Any, test: Trajectories) -> dict[str, Any]:
    """A trained free body on held-out data: open loop over 0.2, 0.5 and 1 s, learned beside closed
    form; the recovered mass, inertia and hover thrust."""
    scene = str(test.metadata.get("scene", "quadrotor"))
    body = scene_quadrotor(scene)
    result: dict[str, Any] = {"checkpoint": str(checkpoint.path),
                              "recovered": recovered_parameters(checkpoint.weights, checkpoint.config, body),
                              "hover_thrust": hover_thrust(checkpoint.weights, checkpoint.config, test),
                              "true_hover_thrust": body.hover_thrust}
    for horizon in (0.2, 0.5, 1.0):
        result[f"horizon_{horizon:g}s"] = compare_open_loop(checkpoint.weights, checkpoint.config, test, scene, horizon)
    return result


#: The spaces whose training differs from the generic defaults.
TRAINING: dict[ConfigurationSpace, SpaceTraining] = {
    # Measured on the quadrotor (docs/quadrotor.md): LM only, longer patience, one thread.
    R3S3: SpaceTraining(settings={"window": 8, "patience": 6, "threads": 1},
                        rest_scale=(POSITION_SCALE,) * 3 + (VELOCITY_SCALE,) * 3 + (1.0,) * 3,
                        report=free_body_report, evaluate=free_body_evaluation, optimizers=("lm",)),
}


def data_control_scale(data: Trajectories) -> tuple[float, ...] | None:
    """Per control, the largest ``|u|`` in ``data`` (the size of a full control, as the data saw it);
    ``None`` when a control is never nonzero (nothing to scale by)."""
    largest = np.abs(np.asarray(data.u, dtype=float)).reshape(-1, data.u.shape[-1]).max(axis=0)
    return tuple(float(v) for v in largest) if np.all(largest > 0.0) else None


def default_model_config(data: Trajectories, space: ConfigurationSpace | None = None, **given: Any) -> Any:
    """The model ``python -m fvin_mpc.train`` builds for ``data`` unless told otherwise, ``given`` fields on
    top: ``space`` (default: the data's, with its first variant) and its first variant, the data's control
    size and step, dissipation on where the data's scene declares joint damping, the scene's hinge
    axis on a hinge, its vertical on a ball joint (:func:`~fvin_mpc.learning.training.scene_vertical`),
    and the data's control scale (each where the space's config has that field).
    ``ValueError`` from the config on a bad field."""
    space = space or space_for_variant(data.space, data.space.variants[0])
    chosen = {"variant": space.variants[0], "control_dim": int(data.u.shape[2]), "step_size": data.control_period,
              **given}
    config_fields = {f.name for f in fields(space.config_type)}
    if "dissipation" in config_fields and "dissipation" not in given:
        chosen["dissipation"] = bool(scene_has_joint_damping(data.metadata))
    if "hinge_axis" in config_fields and "hinge_axis" not in given:
        chosen["hinge_axis"] = scene_hinge_axis(data.metadata)
    if "vertical" in config_fields and "vertical" not in given:
        chosen["vertical"] = scene_vertical(data.metadata)
    if "control_scale" in config_fields and "control_scale" not in given:
        chosen["control_scale"] = data_control_scale(data)
    return space.config_type(**chosen)


def check_training_data(data: Trajectories, config: Any) -> None:
    """``DataFileError`` for data no model can be trained on, before any training: fewer than two trajectories
    (one is held out for validation, at least one trained on), controls of another width than the model's,
    or than the actuators of the scene the data name (a 2-control model of a 1-motor scene)."""
    if data.num_trajectories < 2:
        raise DataFileError(f"the data hold {data.num_trajectories} trajectory: training holds at least one out for "
                            "validation and trains on the rest; collect at least 2 (--trajectories)")
    width = int(data.u.shape[2])
    if int(getattr(config, "control_dim", width)) != width:
        raise DataFileError(f"the data have {width} controls per step and the model {config.control_dim}")
    scene = data.metadata.get("scene")
    if not scene:
        return
    try:
        actuators = load_model(resolve_scene(str(scene)).xml_path).nu
    except (ValueError, OSError):
        return  # a scene not on this machine (or no longer compiling): nothing to compare with
    if actuators != width:
        raise DataFileError(f"the data have {width} controls per step, and their scene {str(scene)!r} has {actuators} "
                            "actuators: the file was not recorded from it (or was edited); collect it again")


def training_for(space: ConfigurationSpace) -> SpaceTraining:
    """What the training command does differently for ``space`` (generic defaults if nothing)."""
    return TRAINING.get(space) or SpaceTraining()


def train_model(data: Trajectories, config: Any, settings: Any, progress: bool = True,
                initial_weights: Mapping[str, Any] | None = None,
                measure: Callable[[Any], float] | None = None) -> tuple[Any, dict[str, Any]]:
    """:func:`fvin_mpc.learning.training.train` on the model of ``config``'s space in the space's
    training layout (its ``rest_scale``), from ``initial_weights`` when given (continued training)
    or the seeded initialization; the report records the scales. ``measure``: :func:`train`'s."""
    from fvin_mpc.learning.model import model_for

    check_training_data(data, config)
    space = space_of_config(config)
    preset = training_for(space)
    if preset.optimizers is not None and settings.optimizer not in preset.optimizers:
        raise ValueError(f"models on {space.description} train with {', '.join(preset.optimizers)} only, "
                         f"not {settings.optimizer!r}")
    extra = {} if preset.rest_scale is None else {"rest_scale": preset.rest_scale}
    model, report = train(data, config, settings, progress,
                          model_factory=lambda config, seed: model_for(config, initial_weights, seed, **extra),
                          measure=measure)
    if preset.rest_scale is not None:
        report["rest_scale"] = list(preset.rest_scale)
    return model, report


# ----------------------------------------------------------------------------- targets
def recovered_parameters(weights: Mapping[str, Any], config: R3S3Config, body: Any = None,
                         orientations: int = 200, seed: int = 0) -> dict[str, Any]:
    """The learned ``M`` and ``J`` in kg and kg·m², each divided by its own scale.

    The translational scale ``c`` is read off the thrust (:func:`fvin_mpc.core.networks_r3s3.physical_scale`:
    one newton shared evenly by the rotors is one newton; its spread over ``orientations`` random
    attitudes is reported). An untethered craft's rotation does not see its translation (no term
    couples them), so its terms carry a second, independent scale ``c_rot``: fixed by the rotors'
    known torque, ``c_rot = ‖ĝ‖ / ‖2B‖`` (Frobenius, ``B`` from ``body``'s rotor sites and κ), when a
    closed-form ``body`` (:class:`~fvin_mpc.core.quadrotor.Quadrotor`) is given; then relative errors
    against its mass and inertia too. ``J`` at the identity."""
    terms = LearnedCombinedTerms(weights, config, get_ops("numpy"))
    scale = physical_scale(terms)
    rng = np.random.default_rng(seed)
    spread = []
    for _ in range(orientations):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        gain = np.asarray(terms.force_gain(tuple(np.zeros(3)), tuple(q)), dtype=float)
        spread.append(np.linalg.norm(gain.mean(axis=1)))
    identity = tuple(np.float64(c) for c in (1.0, 0.0, 0.0, 0.0))
    mass = np.array(terms.mass_matrix(), dtype=float) / scale
    result: dict[str, Any] = {"scale": scale, "scale_over_orientations": {"min": float(np.min(spread)),
                                                                        "max": float(np.max(spread))},
                              "mass_matrix": mass.tolist()}
    inertia = np.array(terms.inertia(identity), dtype=float)
    if body is None:
        result["inertia_unscaled"] = inertia.tolist()
        return result
    gain = np.array(terms.control_gain(tuple(np.zeros(3)), identity), dtype=float)
    rotational_scale = float(np.linalg.norm(gain) / np.linalg.norm(2.0 * np.array(body.torque_map)))
    inertia = inertia / rotational_scale
    true_inertia = np.array(body.inertia)
    result.update(
        rotational_scale=rotational_scale,
        inertia=inertia.tolist(),
        mass_relative_error=float(np.abs(np.linalg.eigvalsh(mass) / body.mass - 1.0).max()),
        inertia_relative_error=float(np.abs(np.diag(inertia) / np.diag(true_inertia) - 1.0).max()),
        inertia_off_diagonal_relative=float(
            np.abs(inertia - np.diag(np.diag(inertia))).max() / np.trace(true_inertia) * 3
        ),
    )
    return result


def open_loop_errors(step: Any, data: Trajectories, horizon_steps: int) -> dict[str, Any]:
    """Open-loop rollouts of ``step(state (B, 13), u (B, m)) -> state (B, 13)`` from the first state of
    every trajectory of ``data`` under its recorded controls, against the recorded states, over
    ``horizon_steps`` steps: position (m), orientation (rad, sign invariant), velocity (m/s) and
    angular velocity (rad/s) errors at the end (median, 90th percentile, max) and the largest
    ``||q| − 1|``."""
    horizon_steps = min(horizon_steps, data.u.shape[1])  # the recorded trajectories' length at most
    states = data.state[:, : horizon_steps + 1]
    predicted = [states[:, 0]]
    for k in range(horizon_steps):
        predicted.append(step(predicted[-1], data.u[:, k]))
    final, truth = predicted[-1], states[:, -1]
    free = data.space.layout.free_body(by="a free body's rollout errors")
    q_final, q_truth = final[:, free.quaternion], truth[:, free.quaternion]
    alignment = np.clip(np.abs(np.sum(q_final * q_truth, axis=1) / np.linalg.norm(q_final, axis=1)), 0, 1)
    errors = {
        "position_m": np.linalg.norm(final[:, free.position] - truth[:, free.position], axis=1),
        "orientation_rad": 2.0 * np.arccos(alignment),
        "velocity_m_s": np.linalg.norm(final[:, free.velocity] - truth[:, free.velocity], axis=1),
        "angular_velocity_rad_s": np.linalg.norm(final[:, free.omega] - truth[:, free.omega], axis=1),
    }
    summary: dict[str, Any] = {name: {"median": float(np.median(e)), "p90": float(np.percentile(e, 90)),
                                      "max": float(np.max(e))} for name, e in errors.items()}
    summary["max_unit_norm_error"] = float(
        max(np.abs(np.linalg.norm(p[:, free.quaternion], axis=1) - 1.0).max() for p in predicted)
    )
    summary["all_finite"] = bool(all(np.all(np.isfinite(p)) for p in predicted))
    summary["horizon_s"] = horizon_steps * data.control_period
    summary["trajectories"] = data.num_trajectories
    return summary


def hover_thrust(weights: Mapping[str, Any], config: R3S3Config, data: Trajectories) -> float:
    """The per-rotor thrust, shared evenly, at which the learned model holds still level at the
    data's hover point (the first recorded position's neighbourhood: ``(0, 0, 1)`` for the scene):
    ``(∇ₓU)_z / (G_x 1)_z`` at ``(x*, identity)``."""
    terms = LearnedCombinedTerms(weights, config, get_ops("numpy"))
    x = tuple(np.float64(c) for c in (0.0, 0.0, 1.0))
    q = tuple(np.float64(c) for c in (1.0, 0.0, 0.0, 0.0))
    gain = np.asarray(terms.force_gain(x, q), dtype=float)
    return float(np.asarray(terms.potential_gradient_x(x, q), dtype=float)[2] / gain[2].sum())


def scene_quadrotor(scene: str) -> Any:
    """The closed-form :class:`~fvin_mpc.core.quadrotor.Quadrotor` of a free-body scene's MJCF."""
    env = QuadrotorEnv(scene=scene)
    try:
        return from_mujoco(env.model, env.body_name)
    finally:
        env.close()


def compare_open_loop(weights: Mapping[str, Any], config: R3S3Config, test: Trajectories, scene: str,
                      horizon_s: float = 1.0) -> dict[str, Any]:
    """:func:`open_loop_errors` over ``horizon_s`` of the learned model and of the closed-form craft read
    off the scene's MJCF (:func:`fvin_mpc.core.quadrotor.from_mujoco`), through the same step (``h``,
    ``K``, force rule), on the same held-out trajectories."""
    body = scene_quadrotor(scene)
    steps = int(round(horizon_s / config.step_size))
    ops = get_ops("numpy")
    return {
        "open_loop_learned": open_loop_errors(numpy_step(LearnedCombinedTerms(weights, config, ops), config,
                                                         config.newton_iters, config.force_rule), test, steps),
        "open_loop_closed_form": open_loop_errors(numpy_step(body.terms(ops), config, config.newton_iters,
                                                             config.force_rule), test, steps),
    }


def numpy_step(terms: Any, config_or_step: Any, newton_iters: int, force_rule: str = "trapezoid") -> Any:
    """``step(state (B, 13), u (B, m))`` of NumPy :class:`CombinedTerms` at step size ``config_or_step``
    (a float, or a config with ``step_size``)."""
    h = float(getattr(config_or_step, "step_size", config_or_step))
    ops = get_ops("numpy")
    return lambda state, u: fvin_r3s3.step_state(state, u, terms, h, newton_iters, ops, force_rule)[0]
