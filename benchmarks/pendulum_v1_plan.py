"""The learned model's DP policy for the swing-up, the MPC for the catch: ``--dp-swing-up``.

The MPC's horizon (30 steps, 1.5 s) is shorter than a swing-up from near hanging. From there its
cold call decides how to pump (which way first, how many swings) with only a local picture of
the rest of the episode, and some of those decisions cost a whole extra swing (seeds 53, 34, 93 of
``docs/pendulum-v1.md``: 40–60 each). The learned model's value function
(:mod:`benchmarks.pendulum_v1_value`: DP on the model's own map, Pendulum-v1's cost) sees the
whole episode, but as the MPC's terminal cost it made the plans end on knife edges.

This controller uses the value where it is global and the MPC where it is precise:

1. **Swing-up** (:meth:`DPSwingUpController.greedy_torque`): the value's greedy policy on the learned
   model, ``u = argmin_u c(x, u) + V(F(x, u))`` over a fine torque set, ``F`` the learned step (the
   MPC's exported ``F``), ``c`` Pendulum-v1's stage cost, ``V`` bilinear — a feedback law, recomputed
   from the measured state at every step (the model/plant mismatch is corrected as it appears).
2. **Handover**: at every swing-up step the greedy policy is rolled out on the learned model over
   ``lookahead`` steps (:meth:`DPSwingUpController.greedy_rollout`); once that rollout reaches the
   upright region (:func:`caught`) the rest of the swing-up fits in the MPC's horizon and the MPC
   takes over for the rest of the episode (its usual cold call, then warm calls). A start from which
   the greedy rollout is caught at once is the plain MPC's episode.
3. **Choice** (:class:`SimulatedChoiceController`): the greedy policy is coarse (the value's grid
   smears) and the MPC is better on most starts, so at an episode's first call each candidate — the
   plain MPC and the swing-up with each lookahead — is simulated in closed loop on the learned model
   (``simulated_steps`` steps, Pendulum-v1's cost; :func:`simulate_episode_cost`) and a swing-up
   runs the episode only if it is cheaper than the plain MPC by more than a margin (the model is not
   the plant: near-ties went either way). Candidates that act as the plain MPC from the start are
   not simulated; where all do (most starts that are not near hanging), nothing is.

Nothing here reads Pendulum-v1's own map: the controller knows the learned model, its value and
Pendulum-v1's cost (the benchmark's objective), as the MPC does.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.pendulum_v1_exact import EPISODE_STEPS, MAX_SPEED, MAX_TORQUE, v1_cost
from benchmarks.pendulum_v1_mpc import BenchmarkConfig, add_references, build_mpc, reuse_references, run_v1_episode
from benchmarks.pendulum_v1_value import interpolate, model_value_table
from fvin_mpc.envs.pendulum_v1 import v1_observation_from_state
from fvin_mpc.studies.pool import run_tasks

#: Torques the greedy policy tries per step (spacing 0.05 on [−2, 2]).
GREEDY_TORQUES = 81
#: Upright region of the handover test: |θ| (rad) and |θ̇| (rad/s).
CAUGHT_ANGLE, CAUGHT_RATE = 0.3, 1.5
#: Steps of the greedy rollout that decides the handover: the MPC's horizon (20 handed over too early
#: on the development seeds; 40 and 50 acted as 30 or as the plain MPC).
DEFAULT_LOOKAHEAD = 30


def caught(theta: np.ndarray, rate: np.ndarray) -> bool:
    """Whether a trajectory ``(θ_k, θ̇_k)`` enters the upright region (|θ| < 0.3, |θ̇| < 1.5)."""
    theta = (np.asarray(theta, float) + np.pi) % (2 * np.pi) - np.pi
    return bool(np.any((np.abs(theta) < CAUGHT_ANGLE) & (np.abs(np.asarray(rate, float)) < CAUGHT_RATE)))


def v1_angles(states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pendulum-v1's ``(θ, θ̇)`` of model states ``(…, 7)`` (θ in ``[−π, π)``, 0 upright)."""

    observed = v1_observation_from_state(np.asarray(states, float).reshape(-1, 7))
    return np.arctan2(observed[:, 1], observed[:, 0]), observed[:, 2]


