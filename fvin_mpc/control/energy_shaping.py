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

Constructors: :meth:`EnergyShapingController.from_checkpoint` (the learned ``J``, ``U``,
``g`` of a trained model), :meth:`EnergyShapingController.from_model` (any
:class:`~fvin_mpc.control.model_export.ExportedModel`), :meth:`EnergyShapingController.from_rigid_body`
(the closed-form "true model") and :func:`scene_controller` (goal and torque bounds of a
scene's env). The LQR design is kept in :attr:`EnergyShapingController.lqr`
(:class:`LQRDesign`: ``A``, ``B``, the weights, the Riccati solution ``P`` and gain ``K``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg

from fvin_mpc.core import fvin, s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.space import S3
from fvin_mpc.core.state import unit_quaternion

NP = get_ops("numpy")
#: The law is written on S³ terms: a pivoted body's ``(q, ω)``.
_ATTITUDE = S3.layout.attitude(by="energy shaping")


def _split(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return x[_ATTITUDE.quaternion], x[_ATTITUDE.omega]


class EnergyShapingNotApplicable(ValueError):
    """The scene is outside what energy shaping handles here (e.g. a ball joint)."""


@dataclass(frozen=True)
class LQRDesign:
    """Discrete LQR on the model's step linearized at the goal, in reduced coordinates.

    The reduced state is ``x = (Bᵀ·angle error, Bᵀ·ω)`` with ``B`` the orthonormal basis of
    the actuated axes (``r`` columns), so ``x ∈ R^{2r}``. ``x_{k+1} ≈ A x_k + B u_k``;
    the gain ``K`` minimizes ``Σ xᵀQx + uᵀRu``, whose minimum from ``x_0`` is ``x_0ᵀ P x_0``.

    Attributes:
        a: ``(2r, 2r)`` state matrix. b: ``(2r, m)`` input matrix.
        q_cost: ``(2r, 2r)`` state weight. r_cost: ``(m, m)`` control weight.
        p: ``(2r, 2r)`` solution of the discrete algebraic Riccati equation.
        k: ``(m, 2r)`` gain, ``u = −K x``.
    """

    a: np.ndarray
    b: np.ndarray
    q_cost: np.ndarray
    r_cost: np.ndarray
    p: np.ndarray
    k: np.ndarray


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
    """``u, info = controller(x)`` for any :class:`~fvin_mpc.core.fvin.RigidBodyTerms` on NumPy."""

    def __init__(self, terms: Any, step_size: float, newton_iters: int, goal: np.ndarray, torque_low: np.ndarray,
                 torque_high: np.ndarray, rest: np.ndarray,
                 settings: EnergyShapingSettings = EnergyShapingSettings()) -> None:
        self.terms = terms
        self.h = step_size
        self.newton_iters = newton_iters
        self.goal = unit_quaternion(goal, "goal")
        self.rest = unit_quaternion(rest, "rest")
        self.low, self.high = np.asarray(torque_low, float), np.asarray(torque_high, float)
        self.settings = settings
        zero3 = np.zeros(3)
        self.goal_energy = float(fvin.total_energy(tuple(self.goal), tuple(zero3), terms))
        self.rest_energy = float(fvin.total_energy(tuple(self.rest), tuple(zero3), terms))
        self.energy_scale = abs(self.goal_energy - self.rest_energy)
        if not self.energy_scale > 0:
            raise ValueError("the model's goal and rest energies coincide; nothing to pump")
        gain_goal = np.array(terms.control_gain(tuple(self.goal)), dtype=float)  # 3×m
        # Orthonormal basis of the actuated axes: LQR lives in this subspace.
        u_svd, singular, _ = np.linalg.svd(gain_goal, full_matrices=False)
        self.actuated_basis = u_svd[:, singular > 1e-9 * singular.max()]
        self.lqr = self._lqr()
        self.lqr_gain = self.lqr.k
        self.catching = False

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_model(cls, model: Any, goal: Any, torque_low: Any, torque_high: Any, rest: Any,
                   settings: EnergyShapingSettings = EnergyShapingSettings()) -> "EnergyShapingController":
        """From an :class:`~fvin_mpc.control.model_export.ExportedModel` — learned or closed form — using
        its NumPy ``J``, ``U``, ``g``, its ``h`` and ``K``; no torch. The law is written on S³ terms."""
        model.require(S3, by="energy shaping")
        return cls(model.numpy_terms, model.step_size, model.newton_iters, goal, torque_low, torque_high, rest,
                   settings)

    # ------------------------------------------------------------------ model
    def energy(self, x: np.ndarray) -> float:
        """The model's ``½ωᵀJω + U(q)`` of a state ``x = (q, ω)`` ``(7,)``."""
        q, omega = _split(np.asarray(x, dtype=float))
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

    def reduced_state(self, x: np.ndarray) -> np.ndarray:
        """The LQR's coordinates of a state ``x = (q, ω)`` ``(7,)`` (see :class:`LQRDesign`)."""
        return self._reduced_state(*_split(S3.check(x)))

    def _lqr(self) -> LQRDesign:
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
        gain = np.linalg.solve(r_cost + b_matrix.T @ p @ b_matrix, b_matrix.T @ p @ a_matrix)
        return LQRDesign(a=a_matrix, b=b_matrix, q_cost=q_cost, r_cost=r_cost, p=p, k=gain)

    # ------------------------------------------------------------------ control
    def __call__(self, x: Any) -> tuple[np.ndarray, dict[str, Any]]:
        """The control for the measured state ``x = (q, ω)`` ``(7,)`` (validated by
        ``StateLayout.check``, the controllers' shared input policy)."""
        x = S3.check(x)
        q, omega = _split(x)
        angle = float(s3.geodesic_angle(tuple(self.goal), tuple(q), NP))
        threshold = self.settings.release_angle if self.catching else self.settings.catch_angle
        self.catching = angle < threshold
        energy = self.energy(x)
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
