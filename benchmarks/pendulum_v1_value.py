"""A value function of the *learned* model for Pendulum-v1's cost: what follows the MPC's horizon.

The MPC's horizon (30 steps, 1.5 s) is shorter than a swing-up from near hanging; with only a
local terminal cost (orientation, speed, energy deficit) it cannot tell one pump swing from two,
or the left swing from the right. This module estimates the cost of the rest of the episode. Two
uses, measured in ``docs/pendulum-v1.md``: ranking the cold call's multi-start plans
(:func:`plan_score`, ``--rank-cold-starts``: seed 53 +41, no other seed changed); its greedy policy
as the swing-up before the MPC's catch, chosen per episode by simulation on the model
(:mod:`benchmarks.pendulum_v1_plan`, ``--dp-swing-up``). As the MPC's terminal cost it measured far
worse (its plans end on knife edges that the model/plant mismatch breaks; docs/pendulum-v1.md), and
that option was removed.

1. **Transitions** (:func:`learned_transitions`): the learned model's step ``F(x, u)`` (the MPC's own
   exported step, no knowledge of Pendulum-v1's map) from every point of a grid ``θ_i`` (periodic,
   ``n_theta`` points on ``[−π, π)``, θ = 0 upright as in Pendulum-v1) × ``θ̇_j`` (``n_rate`` points on
   ``[−8, 8]``) under ``n_torque`` torques evenly on ``[−2, 2]``; the next rate clamped to ±8 (the
   MPC's bound on its predictions, Pendulum-v1's clip).
2. **Value iteration** (:func:`value_iteration`): ``V_0 = 0``,
   ``V_τ(x) = min_u c(x, u) + V_{τ−1}(F(x, u))`` with ``V_{τ−1}`` interpolated bilinearly (θ periodic)
   and ``c`` Pendulum-v1's stage cost ``angle² + 0.1 θ̇² + 0.001 u²`` — the benchmark's objective, the
   cost the reference minimizes. ``τ = steps`` (default 200 − the MPC's horizon) time to go; the
   swing-ups end long before, so the value has settled (the MPC uses one table at every step).

The MPC stays a local solver over its horizon on the learned model; the value only ranks the
states where its plans end. Nothing here reads Pendulum-v1's own map.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from benchmarks.pendulum_v1_exact import EPISODE_STEPS, MAX_SPEED, MAX_TORQUE, v1_cost
from fvin_mpc.control.model_export import cache_dir
from fvin_mpc.envs.pendulum_v1 import state_from_v1_observation, v1_observation_from_state

#: Grid of the learned model's value function: ``(n_theta, n_rate)`` and torques per state.
VALUE_GRID: tuple[int, int] = (256, 129)
VALUE_TORQUES = 21


def mpc_stage_cost(theta: Any, theta_dot: Any, u: Any) -> Any:
    """The benchmark MPC's stage cost (:func:`~benchmarks.pendulum_v1_mpc.benchmark_settings`) in
    Pendulum-v1's angle: ``4 sin²(θ/2) + 0.1 θ̇² + 0.001 u²`` (``≈ θ²`` near upright, 4 hanging)."""
    return 4.0 * np.sin(0.5 * theta) ** 2 + 0.1 * theta_dot**2 + 0.001 * u**2


#: Stage costs of the value iteration: the MPC's own (consistent with its horizon's stage cost) or
#: Pendulum-v1's (the benchmark's objective; ``angle²`` is 9.87 hanging where the MPC's stage pays 4).
STAGE_COSTS: dict[str, Callable[[Any, Any, Any], Any]] = {"mpc": mpc_stage_cost, "v1": v1_cost}


def grid_axes(n_theta: int, n_rate: int) -> tuple[np.ndarray, np.ndarray]:
    """``θ_i = −π + 2πi/n_theta`` (periodic) and ``θ̇_j`` evenly on ``[−8, 8]``."""
    if n_theta < 4 or n_rate < 3:
        raise ValueError(f"need n_theta >= 4 and n_rate >= 3, got {n_theta}, {n_rate}")
    return -np.pi + 2 * np.pi * np.arange(n_theta) / n_theta, np.linspace(-MAX_SPEED, MAX_SPEED, n_rate)


