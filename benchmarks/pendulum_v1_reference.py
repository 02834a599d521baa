"""A global reference for Pendulum-v1's 200-step episode: dynamic programming on the exact map, polished.

The problem per seed: from Gymnasium's initial state ``(θ₀, θ̇₀)``, choose ``u_0 … u_199`` in
``[−2, 2]`` to minimize ``Σ angle_normalize(θ_k)² + 0.1 θ̇_k² + 0.001 u_k²`` under Pendulum-v1's
exact discrete map (:func:`benchmarks.pendulum_v1_mpc.v1_step`): semi-implicit Euler,

    θ̇' = clip(θ̇ + a sin θ + b u, −8, 8),   θ' = θ + dt θ̇',   a = 3g/(2l)·dt = 0.75,  b = 3/(ml²)·dt = 0.15.

A local optimizer (the direct multiple shooting of :class:`~benchmarks.pendulum_v1_mpc.EpisodeOptimizer`)
finds the optimum nearest its first guess; a swing-up has many (left or right first, how many pump
swings, catch or fall through), and the old reference — three first guesses — missed the best one on
many seeds. This module searches globally first:

1. **Value iteration** (:func:`solve_value_tables`) on a grid ``θ_i`` (periodic, ``n_theta`` points on
   ``[−π, π)``) × ``θ̇_j`` (``n_rate`` points on ``[−8, 8]``), backwards over the 200 steps, time to go
   ``τ = 0 … 200``, ``V_0 = 0``. The next state lies on the line ``θ' = θ + dt θ̇'`` parametrized by
   ``θ̇'``, so the value is interpolated in two 1-D passes: ``G(θ_i, θ̇'_m) = V(θ_i + dt θ̇'_m, θ̇'_m)``
   (linear in θ, periodic), then linear in ``θ̇'`` between grid rates. ``u ↦ G`` is then piecewise
   linear with breakpoints where ``θ̇'`` is a grid rate, so the minimum over the *continuous* torque
   of ``0.001u² + G`` is taken over those breakpoints, ``u = ±2`` and ``u = 0`` (the clip makes
   ``G`` constant beyond ``±8``); between breakpoints ``Δu = Δθ̇/b`` the quadratic's own minimum
   is missed by at most ``0.001 (Δu/2)²`` per step. No torque grid: the minimum is exact for the
   interpolated value.
2. **Rollout** (:func:`greedy_rollouts`) of the DP's policy on the *exact* map from every seed: at each
   step the torque minimizing ``0.001u² + V_{τ−1}(f(x, u))`` (bilinear interpolation) over a fine
   torque grid. Its return is exact (the trajectory is the map's), so it is a feasible return.
3. **Noisy rollouts** on the finest grid: the same policy with normal torque noise (σ = 0.1 and 0.3,
   :data:`NOISY_ROLLOUTS` per level); the best few by exact return are kept, in two independent halves.
   The greedy rollout follows the DP's value, whose interpolation smears out knife-edge swing-ups
   (just enough energy to arrive upright): it prefers robust strategies and can miss the best one by
   a whole extra swing (seed 28: −237.5 greedy at 1024 × 513, −214.9 from a noisy rollout).
4. **Polish**: every rollout, the MPC's own episode and the two energy-pumping heuristics are first
   guesses of the episode NLP (:class:`~benchmarks.pendulum_v1_mpc.EpisodeOptimizer`, from IPOPT's
   default start and from a local start, :data:`LOCAL_POLISH_OPTIONS`); the reference is the best of
   the exact returns of the guesses and of the converged NLP solutions.

**Checks.** No rigorous bound: the interpolation error is not bounded (the map's Lipschitz constant
compounds over 200 steps), so what is reported is evidence. Per grid, the DP's estimate ``−V_200(x₀)``,
the greedy rollout's exact return and its polished return, coarse to fine (each grid halves both
spacings). Per family of first guesses, the best return (:func:`converged`: both independent halves
of the noisy restarts reach the reference) and whether the MPC's own episode beats the search
without it (a missed optimum that the MPC found).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from benchmarks.pendulum_v1_exact import (
    DT,
    EPISODE_STEPS,
    MAX_SPEED,
    MAX_TORQUE,
    RATE_GAIN_SIN,
    RATE_GAIN_TORQUE,
    EpisodeOptimizer,
    heuristic_controls,
    replay,
    v1_cost,
    v1_map,
)

#: The reference's DP grids ``(n_theta, n_rate)``, coarse to fine: each halves both spacings of the previous.
REFERENCE_GRIDS: tuple[tuple[int, int], ...] = ((256, 129), (512, 257), (1024, 513))
#: Grids of the convergence study.
DEFAULT_RESOLUTIONS = REFERENCE_GRIDS
#: Two polished returns closer than this are the same local optimum (the NLP's tolerance is 1e-8).
AGREEMENT_TOLERANCE = 1e-3
#: Torques tried per step of a rollout (spacing 0.01).
ROLLOUT_TORQUES = 401
#: Noisy rollouts on the finest grid: torque noise levels, rollouts per level and seed, and how many
#: of them (the best by exact return) per level are polished, in two independent halves ("a", "b").
NOISE_LEVELS: tuple[float, ...] = (0.1, 0.3)
NOISY_ROLLOUTS = 32
NOISY_POLISHED = 4
#: IPOPT solutions accepted as polished (their every step satisfies the exact update to this).
MAX_DEFECT = 1e-6
#: IPOPT options of the *local* polish: a small initial barrier and no push off the torque bounds, so
#: that a bang-bang guess is refined where it is instead of being moved (by IPOPT's default barrier,
#: μ₀ = 0.1) into the basin of another, sometimes worse, local optimum.
LOCAL_POLISH_OPTIONS = {"mu_init": 1e-4, "bound_push": 1e-8, "bound_frac": 1e-8}


def polishers(steps: int = EPISODE_STEPS) -> tuple[EpisodeOptimizer, ...]:
    """The episode NLP with IPOPT's default start and with :data:`LOCAL_POLISH_OPTIONS`."""
    return EpisodeOptimizer(steps), EpisodeOptimizer(steps, ipopt_options=LOCAL_POLISH_OPTIONS)


