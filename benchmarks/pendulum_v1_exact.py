"""Gymnasium's ``Pendulum-v1`` exactly: its constants, discrete map, reward and the episode NLP.

A leaf of the Pendulum-v1 study: the MPC study (:mod:`benchmarks.pendulum_v1_mpc`), the global
reference (:mod:`benchmarks.pendulum_v1_reference`), the learned value
(:mod:`benchmarks.pendulum_v1_value`) and the DP swing-up (:mod:`benchmarks.pendulum_v1_plan`)
all import it, and it imports none of them (before it existed the MPC study and the reference and
value modules imported each other).

    θ̇' = clip(θ̇ + (15 sin θ + 3u)·0.05, −8, 8),   θ' = θ + 0.05·θ̇'    (semi-implicit Euler)
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: Pendulum-v1's constants (gymnasium.envs.classic_control.pendulum, g = 10 as ``make`` uses).
DT, MAX_SPEED, MAX_TORQUE, GRAVITY, MASS, LENGTH = 0.05, 8.0, 2.0, 10.0, 1.0, 1.0
EPISODE_STEPS = 200


def angle_normalize(theta: Any) -> Any:
    """Pendulum-v1's ``((θ + π) mod 2π) − π``."""
    return ((theta + np.pi) % (2 * np.pi)) - np.pi


#: The map's rate increments per step: ``a sin θ + b u`` with ``a = 3g/(2l)·dt``, ``b = 3/(ml²)·dt``.
RATE_GAIN_SIN = 3 * GRAVITY / (2 * LENGTH) * DT
RATE_GAIN_TORQUE = 3.0 / (MASS * LENGTH**2) * DT


def v1_cost(theta: Any, theta_dot: Any, u: Any) -> Any:
    """Pendulum-v1's stage cost (minus its reward), ``angle_normalize(θ)² + 0.1θ̇² + 0.001u²``; arrays broadcast."""
    return angle_normalize(theta) ** 2 + 0.1 * theta_dot**2 + 0.001 * u**2


def v1_map(theta: Any, theta_dot: Any, u: Any) -> tuple[Any, Any]:
    """Pendulum-v1's update of ``(θ, θ̇)`` under ``u`` (already within ±2); numpy arrays broadcast."""
    new_theta_dot = np.clip(theta_dot + RATE_GAIN_SIN * np.sin(theta) + RATE_GAIN_TORQUE * u, -MAX_SPEED, MAX_SPEED)
    return theta + new_theta_dot * DT, new_theta_dot


def v1_step(theta: float, theta_dot: float, u: float) -> tuple[float, float, float]:
    """Pendulum-v1's update and reward, exactly as ``PendulumEnv.step``: ``(θ', θ̇', reward)``."""
    u = float(np.clip(u, -MAX_TORQUE, MAX_TORQUE))
    new_theta, new_theta_dot = v1_map(theta, theta_dot, u)
    return float(new_theta), float(new_theta_dot), -float(v1_cost(theta, theta_dot, u))


def replay(theta0: float, theta_dot0: float, controls: np.ndarray) -> tuple[float, np.ndarray]:
    """Return of ``controls`` from ``(θ₀, θ̇₀)`` under :func:`v1_step`, and the states ``(T+1, 2)``."""
    states, total = [(theta0, theta_dot0)], 0.0
    for u in np.asarray(controls, float).ravel():
        theta, theta_dot, reward = v1_step(*states[-1], u)
        states.append((theta, theta_dot))
        total += reward
    return total, np.array(states)


def heuristic_controls(theta0: float, theta_dot0: float, direction: float, steps: int = EPISODE_STEPS) -> np.ndarray:
    """A swing-up guess on the exact dynamics: energy pumping (first push in ``direction``) + PD near upright."""
    theta, theta_dot, controls = theta0, theta_dot0, []
    for _ in range(steps):
        phi = angle_normalize(theta)
        energy = 0.5 * theta_dot**2 / 3.0 + 5.0 * (np.cos(phi) - 1.0)  # zero upright at rest (J = 1/3, mgl/2 = 5)
        if abs(phi) < 0.6:
            u = -(20.0 * phi + 5.0 * theta_dot)
        elif abs(theta_dot) < 1e-3:
            u = direction * MAX_TORQUE
        else:
            u = -10.0 * energy * np.sign(theta_dot)
        u = float(np.clip(u, -MAX_TORQUE, MAX_TORQUE))
        controls.append(u)
        theta, theta_dot, _ = v1_step(theta, theta_dot, u)
    return np.array(controls)


