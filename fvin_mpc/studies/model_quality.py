"""Model quality of a checkpoint: ``python -m fvin_mpc.quality``.

**Hinges** (planar: the command's report on a hinge checkpoint):

* Held-out rollout error: the model rolled out open loop from unseen initial states under
  the recorded controls, against the recorded (MuJoCo) trajectory; geodesic angle error
  and ‖Δω‖ at every step.
* Energy without control: learned energy ``E = ½ωᵀJω + U`` along a long unforced rollout
  of the model, and the true energy of the states it predicts.
* Learned ``J``, ``U``, ``g`` against the true ones after fixing the common scale λ
  (``(J, U, g) → λ(J, U, g)`` leaves the dynamics unchanged). λ is fixed by least squares
  on the control gain ``g`` along the actuated axes (the one quantity tied to a known
  actuator), i.e. ``λ = Σ⟨g_learned, g_true⟩ / Σ‖g_true‖²`` over sampled states.

**Ball joints** (3-D, :func:`report`: the command's report on checkpoints of a body on a ball joint,
scene ``spherical_pendulum``), against the closed-form body read off the scene's MJCF
(:func:`fvin_mpc.core.rigid_body.from_mujoco`):

* **Held-out rollouts** — open loop from unseen initial states under the recorded torques, geodesic
  angle error and ‖Δω‖ (:func:`rollout_error`), with the closed-form model through
  the same FVIN step as the floor (its error is the integrator's, not the learning's).
* **Scale** — ``(J, U, g) → λ(J, U, g)`` leaves the dynamics unchanged, so λ is fixed first, by least
  squares on the control gain over orientations uniform on S³: ``λ = Σ⟨g_learned, g_true⟩ / Σ‖g_true‖²``
  with ``g_true = 2·B`` (``B`` the actuators' torque axes; ``2·I₃`` here, ``DESIGN.md`` factor of two).
* **Inertia** — ``J(q)/λ`` at those orientations: its mean, the principal moments (eigenvalues) and
  principal axes (eigenvectors, angle to the true axes, sign-free) of the mean against the MJCF's
  inertia about the pivot, and how much the learned ``J`` varies with ``q`` (it is constant in truth).
* **Potential and gain** — ``U/λ`` (relative to hanging) and ``g/λ`` against the true ones.
* **Energy** — unforced rollouts from random states: relative drift of the learned energy
  and of the true energy of the predicted states.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from fvin_mpc.core import fvin, s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.checkpoint import Checkpoint, load_checkpoint
from fvin_mpc.core.data import Trajectories
from fvin_mpc.core.errors import DataFileError, UsageError
from fvin_mpc.core.networks import LearnedTerms
from fvin_mpc.core.rigid_body import from_mujoco
from fvin_mpc.core.space import S3
from fvin_mpc.envs import RigidBodyEnv

NP = get_ops("numpy")


def _components(array: np.ndarray) -> tuple[np.ndarray, ...]:
    return tuple(array[..., i] for i in range(array.shape[-1]))


def rollout(terms: Any, step_size: float, newton_iters: int, q0: np.ndarray, omega0: np.ndarray,
            controls: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batched open-loop rollout: ``q0 (B, 4)``, ``omega0 (B, 3)``, ``controls (B, T, m)`` →
    ``q (B, T+1, 4)``, ``omega (B, T+1, 3)``, ``residual (B, T)``."""
    q, omega = _components(q0), _components(omega0)
    qs, omegas, residuals = [q0], [omega0], []
    for k in range(controls.shape[1]):
        out = fvin.fvin_step(
            q, omega, _components(controls[:, k]), terms, step_size, newton_iters, NP, with_residual=True
        )
        q, omega = out.q, out.omega
        qs.append(np.stack(q, -1))
        omegas.append(np.stack(omega, -1))
        residuals.append(out.residual)
    return np.stack(qs, 1), np.stack(omegas, 1), np.stack(residuals, 1)