class DPSwingUpController:
    """The value's greedy policy on the learned model until :func:`caught`, then ``mpc`` (module docstring).

    Args:
        mpc: the MPC that catches and balances (called as ``mpc(x) -> (u, info)``, ``mpc.reset()``).
        model: the learned model (its ``step`` CasADi function, ``x (7,), u (1,) -> x'``).
        table: the learned model's value ``(n_theta, n_rate)`` for Pendulum-v1's cost
            (:func:`~benchmarks.pendulum_v1_value.model_value_table`).
        torques: torques tried per greedy step, evenly on ``[−2, 2]``.
        lookahead: steps of the greedy rollout that decides the handover (≥ 1).
    """

    def __init__(self, mpc: Any, model: Any, table: np.ndarray, torques: int = GREEDY_TORQUES,
                 lookahead: int = DEFAULT_LOOKAHEAD) -> None:
        if torques < 2 or lookahead < 1:
            raise ValueError(f"need torques >= 2 and lookahead >= 1, got {torques} and {lookahead}")
        self.mpc, self.model, self.table, self.lookahead = mpc, model, np.asarray(table, float), lookahead
        self.torques = np.linspace(-MAX_TORQUE, MAX_TORQUE, torques)
        self._mapped_step = model.step.map(torques)
        self._mpc_active = False

    def reset(self) -> None:
        """A new episode: the swing-up phase again, the MPC's plan forgotten."""
        self.mpc.reset()
        self._mpc_active = False

    def greedy_torque(self, state: np.ndarray) -> tuple[float, np.ndarray]:
        """``argmin_u c(x, u) + V(F(x, u))`` over :attr:`torques` and the model's next state under it."""

        state = np.asarray(state, float).ravel()
        next_states = np.asarray(self._mapped_step(np.tile(state[:, None], (1, len(self.torques))),
                                                   self.torques[None, :])[0]).T
        theta, rate = v1_angles(state)
        next_theta, next_rate = v1_angles(next_states)
        totals = v1_cost(theta[0], rate[0], self.torques) + interpolate(self.table, next_theta,
                                                                        np.clip(next_rate, -MAX_SPEED, MAX_SPEED))
        best = int(np.argmin(totals))
        return float(self.torques[best]), next_states[best]

    def greedy_rollout(self, state: np.ndarray, steps: int) -> tuple[np.ndarray, np.ndarray]:
        """The greedy policy rolled out on the learned model: states ``(steps+1, 7)``, controls ``(steps,)``."""
        states, controls = [np.asarray(state, float).ravel()], []
        for _ in range(steps):
            u, next_state = self.greedy_torque(states[-1])
            controls.append(u)
            states.append(next_state)
        return np.array(states), np.array(controls)

    def hands_over_at_once(self, x: Any) -> bool:
        """Whether the greedy rollout from ``x`` is already caught: then this controller is the plain MPC."""
        return caught(*v1_angles(self.greedy_rollout(x, self.lookahead)[0]))

    def __call__(self, x: Any) -> tuple[np.ndarray, dict[str, Any]]:
        """The control for the measured model state ``x (7,)`` and an info dict (``phase``: ``"dp"`` or the MPC's)."""
        if not self._mpc_active:
            start = time.perf_counter()
            states, controls = self.greedy_rollout(x, self.lookahead)
            if not caught(*v1_angles(states)):
                return np.array([controls[0]]), {"success": True, "phase": "dp", "states": states,
                                                 "controls": controls[:, None],
                                                 "solve_time_s": time.perf_counter() - start}
            self._mpc_active = True
        u, info = self.mpc(x)
        return u, {**info, "phase": "mpc"}


def simulate_episode_cost(controller: Any, model: Any, x0: np.ndarray, steps: int) -> tuple[float, np.ndarray]:
    """``controller`` (reset first) in closed loop on the learned ``model`` from ``x0`` for ``steps`` steps:
    the summed Pendulum-v1 cost and the controls ``(steps,)``; ω clipped to ±8 after every step (the
    plant's clip, the MPC's bound)."""
    controller.reset()
    state, total, controls = np.asarray(x0, float).ravel(), 0.0, []
    for _ in range(steps):
        u, _ = controller(state)
        u = float(np.clip(np.asarray(u, float).ravel()[0], -MAX_TORQUE, MAX_TORQUE))
        theta, rate = v1_angles(state)
        total += float(v1_cost(theta[0], rate[0], u))
        controls.append(u)
        state = model(state, np.array([u]))[0]
        state[4:] = np.clip(state[4:], -MAX_SPEED, MAX_SPEED)
    controller.reset()
    return total, np.array(controls)