def learned_transitions(model: Any, thetas: np.ndarray, rates: np.ndarray, torques: np.ndarray,
                        chunk: int = 200_000) -> tuple[np.ndarray, np.ndarray]:
    """The model's next ``(θ', θ̇')`` (Pendulum-v1 angles, θ' wrapped to ``[−π, π)``), each of shape
    ``(n_theta, n_rate, n_torque)``, from every grid state under every torque (``model.step`` mapped)."""

    theta, rate, torque = np.meshgrid(thetas, rates, torques, indexing="ij")
    observation = np.stack([np.cos(theta), np.sin(theta), rate], axis=-1).reshape(-1, 3)
    states = state_from_v1_observation(observation)
    controls = torque.reshape(-1, 1)
    next_states = np.empty_like(states)
    mapped = None
    for start in range(0, len(states), chunk):
        stop = min(start + chunk, len(states))
        if mapped is None or stop - start != chunk:
            mapped = model.step.map(stop - start)
        next_states[start:stop] = np.asarray(mapped(states[start:stop].T, controls[start:stop].T)[0]).T
    observed = v1_observation_from_state(next_states)
    next_theta = np.arctan2(observed[:, 1], observed[:, 0])
    shape = theta.shape
    return next_theta.reshape(shape), observed[:, 2].reshape(shape)


@dataclass(frozen=True)
class _Stencil:
    """Bilinear interpolation of a periodic-in-θ grid at fixed points: 4 flat indices and weights."""

    index: np.ndarray  # (4, P) int64
    weight: np.ndarray  # (4, P)


def _stencil(n_theta: int, n_rate: int, theta: np.ndarray, rate: np.ndarray) -> _Stencil:
    x = (np.asarray(theta, float).ravel() + np.pi) * (n_theta / (2 * np.pi))
    i0 = np.floor(x)
    fx = x - i0
    i0 = i0.astype(np.int64) % n_theta
    i1 = (i0 + 1) % n_theta
    y = (np.clip(np.asarray(rate, float).ravel(), -MAX_SPEED, MAX_SPEED) + MAX_SPEED) * ((n_rate - 1) / (2 * MAX_SPEED))
    j0 = np.minimum(np.floor(y).astype(np.int64), n_rate - 2)
    fy = y - j0
    index = np.stack([i0 * n_rate + j0, i0 * n_rate + j0 + 1, i1 * n_rate + j0, i1 * n_rate + j0 + 1])
    weight = np.stack([(1 - fx) * (1 - fy), (1 - fx) * fy, fx * (1 - fy), fx * fy])
    return _Stencil(index, weight)


def interpolate(table: np.ndarray, theta: Any, rate: Any) -> np.ndarray:
    """Bilinear interpolation of ``table (n_theta, n_rate)`` at ``(θ, θ̇)`` (θ periodic, θ̇ clamped to ±8)."""
    theta, rate = np.broadcast_arrays(np.asarray(theta, float), np.asarray(rate, float))
    stencil = _stencil(*table.shape, theta, rate)
    flat = np.asarray(table, float).ravel()
    return np.sum(stencil.weight * flat[stencil.index], axis=0).reshape(theta.shape)