def learned_terms(checkpoint: Checkpoint) -> LearnedTerms:
    """The checkpoint's NumPy terms; the quality studies compare ``J(q)``, ``U(q)``, ``g(q)`` on S³
    and refuse other spaces' checkpoints."""
    checkpoint.require(S3, by="the model-quality study")
    return LearnedTerms(checkpoint.weights, checkpoint.config, NP)


def rollout_error(checkpoint: Checkpoint, data: Trajectories, horizon: int | None = None,
                  terms: Any = None) -> dict[str, Any]:
    """Geodesic angle error (rad) and ‖Δω‖ (rad/s) of open-loop rollouts vs ``data``.

    ``terms`` replaces the checkpoint's learned terms (e.g. the closed-form body, to see what
    the same integrator with the true physics achieves); step size and ``K`` stay the checkpoint's.
    """
    terms = learned_terms(checkpoint) if terms is None else terms
    steps = data.u.shape[1] if horizon is None else horizon
    q_hat, omega_hat, residual = rollout(terms, checkpoint.config.step_size, checkpoint.config.newton_iters,
                                         data.q[:, 0], data.omega[:, 0], data.u[:, :steps])
    angle = s3.geodesic_angle(_components(q_hat), _components(data.q[:, : steps + 1]), NP)
    omega_error = np.linalg.norm(omega_hat - data.omega[:, : steps + 1], axis=-1)
    return {
        "trajectories": int(data.q.shape[0]),
        "steps": int(steps),
        "seconds": steps * checkpoint.config.step_size,
        "angle_error_final_mean": float(angle[:, -1].mean()),
        "angle_error_final_median": float(np.median(angle[:, -1])),
        "angle_error_final_p90": float(np.percentile(angle[:, -1], 90)),
        "angle_error_mean": float(angle.mean()),
        "omega_error_final_mean": float(omega_error[:, -1].mean()),
        "omega_error_mean": float(omega_error.mean()),
        "max_newton_residual": float(residual.max()),
        "angle_error_per_step_mean": angle.mean(0).tolist(),
    }


def fit_scale(learned: Any, true: Any, quaternions: np.ndarray) -> float:
    """λ by least squares on ``g``: ``argmin_λ Σ‖g_learned − λ g_true‖²`` over ``quaternions``."""
    q = _components(quaternions)
    g_learned = np.array(learned.control_gain(q), dtype=float)
    g_true = np.broadcast_to(np.array(true.control_gain(q), dtype=float), g_learned.shape)
    return float((g_learned * g_true).sum() / (g_true * g_true).sum())


def compare_components(checkpoint: Checkpoint, true_body: Any, quaternions: np.ndarray, axis: np.ndarray,
                       rest: np.ndarray) -> dict[str, Any]:
    """Learned vs true ``J`` (along ``axis``), ``U`` (both relative to the ``rest`` orientation), ``g``
    after fixing λ; for a model with dissipation also ``D`` (constant; along ``axis`` and the whole
    matrix, over λ)."""
    learned = learned_terms(checkpoint)
    true = true_body.terms(NP)
    scale = fit_scale(learned, true, quaternions)
    q = _components(quaternions)
    at_rest = _components(np.asarray(rest, dtype=float)[None])
    j_learned = np.array(learned.inertia(q), dtype=float)  # 3×3×B
    j_axis = np.einsum("i,ijb,j->b", axis, j_learned, axis) / scale
    j_true = float(axis @ np.array(true_body.inertia) @ axis)
    u_learned = (np.asarray(learned.potential(q)) - np.asarray(learned.potential(at_rest))) / scale
    u_true = np.asarray(true.potential(q)) - np.asarray(true.potential(at_rest))
    g_learned = np.array(learned.control_gain(q), dtype=float) / scale
    g_true = np.broadcast_to(np.array(true.control_gain(q), dtype=float), g_learned.shape)
    dissipation = {}
    d_learned = learned.dissipation(at_rest)
    if d_learned is not None:
        d_learned = np.array(d_learned, dtype=float)[..., 0] / scale
        d_true = true.dissipation(at_rest)
        d_true = np.zeros((3, 3)) if d_true is None else np.array(d_true, dtype=float)[..., 0]
        dissipation = {
            "dissipation_axis_true": float(axis @ d_true @ axis), "dissipation_axis": float(axis @ d_learned @ axis),
            "dissipation_matrix": d_learned.tolist(),
        }
    return {
        "lambda": scale,
        "inertia_axis_true": j_true, "inertia_axis_mean": float(j_axis.mean()),
        "inertia_axis_max_rel_error": float(np.abs(j_axis / j_true - 1).max()),
        "potential_rms_error": float(np.sqrt(np.mean((u_learned - u_true) ** 2))),
        "potential_range_true": float(u_true.max() - u_true.min()),
        "gain_max_abs_error": float(np.abs(g_learned - g_true).max()),
        "gain_true_norm": float(np.linalg.norm(g_true[..., 0], axis=0).max()),
        **dissipation,
    }