class SimulatedChoiceController:
    """At an episode's first call, each candidate controller's episode is simulated on the learned model
    (:func:`simulate_episode_cost`); the one with the lowest Pendulum-v1 cost runs the episode.

    Args:
        candidates: name → controller (``reset()``, ``__call__(x) -> (u, info)``); they may share an MPC
            (they are simulated one after another and reset).
        model: the learned model the episodes are simulated on.
        steps: steps simulated (Pendulum-v1's episode is 200).
        same_as: optional ``(name, x0) -> other name or None``: a candidate that would act exactly as
            another from ``x0`` is not simulated again (its cost is the other's).
        margin: the first candidate is the default; another runs only if its simulated cost is lower by
            more than ``margin`` (the simulation is on the model, not the plant: near-ties say nothing).
    """

    def __init__(self, candidates: dict[str, Any], model: Any, steps: int, same_as: Any = None,
                 margin: float = 0.0) -> None:
        if not candidates or steps < 1 or not margin >= 0.0:
            raise ValueError(f"need at least one candidate, steps >= 1 and margin >= 0, got {list(candidates)}, "
                             f"{steps} and {margin}")
        self.candidates, self.model, self.steps, self.same_as = dict(candidates), model, steps, same_as
        self.margin = float(margin)
        self.choice: str | None = None
        self.simulated_costs: dict[str, float] = {}

    def reset(self) -> None:
        self.choice = None
        for controller in self.candidates.values():
            controller.reset()

    def __call__(self, x: Any) -> tuple[np.ndarray, dict[str, Any]]:
        if self.choice is None:
            start = time.perf_counter()
            twins = {name: self.same_as(name, x) if self.same_as else None for name in self.candidates}
            twins = {name: twin for name, twin in twins.items() if twin in self.candidates and twin != name}
            distinct = [name for name in self.candidates if name not in twins]
            costs: dict[str, float] = {}
            if len(distinct) > 1:  # one distinct candidate needs no simulation
                for name in distinct:
                    costs[name] = simulate_episode_cost(self.candidates[name], self.model, x, self.steps)[0]
                costs.update({name: costs[twin] for name, twin in twins.items()})
            self.choice = distinct[0]
            if costs:
                default = next(iter(self.candidates))
                cheapest = min(costs, key=costs.get)
                self.choice = cheapest if costs[cheapest] < costs[default] - self.margin else default
            self.simulated_costs = costs
            u, info = self.candidates[self.choice](x)
            return u, {**info, "choice": self.choice, "simulated_costs": costs,
                       "choice_time_s": time.perf_counter() - start}
        return self.candidates[self.choice](x)


#: The swing-up's defaults in the benchmark: handover lookaheads and the simulated steps of the choice
#: (the swing-ups from hanging end by ~100 steps; what follows is balancing, the same for all).
DEFAULT_LOOKAHEADS: tuple[int, ...] = (DEFAULT_LOOKAHEAD,)
DEFAULT_SIMULATED_STEPS = 120
#: Simulated costs closer than this (to the plain MPC's) are ties: the plain MPC runs. On the development
#: seeds the swing-ups that helped were 20–53 cheaper in simulation; near-ties went either way on the plant.
DEFAULT_CHOICE_MARGIN = 10.0


def swing_up_controller(mpc: Any, model: Any, table: np.ndarray, lookaheads: tuple[int, ...] = DEFAULT_LOOKAHEADS,
                        simulated_steps: int = DEFAULT_SIMULATED_STEPS,
                        margin: float = DEFAULT_CHOICE_MARGIN) -> SimulatedChoiceController:
    """The plain ``mpc`` and a :class:`DPSwingUpController` per lookahead, chosen per episode by simulation."""
    if not lookaheads:
        raise ValueError("need at least one lookahead")
    candidates: dict[str, Any] = {"mpc": mpc}
    candidates.update({f"dp-swing-up-{n}": DPSwingUpController(mpc, model, table, lookahead=n) for n in lookaheads})

    def same_as(name: str, x: Any) -> str | None:
        return "mpc" if name != "mpc" and candidates[name].hands_over_at_once(x) else None

    return SimulatedChoiceController(candidates, model, simulated_steps, same_as, margin)


@dataclass(frozen=True)
class SwingUpConfig(BenchmarkConfig):
    """:class:`~benchmarks.pendulum_v1_mpc.BenchmarkConfig` with the learned-DP swing-up (module docstring)."""

    dp_lookaheads: tuple[int, ...] = DEFAULT_LOOKAHEADS
    dp_simulated_steps: int = DEFAULT_SIMULATED_STEPS
    dp_choice_margin: float = DEFAULT_CHOICE_MARGIN

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.dp_lookaheads or min(self.dp_lookaheads) < 1 or self.dp_simulated_steps < 1 \
                or not self.dp_choice_margin >= 0.0:
            raise ValueError(f"need lookaheads >= 1, simulated steps >= 1 and a margin >= 0, got {self.dp_lookaheads}, "
                             f"{self.dp_simulated_steps} and {self.dp_choice_margin}")
        if self.true_model:
            raise ValueError("the swing-up's value is the learned model's: not with true_model")