def value_iteration(next_theta: np.ndarray, next_rate: np.ndarray, torques: np.ndarray, steps: int,
                    stage_cost: Callable[[Any, Any, Any], Any] = v1_cost,
                    noise: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """``V_steps`` on the grid whose transitions are ``next_theta, next_rate (n_theta, n_rate, n_torque)``
    (module docstring, step 2): ``V_τ = min_u c(x, u) + E V_{τ−1}(F(x, u) + ε)``, bilinear, θ periodic.

    ``noise = (σ_θ, σ_θ̇)``: the next state's error ``ε`` (normal, independent; rad and rad/s), the
    expectation taken as a Gaussian filter of ``V_{τ−1}`` on the grid (periodic in θ, the rate's ends
    repeated). The model is not the plant: without noise the optimal plans end on the edge of a cliff
    of the value (just enough energy to go over the top, the next state one more pump swing away),
    where the plant's first deviation costs a whole swing; with noise the value there is the average
    of both sides and the plans keep a margin. ``(0, 0)``: the deterministic DP.
    """
    from scipy.ndimage import gaussian_filter1d

    n_theta, n_rate, n_torque = next_theta.shape
    if len(torques) != n_torque or steps < 0:
        raise ValueError(f"need {n_torque} torques and steps >= 0, got {len(torques)} and {steps}")
    if not (noise[0] >= 0 and noise[1] >= 0):
        raise ValueError(f"noise must be >= 0, got {noise}")
    thetas, rates = grid_axes(n_theta, n_rate)
    sigma_cells = (noise[0] * n_theta / (2 * np.pi), noise[1] * (n_rate - 1) / (2 * MAX_SPEED))
    cost = stage_cost(thetas[:, None, None], rates[None, :, None], np.asarray(torques, float)[None, None, :])
    cost = np.broadcast_to(cost, next_theta.shape).reshape(-1)
    stencil = _stencil(n_theta, n_rate, next_theta, next_rate)
    value = np.zeros(n_theta * n_rate)
    for _ in range(steps):
        expected = value.reshape(n_theta, n_rate)
        if sigma_cells[0] > 0:
            expected = gaussian_filter1d(expected, sigma_cells[0], axis=0, mode="wrap")
        if sigma_cells[1] > 0:
            expected = gaussian_filter1d(expected, sigma_cells[1], axis=1, mode="nearest")
        candidates = cost + np.sum(stencil.weight * expected.ravel()[stencil.index], axis=0)
        value = candidates.reshape(n_theta * n_rate, n_torque).min(axis=1)
    return value.reshape(n_theta, n_rate)


def model_value_table(model: Any, grid: tuple[int, int] = VALUE_GRID, torques: int = VALUE_TORQUES,
                      steps: int = EPISODE_STEPS - 30, noise: tuple[float, float] = (0.0, 0.0),
                      stage_cost: str = "mpc", max_torque: float = MAX_TORQUE, cache: bool = True) -> np.ndarray:
    """``V_steps`` of the learned ``model`` for Pendulum-v1's cost on ``grid``; cached on disk under the
    MPC's compile cache (key: the step function's serialization, the grid, torques and steps)."""

    torque_values = np.linspace(-max_torque, max_torque, torques)
    key = hashlib.sha256(
        model.step.serialize().encode() + repr((grid, torques, steps, tuple(noise), stage_cost, max_torque)).encode()
    ).hexdigest()[:20]
    path = cache_dir() / f"pendulum_v1_value_{key}.npy"
    if cache and path.is_file():
        return np.load(path)
    transitions_path = cache_dir() / f"pendulum_v1_transitions_{key_transitions(model, grid, torques, max_torque)}.npz"
    if cache and transitions_path.is_file():
        with np.load(transitions_path) as data:
            next_theta, next_rate = data["theta"], data["rate"]
    else:
        next_theta, next_rate = learned_transitions(model, *grid_axes(*grid), torque_values)
        if cache:
            transitions_path.parent.mkdir(parents=True, exist_ok=True)
            np.savez(transitions_path.with_suffix(".tmp.npz"), theta=next_theta, rate=next_rate)
            transitions_path.with_suffix(".tmp.npz").replace(transitions_path)
    table = value_iteration(next_theta, next_rate, torque_values, steps, STAGE_COSTS[stage_cost], tuple(noise))
    if cache:
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(".tmp.npy")
        np.save(partial, table)
        partial.replace(path)
    return table


def key_transitions(model: Any, grid: tuple[int, int], torques: int, max_torque: float) -> str:
    return hashlib.sha256(
        model.step.serialize().encode() + repr((tuple(grid), torques, max_torque)).encode()
    ).hexdigest()[:20]


def plan_score(table: np.ndarray, stage_cost: str = "v1") -> Callable[[np.ndarray, np.ndarray], float]:
    """``(states (N+1, 7), controls (N, 1)) ↦ Σ_k c(x_k, u_k) + V(x_N)``: a plan's estimate of the whole
    episode's cost (the stage cost over the horizon, the value ``table`` bilinear after it), to rank the
    MPC's cold-start plans (:class:`~fvin_mpc.control.mpc.MPC`'s ``cold_start_score``)."""

    cost = STAGE_COSTS[stage_cost]

    def score(states: np.ndarray, controls: np.ndarray) -> float:
        observed = v1_observation_from_state(np.asarray(states, float))
        theta = np.arctan2(observed[:, 1], observed[:, 0])
        u = np.asarray(controls, float).reshape(len(theta) - 1, -1)[:, 0]
        return float(np.sum(cost(theta[:-1], observed[:-1, 2], u)) + interpolate(table, theta[-1], observed[-1, 2]))

    return score


__all__ = [
    "VALUE_GRID",
    "VALUE_TORQUES",
    "grid_axes",
    "interpolate",
    "learned_transitions",
    "model_value_table",
    "plan_score",
    "value_iteration",
]