def _onto_axis(q: np.ndarray, omega: np.ndarray, axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The nearest rotation about ``axis`` (``q`` projected onto span{1, axis}, renormalized) and ``ω`` along it."""
    planar = np.stack([q[:, 0], q[:, 1:] @ axis], 1)
    planar /= np.linalg.norm(planar, axis=1, keepdims=True)
    return (np.concatenate([planar[:, :1], planar[:, 1:] * axis], 1),
            (omega @ axis)[:, None] * axis)


def energy_behaviour(checkpoint: Checkpoint, true_body: Any, initial_angles: np.ndarray, steps: int,
                     axis: np.ndarray, rest: np.ndarray, goal: np.ndarray, on_axis: bool = False) -> dict[str, Any]:
    """Unforced rollouts of the model from rest at ``initial_angles`` about ``axis``.

    Energy deviations are relative to the potential's range ``U(goal) − U(rest)`` of the
    same energy (learned or true), since ``U`` has an arbitrary offset. ``max_off_axis_omega``
    is the largest angular velocity off ``axis``: a planar scene's data never leaves the plane,
    so nothing in training keeps the model's unforced motion in it. ``on_axis`` puts every
    step back onto rotations about ``axis`` (the hinge's constraint), isolating the in-plane behaviour.
    """
    terms = learned_terms(checkpoint)
    true = true_body.terms(NP)
    n = initial_angles.size
    q0 = np.concatenate([np.cos(initial_angles / 2)[:, None], np.sin(initial_angles / 2)[:, None] * axis], 1)
    controls = np.zeros((n, steps, checkpoint.config.control_dim))
    h, k = checkpoint.config.step_size, checkpoint.config.newton_iters
    if on_axis:
        states, residuals = [(q0, np.zeros((n, 3)))], []
        for _ in range(steps):  # one step at a time, put back on the hinge as MuJoCo's joint would
            q_next, omega_next, step_residual = rollout(terms, h, k, *states[-1], controls[:, :1])
            states.append(_onto_axis(q_next[:, 1], omega_next[:, 1], axis))
            residuals.append(step_residual)
        q, omega = np.stack([s[0] for s in states], 1), np.stack([s[1] for s in states], 1)
        residual = np.concatenate(residuals, 1)
    else:
        q, omega, residual = rollout(terms, h, k, q0, np.zeros((n, 3)), controls)
    learned_energy = np.asarray(fvin.total_energy(_components(q), _components(omega), terms))
    true_energy = np.asarray(fvin.total_energy(_components(q), _components(omega), true))
    ends = _components(np.array([rest, goal], dtype=float))

    def deviation(energy: np.ndarray, model: Any) -> np.ndarray:
        hanging, upright = np.asarray(model.potential(ends), dtype=float).ravel()
        return np.abs(energy - energy[:, :1]) / abs(upright - hanging)

    off_axis = omega - np.einsum("...i,i->...", omega, axis)[..., None] * axis
    return {
        "steps": steps, "initial_angles": initial_angles.tolist(),
        "learned_energy_max_deviation_over_potential_range": deviation(learned_energy, terms).max(1).tolist(),
        "true_energy_max_deviation_over_potential_range": deviation(true_energy, true).max(1).tolist(),
        "max_off_axis_omega": np.linalg.norm(off_axis, axis=-1).max(1).tolist(),
        "max_newton_residual": float(residual.max()),
        "max_norm_error": float(np.abs(np.linalg.norm(q, axis=-1) - 1).max()),
        "true_energy": true_energy.tolist() if steps <= 5000 else None,
    }


# ---------------------------------------------------------------------- ball joints (3-D)
def uniform_quaternions(count: int, seed: int) -> np.ndarray:
    """``(count, 4)`` unit quaternions uniform on S³ (normalized Gaussians), seeded."""
    q = np.random.default_rng(seed).normal(size=(count, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def scene_body(scene: str = "spherical_pendulum") -> tuple[Any, np.ndarray]:
    """The closed-form :class:`~fvin_mpc.core.rigid_body.PivotedRigidBody` of a scene (read off its
    MJCF) and the scene's rest orientation."""

    env = RigidBodyEnv(scene=scene)
    body, rest = from_mujoco(env.model, env.body_name), env.rest
    env.close()
    return body, rest


def principal_axes(inertia: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (ascending) and unit eigenvectors (columns) of a symmetric 3×3 matrix."""
    values, vectors = np.linalg.eigh(0.5 * (inertia + inertia.T))
    return values, vectors


def axis_angles_deg(learned_axes: np.ndarray, true_axes: np.ndarray) -> np.ndarray:
    """Angle (degrees, in [0, 90]) between corresponding columns, ignoring the sign of each axis."""
    cosines = np.abs(np.sum(learned_axes * true_axes, axis=0)).clip(0.0, 1.0)
    return np.degrees(np.arccos(cosines))


def recover_inertia(checkpoint: Checkpoint, body: Any, quaternions: np.ndarray, rest: np.ndarray) -> dict[str, Any]:
    """Learned ``J``, ``U``, ``g`` against ``body`` after fixing λ on ``g`` (see the module docstring)."""
    learned = learned_terms(checkpoint)
    true = body.terms(NP)
    q = _components(quaternions)
    scale = fit_scale(learned, true, quaternions)
    if not (np.isfinite(scale) and scale > 1e-9):
        raise ValueError(f"cannot fix the scale: the learned gain does not align with the true one (λ = {scale:.3g})")

    j_learned = np.moveaxis(np.array(learned.inertia(q), dtype=float), -1, 0) / scale  # (B, 3, 3)
    j_mean = j_learned.mean(0)
    j_true = np.array(body.inertia, dtype=float)
    moments_learned, axes_learned = principal_axes(j_mean)
    moments_true, axes_true = principal_axes(j_true)
    variation = np.linalg.norm(j_learned - j_mean, axis=(1, 2)) / np.linalg.norm(j_mean)

    at_rest = _components(np.asarray(rest, dtype=float)[None])
    u_learned = (np.asarray(learned.potential(q)) - np.asarray(learned.potential(at_rest))) / scale
    u_true = np.asarray(true.potential(q)) - np.asarray(true.potential(at_rest))
    g_learned = np.array(learned.control_gain(q), dtype=float) / scale  # (3, m, B)
    g_true = np.broadcast_to(np.array(true.control_gain(q), dtype=float), g_learned.shape)
    gain_error = np.linalg.norm(g_learned - g_true, axis=(0, 1)) / np.linalg.norm(g_true, axis=(0, 1))
    # Per-axis scale: the z row of (J, g) is tied to the others only through the gyroscopic term
    # (gravity exerts no torque about the body's z axis, its centre of mass lies on it), so the data
    # pin down J⁻¹g much better than J and g separately. Compare J against the actuators directly:
    # J_act = sym(2 ḡ⁻¹ J̄) (= J_true when J⁻¹g = J_true⁻¹·2I), independent of any λ.
    g_mean = np.array(learned.control_gain(q), dtype=float).mean(-1)  # (3, m), unscaled
    j_raw_mean = j_mean * scale
    actuator_referenced = None
    if g_mean.shape[0] == g_mean.shape[1] and abs(np.linalg.det(g_mean)) > 1e-12:
        raw = 2.0 * np.linalg.solve(g_mean, j_raw_mean) @ np.linalg.inv(np.array(body.actuator_axes, dtype=float))
        actuator_referenced = 0.5 * (raw + raw.T)
    u_raw = np.asarray(learned.potential(q)) - np.asarray(learned.potential(at_rest))
    lambda_potential = float((u_raw * u_true).sum() / (u_true * u_true).sum())
    result = {
        "samples": int(quaternions.shape[0]),
        "lambda": scale,
        "lambda_per_body_axis_from_gain": (
            np.diag(g_mean) / np.diag(2.0 * np.array(body.actuator_axes, dtype=float))
        ).tolist()
        if g_mean.shape == (3, 3)
        else None,
        "lambda_from_potential": lambda_potential,
        "potential_rms_error_lambda_from_potential": float(np.sqrt(np.mean((u_raw / lambda_potential - u_true) ** 2))),
        "inertia_true": j_true.tolist(),
        "inertia_learned_mean": j_mean.tolist(),
        "inertia_relative_error_fro": float(np.linalg.norm(j_mean - j_true) / np.linalg.norm(j_true)),
        "principal_moments_true": moments_true.tolist(),
        "principal_moments_learned": moments_learned.tolist(),
        "principal_moments_relative_error": (moments_learned / moments_true - 1.0).tolist(),
        "principal_axes_true": axes_true.T.tolist(),
        "principal_axes_learned": axes_learned.T.tolist(),
        "principal_axes_angle_deg": axis_angles_deg(axes_learned, axes_true).tolist(),
        "inertia_variation_over_q_median": float(np.median(variation)),
        "inertia_variation_over_q_max": float(variation.max()),
        "potential_rms_error": float(np.sqrt(np.mean((u_learned - u_true) ** 2))),
        "potential_range_true": float(u_true.max() - u_true.min()),
        "gain_relative_error_median": float(np.median(gain_error)),
        "gain_relative_error_max": float(gain_error.max()),
        "gain_learned_mean": g_learned.mean(-1).tolist(),
    }
    if actuator_referenced is not None:
        moments_act, axes_act = principal_axes(actuator_referenced)
        result.update({
            "actuator_referenced_inertia": actuator_referenced.tolist(),
            "actuator_referenced_moments": moments_act.tolist(),
            "actuator_referenced_moments_relative_error": (moments_act / moments_true - 1.0).tolist(),
            "actuator_referenced_axes_angle_deg": axis_angles_deg(axes_act, axes_true).tolist(),
        })
    return result


def energy_drift(
    checkpoint: Checkpoint, body: Any, count: int, steps: int, max_omega: float, seed: int
) -> dict[str, Any]:
    """Unforced rollouts of the learned model from ``count`` random states (|ω| ≤ ``max_omega``)."""
    terms = learned_terms(checkpoint)
    true = body.terms(NP)
    rng = np.random.default_rng(seed)
    q0 = uniform_quaternions(count, seed)
    omega0 = rng.uniform(-max_omega, max_omega, size=(count, 3)) / np.sqrt(3.0)
    q, omega, residual = rollout(terms, checkpoint.config.step_size, checkpoint.config.newton_iters, q0, omega0,
                                 np.zeros((count, steps, checkpoint.config.control_dim)))
    learned_energy = np.asarray(fvin.total_energy(_components(q), _components(omega), terms))
    true_energy = np.asarray(fvin.total_energy(_components(q), _components(omega), true))
    spread = lambda e: (e.max(1) - e.min(1)) / np.abs(e).max(1)  # noqa: E731
    q_t, omega_t, _ = rollout(true, checkpoint.config.step_size, checkpoint.config.newton_iters, q0, omega0,
                              np.zeros((count, steps, body.control_dim)))
    closed_form_energy = np.asarray(fvin.total_energy(_components(q_t), _components(omega_t), true))
    return {
        "closed_form_model_energy_rel_spread_median": float(np.median(spread(closed_form_energy))),
        "closed_form_model_energy_rel_spread_max": float(spread(closed_form_energy).max()),
        "trajectories": count, "steps": steps,
        "learned_energy_rel_spread_median": float(np.median(spread(learned_energy))),
        "learned_energy_rel_spread_max": float(spread(learned_energy).max()),
        "true_energy_of_prediction_rel_spread_median": float(np.median(spread(true_energy))),
        "max_norm_error": float(np.abs(np.linalg.norm(q, axis=-1) - 1).max()),
        "max_newton_residual": float(residual.max()),
    }


def solvability_limit(inertia: np.ndarray, step_size: float, directions: np.ndarray, newton_iters: int = 40,
                      tolerance: float = 1e-8, radii: np.ndarray | None = None) -> np.ndarray:
    """Largest ``|ω|`` (rad/s) along each unit direction ``(D, 3)`` for which the unforced step's implicit
    equation ``Φ(ξ) = −(h/2)Jω`` is still solved by Newton from ``ξ = 0`` (residual ≤ ``tolerance``).

    For ``J = jI`` this is ``1/h`` in every direction (``DESIGN.md``); an anisotropic ``J`` moves it.
    The scale of ``J`` cancels, so a learned ``J`` needs no λ.
    """
    radii = np.arange(0.5, 40.0, 0.25) if radii is None else radii
    j = tuple(tuple(float(x) for x in row) for row in np.asarray(inertia, dtype=float))
    d, r = np.meshgrid(np.arange(directions.shape[0]), radii, indexing="ij")
    omega = directions[d.ravel()] * r.ravel()[:, None]
    rhs = tuple(-(step_size / 2.0) * (np.asarray(j[i]) @ omega.T) for i in range(3))
    xi = fvin.solve_implicit(rhs, j, newton_iters, NP)
    phi = fvin.implicit_lhs(xi, j, NP)
    residual = np.linalg.norm(np.stack(phi, -1) - np.stack(rhs, -1), axis=-1) / np.linalg.norm(
        np.stack(rhs, -1), axis=-1
    )
    solved = (residual <= tolerance).reshape(d.shape)
    first_failure = np.where(solved.all(1), radii.size, np.argmin(solved, axis=1))
    return np.where(first_failure > 0, radii[np.maximum(first_failure - 1, 0)], 0.0)


def true_rollout_error(
    body: Any, step_size: float, newton_iters: int, data: Trajectories, horizon: int
) -> dict[str, Any]:
    """:func:`rollout_error` of the closed-form body (the integrator's own error)."""

    q_hat, omega_hat, residual = rollout(body.terms(NP), step_size, newton_iters, data.q[:, 0], data.omega[:, 0],
                                         data.u[:, :horizon])
    angle = s3.geodesic_angle(_components(q_hat), _components(data.q[:, : horizon + 1]), NP)
    omega_error = np.linalg.norm(omega_hat - data.omega[:, : horizon + 1], axis=-1)
    return {
        "steps": horizon, "angle_error_final_mean": float(angle[:, -1].mean()),
        "angle_error_final_median": float(np.median(angle[:, -1])),
        "angle_error_final_p90": float(np.percentile(angle[:, -1], 90)), "angle_error_mean": float(angle.mean()),
        "omega_error_final_mean": float(omega_error[:, -1].mean()), "omega_error_mean": float(omega_error.mean()),
        "max_newton_residual": float(residual.max()),
        "angle_error_per_step_mean": angle.mean(0).tolist(),
    }


def check_held_out(data: Trajectories, checkpoint: Checkpoint, path: Any, horizon: int | None = None) -> Trajectories:
    """Held-out data a checkpoint is measured against, checked before any rollout: states of the model's
    configuration space, as many controls, recorded at the model's step (a rollout compares them step by
    step: data of another period would measure nothing, silently), and — with ``horizon`` — trajectories at
    least that many steps long. Returns ``data``.

    Raises:
        DataFileError: naming the file, what differs and how to get matching data.
    """
    config = checkpoint.config
    if data.space.layout != checkpoint.space.layout:
        raise DataFileError(f"{path}: states of {data.space.description}; the checkpoint is a model on "
                            f"{checkpoint.space.description}")
    if int(data.u.shape[2]) != int(config.control_dim):
        raise DataFileError(f"{path}: {data.u.shape[2]} controls per step; the checkpoint's model has "
                            f"{config.control_dim}")
    step = float(config.step_size)
    if abs(data.control_period - step) > 1e-9 * max(1.0, step):
        raise DataFileError(f"{path} was recorded every {data.control_period:g} s and the "
                            f"checkpoint steps at {step:g} s: "
                            f"collect held-out data at its period (python -m fvin_mpc.collect "
                            f"--control-period {step:g} "
                            "--seed 1 --out …)")
    if horizon is not None and horizon > data.u.shape[1]:
        raise UsageError(f"--horizon {horizon} is longer than the held-out trajectories of {path} "
                         f"({data.u.shape[1]} steps)")
    return data


def report(checkpoint: Checkpoint | str | Path, data: Trajectories, horizon: int = 20, samples: int = 512,
           energy_steps: int = 400, seed: int = 0) -> dict[str, Any]:
    """Everything in the module docstring for one checkpoint, as a JSON-ready dict."""
    if not isinstance(checkpoint, Checkpoint):
        checkpoint = load_checkpoint(checkpoint)
    check_held_out(data, checkpoint, "the held-out data")
    scene = checkpoint.scene or "spherical_pendulum"
    body, rest = scene_body(scene)
    horizon = min(horizon, data.u.shape[1])
    learned = rollout_error(checkpoint, data, horizon)
    true = true_rollout_error(body, checkpoint.config.step_size, checkpoint.config.newton_iters, data, horizon)
    return {
        "checkpoint": str(checkpoint.path), "variant": checkpoint.config.variant,
        "hidden_width": checkpoint.config.hidden_width, "scene": scene,
        "rollout": {"learned": learned, "true_model": true},
        "components": recover_inertia(checkpoint, body, uniform_quaternions(samples, seed), rest),
        "energy": energy_drift(checkpoint, body, 32, energy_steps, 4.0, seed),
        "solvability": solvability_summary(checkpoint, body, seed),
    }


def solvability_summary(checkpoint: Checkpoint, body: Any, seed: int = 0, directions: int = 200) -> dict[str, Any]:
    """:func:`solvability_limit` over random directions and the principal axes, true vs learned mean ``J``."""
    h = checkpoint.config.step_size
    sampled = uniform_quaternions(directions, seed + 1)[:, 1:]
    sampled = np.vstack([np.eye(3), sampled / np.linalg.norm(sampled, axis=1, keepdims=True)])
    learned = learned_terms(checkpoint)
    j_learned = np.moveaxis(
        np.array(learned.inertia(_components(uniform_quaternions(256, seed))), dtype=float), -1, 0
    ).mean(0)
    out: dict[str, Any] = {"step_size": h, "isotropic_limit": 1.0 / h}
    for name, inertia in (("true", np.array(body.inertia)), ("learned", j_learned)):
        limits = solvability_limit(inertia, h, sampled)
        out[name] = {"body_axes_x_y_z": limits[:3].tolist(), "min_over_directions": float(limits.min()),
                     "median_over_directions": float(np.median(limits)),
                     "max_over_directions": float(limits.max())}
    return out