def build_swing_up_controller(config: SwingUpConfig) -> SimulatedChoiceController:
    """The benchmark's MPC (:func:`~benchmarks.pendulum_v1_mpc.build_mpc`) with the learned-DP swing-up."""

    mpc = build_mpc(config)
    table = model_value_table(mpc.model, config.value_grid, steps=EPISODE_STEPS - config.horizon, stage_cost="v1")
    return swing_up_controller(mpc, mpc.model, table, config.dp_lookaheads, config.dp_simulated_steps,
                               config.dp_choice_margin)


_WORKER: dict[str, Any] = {}


def _init_worker(config: SwingUpConfig) -> None:
    import gymnasium

    _WORKER.update(env=gymnasium.make("Pendulum-v1"), controller=build_swing_up_controller(config))


def run_seed(seed: int) -> dict[str, Any]:
    """The swing-up controller's episode on ``seed``, with its choice and the simulated costs."""

    controller = _WORKER["controller"]
    record = run_v1_episode(_WORKER["env"], controller, seed)
    return {**record, "swing_up_choice": controller.choice, "simulated_costs": dict(controller.simulated_costs)}


def run_swing_up_benchmark(
    config: SwingUpConfig,
    workers: int = 1,
    progress: bool = True,
    backend: str = "process",
    address: str | None = None,
    reference_from: dict[str, Any] | None = None,
) -> list[dict[str, Any]]:
    """:func:`~benchmarks.pendulum_v1_mpc.run_benchmark` with :func:`build_swing_up_controller`'s episodes
    (their references the same way: computed, or reused from ``reference_from``)."""

    if workers > 1 or backend != "process":
        build_swing_up_controller(config)  # compiles the MPC's library and the value into the disk cache once
    pool = {"workers": workers, "progress": progress, "backend": backend, "address": address}
    records = run_tasks(run_seed, [(config.seed + i,) for i in range(config.episodes)], _init_worker, (config,),
                        description="Pendulum-v1 (DP swing-up)", **pool)
    if config.reference:
        reused = (reference_from,) if reference_from is not None else ()
        (reuse_references if reused else add_references)(records, *reused, config.reference_grids, **pool)
    return records


def describe_swing_up(markdown: Path, config: SwingUpConfig, records: list[dict[str, Any]]) -> None:
    """Name the swing-up in the report ``markdown`` written by
    :func:`~benchmarks.pendulum_v1_mpc.write_markdown`: the controller's row and a bullet on the choice."""
    text = markdown.read_text()
    lookaheads = ", ".join(map(str, config.dp_lookaheads))
    label = "| MPC (" + config.solver + ")"
    if label not in text:
        raise ValueError(f"{markdown}: no controller row starting {label!r}")
    text = text.replace(label, f"| learned-DP swing-up (lookahead {lookaheads}) or {label[2:]}", 1)
    chosen = [r for r in records if r["swing_up_choice"] != "mpc"]
    simulated = [r for r in records if r["simulated_costs"]]
    first_call_s = np.array([r["controller_time_s"][0] for r in records])
    bullet = (f"* Swing-up (`--dp-swing-up`, `benchmarks/pendulum_v1_plan.py`): at each episode's first call the "
              f"plain MPC and the learned model's DP policy (greedy on its value, {GREEDY_TORQUES} torques) handing "
              f"over to the MPC once its {lookaheads}-step rollout on the model is caught (|θ| < {CAUGHT_ANGLE}, "
              f"|θ̇| < {CAUGHT_RATE}) are simulated in closed loop on the learned model for "
              f"{config.dp_simulated_steps} steps; the swing-up runs the episode if its Pendulum-v1 cost is lower "
              f"by more than {config.dp_choice_margin:g}, else the MPC. Simulated on "
              f"{len(simulated)} of {len(records)} starts (elsewhere the swing-up hands over at once); the swing-up "
              f"ran on {len(chosen)}" + (f" (seeds {', '.join(str(r['seed']) for r in chosen)})" if chosen else "")
              + f". The first call takes {np.median(first_call_s):.2f} s median, {first_call_s.max():.1f} s at most "
              "(the simulations; included in the controller times above).")
    marker = "\n* Reference"
    if marker not in text:
        raise ValueError(f"{markdown}: no '* Reference' bullet to put the swing-up's before")
    markdown.write_text(text.replace(marker, "\n" + bullet + marker, 1))


__all__ = [
    "DEFAULT_CHOICE_MARGIN",
    "DEFAULT_LOOKAHEADS",
    "describe_swing_up",
    "DEFAULT_SIMULATED_STEPS",
    "SwingUpConfig",
    "build_swing_up_controller",
    "run_swing_up_benchmark",
    "swing_up_controller",
    "CAUGHT_ANGLE",
    "CAUGHT_RATE",
    "DEFAULT_LOOKAHEAD",
    "DPSwingUpController",
    "GREEDY_TORQUES",
    "SimulatedChoiceController",
    "caught",
    "simulate_episode_cost",
    "v1_angles",
]