@dataclass(frozen=True)
class ValueTables:
    """The DP's values ``values[τ, i, j] ≈ V_τ(θ_i, θ̇_j)`` (float32, time to go ``τ = 0 … steps``).

    ``θ_i = −π + 2πi/n_theta``, ``θ̇_j = −8 + 16j/(n_rate − 1)``. Stored in float32 (a 1024 × 513 grid
    over 201 steps is 420 MB): the tables only guide the rollout, whose return is computed exactly.
    """

    values: np.ndarray

    @property
    def steps(self) -> int:
        return self.values.shape[0] - 1

    @property
    def shape(self) -> tuple[int, int]:
        return self.values.shape[1], self.values.shape[2]

    def interpolate(self, to_go: int, theta: np.ndarray, rate: np.ndarray) -> np.ndarray:
        """Bilinear interpolation of ``V_to_go`` at ``(θ, θ̇)`` (any shape; θ periodic, θ̇ clamped to ±8)."""
        n_theta, n_rate = self.shape
        table = self.values[to_go].ravel()
        x = (np.asarray(theta, dtype=np.float64) + np.pi) * (n_theta / (2 * np.pi))
        i0 = np.floor(x)
        fx = x - i0
        i0 = i0.astype(np.int64) % n_theta
        i1 = (i0 + 1) % n_theta
        y = (np.clip(rate, -MAX_SPEED, MAX_SPEED) + MAX_SPEED) * ((n_rate - 1) / (2 * MAX_SPEED))
        j0 = np.minimum(np.floor(y).astype(np.int64), n_rate - 2)
        fy = y - j0
        return ((1 - fx) * ((1 - fy) * table[i0 * n_rate + j0] + fy * table[i0 * n_rate + j0 + 1])
                + fx * ((1 - fy) * table[i1 * n_rate + j0] + fy * table[i1 * n_rate + j0 + 1]))


