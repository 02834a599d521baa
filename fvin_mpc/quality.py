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

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from . import fvin, s3
from .backend import get_ops
from .checkpoint import Checkpoint, load_checkpoint
from .data import TrajectoryData, load_data
from .networks import LearnedTerms

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


def rollout_error(checkpoint: Checkpoint, data: TrajectoryData, horizon: int | None = None) -> dict[str, Any]:
    """Geodesic angle error (rad) and ‖Δω‖ (rad/s) of open-loop rollouts vs ``data``."""
    terms = LearnedTerms(checkpoint.weights, checkpoint.config, NP)
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


def compare_components(checkpoint: Checkpoint, true_body: Any, quaternions: np.ndarray, axis: np.ndarray) -> dict[str, Any]:
    """Learned vs true ``J`` (along ``axis``), ``U`` (relative to hanging), ``g`` after fixing λ."""
    learned = LearnedTerms(checkpoint.weights, checkpoint.config, NP)
    true = true_body.terms(NP)
    scale = fit_scale(learned, true, quaternions)
    q = _components(quaternions)
    identity = _components(np.array([[1.0, 0.0, 0.0, 0.0]]))
    j_learned = np.array(learned.inertia(q), dtype=float)  # 3×3×B
    j_axis = np.einsum("i,ijb,j->b", axis, j_learned, axis) / scale
    j_true = float(axis @ np.array(true_body.inertia) @ axis)
    u_learned = (np.asarray(learned.potential(q)) - np.asarray(learned.potential(identity))) / scale
    u_true = np.asarray(true.potential(q))
    g_learned = np.array(learned.control_gain(q), dtype=float) / scale
    g_true = np.broadcast_to(np.array(true.control_gain(q), dtype=float), g_learned.shape)
    return {
        "lambda": scale,
        "inertia_axis_true": j_true, "inertia_axis_mean": float(j_axis.mean()),
        "inertia_axis_max_rel_error": float(np.abs(j_axis / j_true - 1).max()),
        "potential_rms_error": float(np.sqrt(np.mean((u_learned - u_true) ** 2))),
        "potential_range_true": float(u_true.max() - u_true.min()),
        "gain_max_abs_error": float(np.abs(g_learned - g_true).max()),
        "gain_true_norm": float(np.linalg.norm(g_true[..., 0], axis=0).max()),
    }


def energy_behaviour(checkpoint: Checkpoint, true_body: Any, initial_angles: np.ndarray, steps: int,
                     axis: np.ndarray) -> dict[str, Any]:
    """Unforced rollouts of the model from rest at ``initial_angles`` about ``axis``."""
    terms = LearnedTerms(checkpoint.weights, checkpoint.config, NP)
    true = true_body.terms(NP)
    n = initial_angles.size
    q0 = np.concatenate([np.cos(initial_angles / 2)[:, None], np.sin(initial_angles / 2)[:, None] * axis], 1)
    q, omega, _ = rollout(terms, checkpoint.config.step_size, checkpoint.config.newton_iters, q0, np.zeros((n, 3)),
                          np.zeros((n, steps, checkpoint.config.control_dim)))
    learned_energy = np.asarray(fvin.total_energy(_components(q), _components(omega), terms))
    true_energy = np.asarray(fvin.total_energy(_components(q), _components(omega), true))
    rel = lambda e: np.abs(e - e[:, :1]) / np.abs(e[:, :1])  # noqa: E731
    return {
        "steps": steps, "initial_angles": initial_angles.tolist(),
        "learned_energy_max_rel_deviation": float(rel(learned_energy).max()),
        "true_energy_max_rel_deviation": float(rel(true_energy).max()),
        "true_energy_final_rel_change": float(((true_energy[:, -1] - true_energy[:, 0]) / true_energy[:, 0]).mean()),
        "max_norm_error": float(np.abs(np.linalg.norm(q, axis=-1) - 1).max()),
        "true_energy": true_energy.tolist() if steps <= 5000 else None,
    }


def main(argv: list[str] | None = None) -> int:
    from .rigid_body import PENDULUM, PENDULUM_DAMPED

    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.quality", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", default="pendulum_sign-invariant")
    parser.add_argument("--data", type=Path, default=Path("data/pendulum_heldout.npz"),
                        help="held-out trajectories (collect with a different --seed), default: %(default)s")
    parser.add_argument("--horizon", type=int, default=40, help="rollout steps (default: %(default)s = 2 s at h = 0.05)")
    parser.add_argument("--energy-steps", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0, help="seeds the sampled states of the component comparison")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    checkpoint = load_checkpoint(args.checkpoint)
    body = PENDULUM_DAMPED if checkpoint.scene == "pendulum_damped" else PENDULUM
    axis = np.array([0.0, 1.0, 0.0])
    angles = np.random.default_rng(args.seed).uniform(-np.pi, np.pi, 256)
    quaternions = np.concatenate([np.cos(angles / 2)[:, None], np.sin(angles / 2)[:, None] * axis], 1)
    report = {
        "checkpoint": str(checkpoint.path), "variant": checkpoint.config.variant,
        "rollout": rollout_error(checkpoint, load_data(args.data), args.horizon),
        "components": compare_components(checkpoint, body, quaternions, axis),
        "energy": energy_behaviour(checkpoint, body, np.array([0.5, 1.5, 2.5, 3.0]), args.energy_steps, axis),
    }
    report["rollout"].pop("angle_error_per_step_mean")
    report["energy"].pop("true_energy")
    text = json.dumps(report, indent=2)
    print(text)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
