"""Model quality of a checkpoint: ``python -m fvin_mpc.quality``.

* Held-out rollout error: the model rolled out open loop from unseen initial states under
  the recorded controls, against the recorded (MuJoCo) trajectory; geodesic angle error
  and ‖Δω‖ at every step.
* Energy without control: learned energy ``E = ½ωᵀJω + U`` along a long unforced rollout
  of the model, and the true energy of the states it predicts.
* Learned ``J``, ``U``, ``g`` against the true ones after fixing the common scale λ
  (``(J, U, g) → λ(J, U, g)`` leaves the dynamics unchanged). λ is fixed by least squares
  on the control gain ``g`` along the actuated axes (the one quantity tied to a known
  actuator), i.e. ``λ = Σ⟨g_learned, g_true⟩ / Σ‖g_true‖²`` over sampled states.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fvin_mpc.core import fvin, s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.checkpoint import Checkpoint
from fvin_mpc.core.data import Trajectories
from fvin_mpc.core.networks import LearnedTerms
from fvin_mpc.core.space import S3

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
        out = fvin.fvin_step(q, omega, _components(controls[:, k]), terms, step_size, newton_iters, NP, with_residual=True)
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
        "trajectories": int(data.q.shape[0]), "steps": int(steps), "seconds": steps * checkpoint.config.step_size,
        "angle_error_final_mean": float(angle[:, -1].mean()), "angle_error_final_median": float(np.median(angle[:, -1])),
        "angle_error_final_p90": float(np.percentile(angle[:, -1], 90)), "angle_error_mean": float(angle.mean()),
        "omega_error_final_mean": float(omega_error[:, -1].mean()), "omega_error_mean": float(omega_error.mean()),
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