def solve_value_tables(n_theta: int, n_rate: int, steps: int = EPISODE_STEPS, progress: bool = False) -> ValueTables:
    """Value iteration of the exact map on an ``n_theta × n_rate`` grid (module docstring, step 1)."""
    from tqdm.auto import tqdm

    if n_theta < 4 or n_rate < 3:
        raise ValueError(f"need n_theta >= 4 and n_rate >= 3, got {n_theta}, {n_rate}")
    theta = -np.pi + 2 * np.pi * np.arange(n_theta) / n_theta
    rate = np.linspace(-MAX_SPEED, MAX_SPEED, n_rate)
    d_theta, d_rate = 2 * np.pi / n_theta, 2 * MAX_SPEED / (n_rate - 1)
    stage = v1_cost(theta[:, None], rate[None, :], 0.0)
    gravity_kick = RATE_GAIN_SIN * np.sin(theta)  # θ̇' − θ̇ without torque, per row
    rows, columns = np.arange(n_theta)[:, None], np.arange(n_rate)[None, :]
    # Pass 1, G(θ_i, θ̇'_m) = V(θ_i + dt θ̇'_m, θ̇'_m): a constant shift of column m along θ.
    shift = DT * rate / d_theta
    whole = np.floor(shift).astype(np.int64)
    frac = shift - whole
    below = (rows + whole[None, :]) % n_theta
    above = (below + 1) % n_theta
    # Pass 2, breakpoints θ̇'_m = θ̇_j + kick_i + b·u on the grid: m = j + first_i + e, e = 0 … span.
    torque_reach = RATE_GAIN_TORQUE * MAX_TORQUE
    first = np.ceil((-torque_reach - gravity_kick) / d_rate - 1e-12).astype(np.int64)
    span = int(np.floor(2 * torque_reach / d_rate)) + 1
    # The end points and u = 0, through the clip (linear in θ̇' between grid rates).
    end_points = []
    for u in (-MAX_TORQUE, 0.0, MAX_TORQUE):
        y = (np.clip(rate[None, :] + gravity_kick[:, None] + RATE_GAIN_TORQUE * u, -MAX_SPEED, MAX_SPEED)
             + MAX_SPEED) / d_rate
        m0 = np.minimum(np.floor(y).astype(np.int64), n_rate - 2)
        end_points.append((rows * n_rate + m0, y - m0, 0.001 * u * u))
    values = np.zeros((steps + 1, n_theta, n_rate), dtype=np.float32)
    value = np.zeros((n_theta, n_rate))
    for to_go in tqdm(range(1, steps + 1), desc=f"DP {n_theta}x{n_rate}", disable=not progress, leave=False):
        g = ((1 - frac) * value[below, columns] + frac * value[above, columns]).ravel()
        best = np.full((n_theta, n_rate), np.inf)
        for e in range(span + 1):
            offset = first + e
            u = (offset * d_rate - gravity_kick) / RATE_GAIN_TORQUE  # per row
            m = columns + offset[:, None]
            usable = (np.abs(u) <= MAX_TORQUE + 1e-12)[:, None] & (m >= 0) & (m < n_rate)
            candidate = g[rows * n_rate + np.clip(m, 0, n_rate - 1)] + (0.001 * u * u)[:, None]
            np.minimum(best, np.where(usable, candidate, np.inf), out=best)
        for index, weight, control_cost in end_points:
            np.minimum(best, (1 - weight) * g[index] + weight * g[index + 1] + control_cost, out=best)
        value = stage + best
        values[to_go] = value
    return ValueTables(values)


