"""Energy-shaping swing-up with an LQR catch, built only from a model's ``J``, ``U``, ``g``.

Swing-up (energy pumping): with ``E = ½ωᵀJω + U(q)`` and the generalized force ``g u``
(twice the physical torque, ``DESIGN.md``), ``dE/dt = ½ ωᵀ g u``. The law

    u = clip(k · (E* − E)/|E* − E₀| · (gᵀω)/‖g‖, ±u_max)

pushes ``E`` towards the upright energy ``E* = U(q_goal)``; both factors are ratios, so
the model's unknown scale λ (``(J, U, g) → λ(J, U, g)`` gives the same dynamics)
cancels. At exact rest ``gᵀω = 0``; a full-torque kick breaks that symmetry.

Catch: within ``catch_angle`` of the goal the controller switches to a discrete LQR on
the model's own step linearized at ``(q_goal, ω = 0, u = 0)``, in coordinates restricted
to the actuated axes (for a planar pendulum the out-of-plane modes are neither actuated
nor learned, so a full 6-state LQR would not be stabilizable).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg

from . import fvin, s3
from .backend import get_ops

NP = get_ops("numpy")


@dataclass(frozen=True)
class EnergyShapingSettings:
    """Gains of :class:`EnergyShapingController`.

    Attributes:
        pump_gain: ``k`` of the pumping law (dimensionless after normalization).
        catch_angle: switch to LQR below this angle from the goal (rad).
        release_angle: fall back to pumping above this angle (rad); hysteresis.
        lqr_state_weight: weight of angle² and (0.1·ω)² in the LQR cost.
        lqr_control_weight: weight of u² in the LQR cost.
        kick_speed: below this |ω| (rad/s) and far from the goal, apply full torque.
    """

    pump_gain: float = 20.0
    catch_angle: float = 0.5
    release_angle: float = 0.9
    lqr_state_weight: float = 10.0
    lqr_control_weight: float = 1.0
    kick_speed: float = 1e-3


class EnergyShapingController:
    """``u, info = controller(q, omega)`` for any :class:`~fvin_mpc.fvin.RigidBodyTerms` on NumPy."""

    def __init__(self, terms: Any, step_size: float, newton_iters: int, goal: np.ndarray, torque_low: np.ndarray,
                 torque_high: np.ndarray, settings: EnergyShapingSettings = EnergyShapingSettings(),
                 hanging: np.ndarray = np.array([1.0, 0.0, 0.0, 0.0])) -> None:
        self.terms = terms
        self.h = step_size
        self.newton_iters = newton_iters
        self.goal = np.asarray(goal, dtype=float) / np.linalg.norm(goal)
        self.low, self.high = np.asarray(torque_low, float), np.asarray(torque_high, float)
        self.settings = settings
        zero3 = np.zeros(3)
        self.goal_energy = float(fvin.total_energy(tuple(self.goal), tuple(zero3), terms))
        self.rest_energy = float(fvin.total_energy(tuple(np.asarray(hanging, float)), tuple(zero3), terms))
        self.energy_scale = abs(self.goal_energy - self.rest_energy)
        if not self.energy_scale > 0:
            raise ValueError("the model's upright and hanging energies coincide; nothing to pump")
        gain_goal = np.array(terms.control_gain(tuple(self.goal)), dtype=float)  # 3×m
        # Orthonormal basis of the actuated axes: LQR lives in this subspace.
        u_svd, singular, _ = np.linalg.svd(gain_goal, full_matrices=False)
        self.actuated_basis = u_svd[:, singular > 1e-9 * singular.max()]
        self.lqr_gain = self._lqr()
        self.catching = False

    # ------------------------------------------------------------------ model
    def energy(self, q: np.ndarray, omega: np.ndarray) -> float:
        return float(fvin.total_energy(tuple(q), tuple(omega), self.terms))

    def _step(self, q: np.ndarray, omega: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        out = fvin.fvin_step(tuple(q), tuple(omega), tuple(u), self.terms, self.h, self.newton_iters, NP)
        return np.array(out.q, dtype=float), np.array(out.omega, dtype=float)

    def _reduced_state(self, q: np.ndarray, omega: np.ndarray) -> np.ndarray:
        """(angle error, ω) on the actuated axes; the error is ``2 log(q_goal* ⊗ q)`` (rad)."""
        relative = np.array(s3.multiply(s3.conjugate(tuple(self.goal)), tuple(q)), dtype=float)
        relative *= np.sign(relative[0]) or 1.0
        error = 2.0 * np.array(s3.log(tuple(relative), NP), dtype=float)
        return np.concatenate([self.actuated_basis.T @ error, self.actuated_basis.T @ omega])

    def _lqr(self) -> np.ndarray:
        r = self.actuated_basis.shape[1]
        m = self.low.size
        eps = 1e-6
        a_matrix, b_matrix = np.zeros((2 * r, 2 * r)), np.zeros((2 * r, m))
        for j in range(2 * r):
            # Perturb along the actuated axes only, in the same coordinates.
            delta_angle = self.actuated_basis @ (np.eye(2 * r)[j, :r] * eps)
            delta_omega = self.actuated_basis @ (np.eye(2 * r)[j, r:] * eps)
            q = np.array(s3.multiply(tuple(self.goal), s3.exp(tuple(delta_angle / 2), NP)), dtype=float)
            plus = self._reduced_state(*self._step(q, delta_omega, np.zeros(m)))
            q = np.array(s3.multiply(tuple(self.goal), s3.exp(tuple(-delta_angle / 2), NP)), dtype=float)
            minus = self._reduced_state(*self._step(q, -delta_omega, np.zeros(m)))
            a_matrix[:, j] = (plus - minus) / (2 * eps)
        for j in range(m):
            du = np.eye(m)[j] * eps
            plus = self._reduced_state(*self._step(self.goal, np.zeros(3), du))
            minus = self._reduced_state(*self._step(self.goal, np.zeros(3), -du))
            b_matrix[:, j] = (plus - minus) / (2 * eps)
        weights = np.r_[np.ones(r), 0.01 * np.ones(r)] * self.settings.lqr_state_weight
        q_cost, r_cost = np.diag(weights), self.settings.lqr_control_weight * np.eye(m)
        p = scipy.linalg.solve_discrete_are(a_matrix, b_matrix, q_cost, r_cost)
        return np.linalg.solve(r_cost + b_matrix.T @ p @ b_matrix, b_matrix.T @ p @ a_matrix)

    # ------------------------------------------------------------------ control
    def __call__(self, q: np.ndarray, omega: np.ndarray) -> tuple[np.ndarray, dict[str, Any]]:
        q, omega = np.asarray(q, dtype=float), np.asarray(omega, dtype=float)
        if q.shape != (4,) or omega.shape != (3,) or not (np.all(np.isfinite(q)) and np.all(np.isfinite(omega))):
            raise ValueError(f"expected finite q (4,) and omega (3,), got {q.shape}, {omega.shape}")
        q = q / np.linalg.norm(q)
        angle = float(s3.geodesic_angle(tuple(self.goal), tuple(q), NP))
        threshold = self.settings.release_angle if self.catching else self.settings.catch_angle
        self.catching = angle < threshold
        energy = self.energy(q, omega)
        if self.catching:
            u = -self.lqr_gain @ self._reduced_state(q, omega)
            mode = "lqr"
        else:
            gain = np.array(self.terms.control_gain(tuple(q)), dtype=float)
            direction = gain.T @ omega / np.linalg.norm(gain, axis=0)
            if np.linalg.norm(omega) < self.settings.kick_speed and energy < self.goal_energy:
                u, mode = self.high.copy(), "kick"
            else:
                u = self.settings.pump_gain * (self.goal_energy - energy) / self.energy_scale * direction
                mode = "pump"
        u = np.clip(u, self.low, self.high)
        return u, {"mode": mode, "energy": energy, "goal_energy": self.goal_energy, "angle_from_goal": angle,
                   "success": True, "solve_time_s": 0.0}

    def reset(self) -> None:
        self.catching = False
