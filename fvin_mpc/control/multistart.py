"""MPC with several first guesses on cold solves: :class:`MultiStartMPC`.

A swing-up NLP has many local optima (swing left or right first, pump now or one swing
later, catch the pendulum near upright or let it fall through a full turn). The plain
:class:`~fvin_mpc.control.mpc.MPC` starts every cold solve from one guess (the model rolled out under
a constant torque), and IPOPT, a local method, converges to the optimum nearest to it.
Warm starts then follow that choice for the rest of the episode. Measured in
``docs/evaluation.md`` and ``docs/pendulum-v1.md``: started near upright, every constant
torque guess falls, and the MPC takes a full extra turn (cost ≈ 125 instead of ≈ 2).

:class:`MultiStartMPC` solves a cold problem (the first call after ``reset()``, or after a
zero fallback) from each of :data:`GUESSES` and keeps the successful solve of lowest cost;
warm-started calls are unchanged. The cold call costs one solve per guess. With
``restart_every = k`` every k-th call also solves from the cold guesses, and the warm plan
competes with them (against MPC "procrastination": a warm plan that keeps deferring the
swing-up to the end of a short horizon).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fvin_mpc.control.mpc import MPC, MPCSettings, _Plan

#: The first guesses: the model under ``+f·u_max`` and ``−f·u_max`` (``f`` the settings'
#: ``initial_torque_fraction``), and ``"goal"``: the orientation slerped from the measured
#: one to the goal over the first third of the horizon, at rest, no torque (not a model
#: trajectory — IPOPT closes the gaps — but in the basin of "catch it").
GUESSES: tuple[str, ...] = ("rollout+", "rollout-", "goal")


class MultiStartMPC(MPC):
    """:class:`~fvin_mpc.control.mpc.MPC` whose cold solves try every guess in ``guesses``.

    ``info`` gains ``cold_start`` (the guess that won, on cold calls) and ``cold_costs``
    (guess → cost, ``nan`` if that solve failed); ``solve_time_s`` is the sum over guesses.
    """

    def __init__(self, model: Any, settings: MPCSettings = MPCSettings(), goal: Any = (0.0, 0.0, 1.0, 0.0),
                 torque_low: Any = (-2.0,), torque_high: Any = (2.0,), guesses: tuple[str, ...] = GUESSES,
                 restart_every: int | None = None, rest: Any = (1.0, 0.0, 0.0, 0.0)) -> None:
        unknown = [g for g in guesses if g not in GUESSES]
        if unknown or not guesses:
            raise ValueError(f"unknown guesses {unknown}; choose from {GUESSES}")
        if restart_every is not None and restart_every < 1:
            raise ValueError(f"restart_every must be >= 1 or None, got {restart_every}")
        self.guesses = tuple(guesses)
        self.restart_every = restart_every
        self._guess = self.guesses[0]
        self._calls = 0
        super().__init__(model, settings, goal, torque_low, torque_high, rest)

    def reset(self) -> None:
        super().reset()
        self._calls = 0

    def _first_guess(self, x0: np.ndarray) -> _Plan:
        n = self.horizon
        if self._guess == "goal":
            q0, goal = x0[:4], self.goal * (1.0 if float(np.dot(x0[:4], self.goal)) >= 0 else -1.0)
            angle = float(np.arccos(np.clip(np.dot(q0, goal), -1.0, 1.0)))
            weights = np.clip(np.arange(n + 1) / max(1, n // 3), 0.0, 1.0)
            if angle < 1e-9:
                quaternions = np.tile(q0, (n + 1, 1))
            else:  # slerp
                quaternions = (np.sin((1 - weights) * angle)[:, None] * q0 + np.sin(weights * angle)[:, None] * goal) \
                    / np.sin(angle)
            states = np.concatenate([quaternions, np.zeros((n + 1, 3))], axis=1)
            states[0] = x0
            return _Plan(states, np.zeros((n, self.model.control_dim)), None, None)
        sign = 1.0 if self._guess == "rollout+" else -1.0
        return self._rollout_guess(x0, sign * abs(self.settings.initial_torque_fraction) * self.torque_high)

    def __call__(self, q: Any, omega: Any) -> tuple[np.ndarray, dict[str, Any]]:
        self._calls += 1
        warm = self._previous is not None and self.settings.warm_start != "none"
        restart = self.restart_every is not None and (self._calls - 1) % self.restart_every == 0
        if warm and not restart:
            return super().__call__(q, omega)
        best: tuple[np.ndarray, dict[str, Any], Any] | None = None
        costs: dict[str, float] = {}
        total_time = 0.0
        if warm:  # the warm-started plan competes with the cold guesses
            u, info = super().__call__(q, omega)
            total_time += info["solve_time_s"]
            costs["warm"] = info["cost"] if info["success"] else float("nan")
            if info["success"]:
                best = (u, {**info, "cold_start": "warm"}, self._previous)
        for guess in self.guesses:
            self._guess, self._previous = guess, None
            u, info = super().__call__(q, omega)
            total_time += info["solve_time_s"]
            costs[guess] = info["cost"] if info["success"] else float("nan")
            if info["success"] and (best is None or info["cost"] < best[1]["cost"]):
                best = (u, {**info, "cold_start": guess}, self._previous)
        if best is None:  # every guess failed: the last call's fallback stands
            self._previous = None
            return u, {**info, "solve_time_s": total_time, "cold_start": None, "cold_costs": costs}
        u, info, self._previous = best
        return u, {**info, "solve_time_s": total_time, "cold_costs": costs}