def greedy_rollouts(tables: ValueTables, theta0: Sequence[float], rate0: Sequence[float],
                    torques: int = ROLLOUT_TORQUES, noise: float = 0.0,
                    rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The DP's policy on the exact map from each initial state (module docstring, step 2); with
    ``noise > 0`` each torque is perturbed by a normal of that standard deviation (clipped to ±2), which
    lands the rollout in a neighbouring local optimum's basin.

    Returns ``(controls (S, steps), returns (S,))``; the returns are the exact map's.
    """
    theta = np.asarray(theta0, dtype=np.float64).copy()
    rate = np.asarray(rate0, dtype=np.float64).copy()
    candidates = np.linspace(-MAX_TORQUE, MAX_TORQUE, torques)
    steps = tables.steps
    controls, returns = np.zeros((theta.size, steps)), np.zeros(theta.size)
    for k in range(steps):
        next_theta, next_rate = v1_map(theta[:, None], rate[:, None], candidates[None, :])
        q = 0.001 * candidates**2 + tables.interpolate(steps - k - 1, next_theta, next_rate)
        u = candidates[np.argmin(q, axis=1)]
        if noise > 0:
            u = np.clip(u + noise * rng.standard_normal(u.shape), -MAX_TORQUE, MAX_TORQUE)
        controls[:, k] = u
        returns -= v1_cost(theta, rate, u)
        theta, rate = v1_map(theta, rate, u)
    return controls, returns


def dp_estimate(tables: ValueTables, theta0: Sequence[float], rate0: Sequence[float]) -> np.ndarray:
    """The DP's own estimate of the optimal return, ``−V_steps(θ₀, θ̇₀)`` (interpolated)."""
    return -tables.interpolate(tables.steps, np.asarray(theta0, float), np.asarray(rate0, float))


def polish(theta0: float, rate0: float, guesses: dict[str, Any],
           optimizers: Sequence[EpisodeOptimizer]) -> dict[str, dict[str, float]]:
    """Each named guess's exact return and its best optimized return over ``optimizers`` (NaN if none
    converged to :data:`MAX_DEFECT`).

    A guess is controls ``(T,)``, or ``(controls, states (T+1, 2), return)`` for a closed-loop episode
    (the MPC's): its states start the NLP and its return is the episode's (an open-loop replay of its
    controls diverges near upright).
    """
    out: dict[str, dict[str, float]] = {}
    for name, guess in guesses.items():
        if isinstance(guess, tuple):
            controls, states, guess_return = guess
        else:
            controls, states = guess, None
            guess_return, _ = replay(theta0, rate0, controls)
        polished = float("nan")
        for optimizer in optimizers:
            total, _, status, defect = optimizer.solve(theta0, rate0, controls, states)
            if status in ("Solve_Succeeded", "Solved_To_Acceptable_Level") and defect <= MAX_DEFECT:
                polished = float(np.fmax(polished, total))
        out[name] = {"guess": float(guess_return), "polished": polished}
    return out


def best_of(polished: dict[str, dict[str, float]]) -> tuple[float, str]:
    """The best return among the guesses and their polished solutions, and where it came from."""
    best, source = -np.inf, ""
    for name, result in polished.items():
        for kind in ("guess", "polished"):
            value = result[kind]
            if np.isfinite(value) and value > best:
                best, source = value, f"{name} ({kind})"
    return float(best), source


def resolution_name(resolution: tuple[int, int]) -> str:
    return f"dp{resolution[0]}x{resolution[1]}"


def rollout_guesses(initial: np.ndarray, resolutions: Sequence[tuple[int, int]] = DEFAULT_RESOLUTIONS,
                    steps: int = EPISODE_STEPS, progress: bool = False,
                    seed: int = 0) -> tuple[dict[str, dict[str, np.ndarray]], list[dict[str, np.ndarray]]]:
    """First guesses for ``initial (S, 2)`` from the DP.

    Returns ``(greedy, noisy)``: ``greedy[grid name]`` the greedy rollouts' ``controls (S, steps)``,
    exact ``returns`` and the DP's ``estimates``, per grid; ``noisy[s]`` for seed ``s`` the named
    controls of the best :data:`NOISY_POLISHED` of :data:`NOISY_ROLLOUTS` noisy rollouts per noise
    level on the finest grid, split into two independent halves (names ``noisy<σ><half>-<i>``). The
    tables of one grid are freed before the next is solved (the finest is the largest).
    """
    initial = np.asarray(initial, dtype=np.float64).reshape(-1, 2)
    rng = np.random.default_rng(seed)
    greedy: dict[str, dict[str, np.ndarray]] = {}
    noisy: list[dict[str, np.ndarray]] = [{} for _ in initial]
    for resolution in resolutions:
        tables = solve_value_tables(*resolution, steps=steps, progress=progress)
        controls, returns = greedy_rollouts(tables, initial[:, 0], initial[:, 1])
        greedy[resolution_name(resolution)] = {"controls": controls, "returns": returns,
                                               "estimates": dp_estimate(tables, initial[:, 0], initial[:, 1])}
        if resolution == tuple(resolutions[-1]):
            half = NOISY_ROLLOUTS // 2
            for sigma in NOISE_LEVELS:
                repeated = np.repeat(initial, NOISY_ROLLOUTS, axis=0)
                controls, returns = greedy_rollouts(tables, repeated[:, 0], repeated[:, 1], torques=101,
                                                    noise=sigma, rng=rng)
                controls = controls.reshape(len(initial), NOISY_ROLLOUTS, steps)
                returns = returns.reshape(len(initial), NOISY_ROLLOUTS)
                for s in range(len(initial)):
                    for name, block in (("a", slice(0, half)), ("b", slice(half, NOISY_ROLLOUTS))):
                        order = np.argsort(-returns[s, block])[:NOISY_POLISHED // 2]
                        for i, j in enumerate(order):
                            noisy[s][f"noisy{sigma:g}{name}-{i}"] = controls[s, block][j]
        del tables
    return greedy, noisy


def reference_for_seed(theta0: float, rate0: float, guesses: dict[str, Any],
                       optimizers: Sequence[EpisodeOptimizer] | None = None) -> dict[str, Any]:
    """The per-seed reference (module docstring, step 3) from named first guesses (the DP rollouts,
    the MPC's episode); the two energy-pumping heuristics are added here."""
    optimizers = optimizers or polishers()
    steps = optimizers[0].steps
    guesses = dict(guesses)
    for direction, name in ((1.0, "heuristic+"), (-1.0, "heuristic-")):
        guesses[name] = heuristic_controls(theta0, rate0, direction, steps)
    results = polish(theta0, rate0, guesses, optimizers)
    value, source = best_of(results)
    return {"return": value, "source": source, "candidates": results}


def converged(families: dict[str, float], reference: float, tolerance: float = AGREEMENT_TOLERANCE) -> bool:
    """Both independent halves of the noisy restarts reach the reference (the best of every guess,
    the MPC's episode included) within ``tolerance``."""
    return bool(all(abs(families[half] - reference) <= tolerance for half in ("noisy-a", "noisy-b")))


__all__ = ["AGREEMENT_TOLERANCE", "DEFAULT_RESOLUTIONS", "ValueTables", "best_of", "converged", "dp_estimate",
           "greedy_rollouts", "polish", "polishers", "reference_for_seed", "rollout_guesses", "solve_value_tables"]