class EpisodeOptimizer:
    """The whole episode as one NLP on Pendulum-v1's exact update (direct multiple shooting).

    Decision variables ``θ_0…θ_T``, ``θ̇_0…θ̇_T``, ``u_0…u_{T−1}``; objective the episode's
    cost ``Σ angle_normalize(θ_k)² + 0.1θ̇_k² + 0.001u_k²``; dynamics the semi-implicit Euler
    step; bounds ``|u| ≤ 2``, ``|θ̇_k| ≤ 8`` for ``k ≥ 1``, ``(θ_0, θ̇_0)`` fixed.

    The speed clip is non-smooth, so each solve fixes which steps it clips (a parameter
    ``c_k ∈ {−1, 0, +1}``): an unclipped step is the plain update (``θ̇_{k+1} = r_k``,
    ``r_k = θ̇_k + a sin θ_k + b u_k``, within the bound ±8); a clipped one sets
    ``θ̇_{k+1} = 8 c_k`` and keeps ``c_k r_k ≥ 8``. Every solution is then a trajectory of the
    clipped map. :meth:`solve` takes the pattern from the guess's replay and, if it clips,
    also tries never clipping.
    """

    def __init__(self, steps: int = EPISODE_STEPS, max_iter: int = 500, ipopt_options: dict | None = None) -> None:
        import casadi as ca

        self.steps = steps
        theta, rate, u = ca.SX.sym("theta", steps + 1), ca.SX.sym("rate", steps + 1), ca.SX.sym("u", steps)
        clip = ca.SX.sym("clip", steps)  # c_k: 0 the plain update, ±1 clipped at ±8
        wrapped = theta[:steps] - 2 * np.pi * ca.floor((theta[:steps] + np.pi) / (2 * np.pi))
        objective = ca.sumsqr(wrapped) + 0.1 * ca.sumsqr(rate[:steps]) + 0.001 * ca.sumsqr(u)
        raw_rate = rate[:steps] + RATE_GAIN_SIN * ca.sin(theta[:steps]) + RATE_GAIN_TORQUE * u
        next_rate = (1 - clip**2) * raw_rate + MAX_SPEED * clip
        defects = ca.vertcat(rate[1:] - next_rate, theta[1:] - (theta[:steps] + rate[1:] * DT))
        excess = clip * raw_rate - clip**2 * MAX_SPEED  # ≥ 0: a clipped step really exceeds the clip
        self._solver = ca.nlpsol("episode", "ipopt", {"x": ca.vertcat(theta, rate, u), "p": clip, "f": objective,
                                                      "g": ca.vertcat(defects, excess)},
                                 {"ipopt": {"print_level": 0, "sb": "yes", "max_iter": max_iter, "tol": 1e-8,
                                            **(ipopt_options or {})},
                                  "print_time": False, "error_on_fail": False})

    def solve(self, theta0: float, theta_dot0: float, controls_guess: np.ndarray,
              states_guess: np.ndarray | None = None) -> tuple[float, np.ndarray, str, float]:
        """Optimize from a control guess and its states ``(T+1, 2)`` (by default the controls replayed;
        a closed-loop episode's own states are a better start: replaying its controls open loop
        diverges near upright); the better of the guess's clip pattern and no clipping (class docstring).

        Returns ``(return, controls, status, max_defect)``: the return is minus the NLP's objective,
        i.e. the cost of the optimized trajectory, whose every step satisfies the exact update to
        ``max_defect``. (Replaying the controls open loop is no check: over 10 s the upright
        equilibrium amplifies a 1e-9 difference by ``e^(√15·10) ≈ 1e17``.)
        """
        controls_guess = np.clip(np.asarray(controls_guess, float).ravel(), -MAX_TORQUE, MAX_TORQUE)
        states = (
            replay(theta0, theta_dot0, controls_guess)[1] if states_guess is None else np.asarray(states_guess, float)
        )
        raw = states[:-1, 1] + RATE_GAIN_SIN * np.sin(states[:-1, 0]) + RATE_GAIN_TORQUE * controls_guess
        pattern = np.where(raw >= MAX_SPEED, 1.0, np.where(raw <= -MAX_SPEED, -1.0, 0.0))
        best = self._solve(theta0, theta_dot0, controls_guess, states, pattern)
        if pattern.any():
            plain = self._solve(theta0, theta_dot0, controls_guess, states, np.zeros_like(pattern))
            if plain[2] in ("Solve_Succeeded", "Solved_To_Acceptable_Level") and (
                    best[2] not in ("Solve_Succeeded", "Solved_To_Acceptable_Level") or plain[0] > best[0]):
                best = plain
        return best

    def _solve(self, theta0: float, theta_dot0: float, controls_guess: np.ndarray, states: np.ndarray,
               pattern: np.ndarray) -> tuple[float, np.ndarray, str, float]:
        n = self.steps
        lower = np.r_[np.full(n + 1, -np.inf), np.full(n + 1, -MAX_SPEED), np.full(n, -MAX_TORQUE)]
        upper = -lower
        lower[0] = upper[0] = theta0
        lower[n + 1] = upper[n + 1] = theta_dot0
        solution = self._solver(x0=np.r_[states[:, 0], states[:, 1], controls_guess], p=pattern, lbx=lower,
                                ubx=upper, lbg=0.0, ubg=np.r_[np.zeros(2 * n), np.full(n, np.inf)])
        x = np.asarray(solution["x"]).ravel()
        controls = np.clip(x[2 * (n + 1):], -MAX_TORQUE, MAX_TORQUE)
        g = np.asarray(solution["g"]).ravel()
        defect = float(max(np.abs(g[:2 * n]).max(), -min(g[2 * n:].min(), 0.0)))
        return -float(solution["f"]), controls, str(self._solver.stats()["return_status"]), defect
