"""The learned model's MPC on Gymnasium's own ``Pendulum-v1``: ``python -m fvin_mpc.pendulum_v1``.

The plant is the unmodified ``gymnasium.make("Pendulum-v1")``; its observation
``[cos θ, sin θ, θ̇]`` is converted to the model's ``(q, ω)`` by :mod:`envs.pendulum_v1`.
The model was trained on the MuJoCo ``pendulum`` scene, whose physics are Pendulum-v1's
(``θ̈ = 15 sin θ + 3u`` with θ = 0 upright, ``|u| ≤ 2``) integrated accurately (RK4 at 5 ms).
Pendulum-v1 itself is a *discrete* system, which the model does not know:

    θ̇' = clip(θ̇ + (15 sin θ + 3u)·0.05, −8, 8),   θ' = θ + 0.05·θ̇'    (semi-implicit Euler)

so the MPC runs with a model mismatch (discretization, and the speed clip, which the MPC
respects as a bound ``|ω| ≤ 8`` on its predictions). The MPC's cost is the benchmark's
reward: ``orientation_weight = 4`` on ``sin²(angle/2)`` (≈ angle²), ``0.1|ω|²``, ``0.001u²``.

Reference per seed (``--reference``): the whole 200-step episode optimized open loop on the
*exact* discrete dynamics above (direct multiple shooting, IPOPT, the speed clip as a bound
on ``θ̇``, several initial guesses incl. the MPC's own episode), replayed through the same
update (or the optimized trajectory's own cost: open-loop replay near upright amplifies rounding
exponentially). The episode is deterministic given the seed, so this is the best
return an omniscient controller found — an (approximate, local-optimum) upper bound for any
policy on that seed; the gap to it is what the MPC leaves on the table.

Outputs ``--out`` (Markdown), ``<out>.json`` and ``<out>.png`` (returns per seed).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from fvin_mpc.envs.scenes import resolve_scene
from fvin_mpc.control.mpc import MPCSettings

#: Pendulum-v1's constants (gymnasium.envs.classic_control.pendulum, g = 10 as ``make`` uses).
DT, MAX_SPEED, MAX_TORQUE, GRAVITY, MASS, LENGTH = 0.05, 8.0, 2.0, 10.0, 1.0, 1.0
EPISODE_STEPS = 200
#: rl-baselines3-zoo's best Pendulum-v1 entry (benchmark.md): TQC, mean ± std over 750 episodes.
ZOO_BEST = {"algorithm": "TQC", "mean": -151.3, "std": 87.9, "episodes": 750}


def benchmark_settings(horizon: int = 30, terminal_energy_weight: float | None = None,
                       multistart: bool = True) -> MPCSettings:
    """MPC settings whose stage cost is Pendulum-v1's: ``4 sin²(a/2) ≈ a²``, ``0.1ω²``, ``0.001u²``.

    The predicted ``|ω|`` is bounded by Pendulum-v1's speed clip (8 rad/s = 0.4/h). The terminal
    energy-deficit weight is the scenes' default
    (:data:`fvin_mpc.control.scene.DEFAULT_TERMINAL_ENERGY_WEIGHT`) unless given; cold solves try
    every first guess unless ``multistart=False`` (a single constant-torque guess lets a pendulum
    that starts near upright fall through a full turn: cost ≈ 128 instead of ≈ 0.4).
    """
    from fvin_mpc.control.mpc import COLD_STARTS
    from fvin_mpc.control.scene import DEFAULT_TERMINAL_ENERGY_WEIGHT

    energy_weight = DEFAULT_TERMINAL_ENERGY_WEIGHT if terminal_energy_weight is None else terminal_energy_weight
    return replace(MPCSettings(), horizon=horizon, orientation_weight=4.0, omega_weight=0.1, control_weight=0.001,
                   omega_bound_fraction=MAX_SPEED * DT, terminal_energy_weight=energy_weight,
                   cold_starts=COLD_STARTS if multistart else COLD_STARTS[:1])


# ---------------------------------------------------------------------- exact dynamics
def angle_normalize(theta: Any) -> Any:
    """Pendulum-v1's ``((θ + π) mod 2π) − π``."""
    return ((theta + np.pi) % (2 * np.pi)) - np.pi


def v1_step(theta: float, theta_dot: float, u: float) -> tuple[float, float, float]:
    """Pendulum-v1's update and reward, exactly as ``PendulumEnv.step``: ``(θ', θ̇', reward)``."""
    u = float(np.clip(u, -MAX_TORQUE, MAX_TORQUE))
    cost = angle_normalize(theta) ** 2 + 0.1 * theta_dot**2 + 0.001 * u**2
    new_theta_dot = theta_dot + (3 * GRAVITY / (2 * LENGTH) * np.sin(theta) + 3.0 / (MASS * LENGTH**2) * u) * DT
    new_theta_dot = float(np.clip(new_theta_dot, -MAX_SPEED, MAX_SPEED))
    return theta + new_theta_dot * DT, new_theta_dot, -float(cost)


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
    step; bounds ``|u| ≤ 2``, ``|θ̇_k| ≤ 8`` for ``k ≥ 1`` (the speed clip: trajectories that
    never hit it are exactly Pendulum-v1's), ``(θ_0, θ̇_0)`` fixed.
    """

    def __init__(self, steps: int = EPISODE_STEPS, max_iter: int = 500) -> None:
        import casadi as ca

        self.steps = steps
        theta, rate, u = ca.SX.sym("theta", steps + 1), ca.SX.sym("rate", steps + 1), ca.SX.sym("u", steps)
        wrapped = theta[:steps] - 2 * np.pi * ca.floor((theta[:steps] + np.pi) / (2 * np.pi))
        objective = ca.sumsqr(wrapped) + 0.1 * ca.sumsqr(rate[:steps]) + 0.001 * ca.sumsqr(u)
        next_rate = rate[:steps] + (3 * GRAVITY / (2 * LENGTH) * ca.sin(theta[:steps]) + 3.0 / (MASS * LENGTH**2) * u) * DT
        defects = ca.vertcat(rate[1:] - next_rate, theta[1:] - (theta[:steps] + rate[1:] * DT))
        self._solver = ca.nlpsol("episode", "ipopt", {"x": ca.vertcat(theta, rate, u), "f": objective, "g": defects},
                                 {"ipopt": {"print_level": 0, "sb": "yes", "max_iter": max_iter, "tol": 1e-8},
                                  "print_time": False, "error_on_fail": False})

    def solve(self, theta0: float, theta_dot0: float,
              controls_guess: np.ndarray) -> tuple[float, np.ndarray, str, float]:
        """Optimize from a control guess (states by replaying it).

        Returns ``(return, controls, status, max_defect)``: the return is minus the NLP's objective,
        i.e. the cost of the optimized trajectory, whose every step satisfies the exact update to
        ``max_defect``. (Replaying the controls open loop is no check: over 10 s the upright
        equilibrium amplifies a 1e-9 difference by ``e^(√15·10) ≈ 1e17``.)
        """
        n = self.steps
        controls_guess = np.clip(np.asarray(controls_guess, float).ravel(), -MAX_TORQUE, MAX_TORQUE)
        _, states = replay(theta0, theta_dot0, controls_guess)
        lower = np.r_[np.full(n + 1, -np.inf), np.full(n + 1, -MAX_SPEED), np.full(n, -MAX_TORQUE)]
        upper = -lower
        lower[0] = upper[0] = theta0
        lower[n + 1] = upper[n + 1] = theta_dot0
        solution = self._solver(x0=np.r_[states[:, 0], states[:, 1], controls_guess], lbx=lower, ubx=upper,
                                lbg=0.0, ubg=0.0)
        x = np.asarray(solution["x"]).ravel()
        controls = np.clip(x[2 * (n + 1):], -MAX_TORQUE, MAX_TORQUE)
        defect = float(np.abs(np.asarray(solution["g"])).max())
        return -float(solution["f"]), controls, str(self._solver.stats()["return_status"]), defect


def reference_return(theta0: float, theta_dot0: float, guesses: list[np.ndarray],
                     optimizer: EpisodeOptimizer | None = None, max_defect: float = 1e-6) -> dict[str, Any]:
    """Best return over the guesses (replayed exactly) and their optimized trajectories (IPOPT
    converged, dynamics satisfied to ``max_defect``)."""
    optimizer = optimizer or EpisodeOptimizer()
    best: dict[str, Any] = {"return": -np.inf}
    for i, guess in enumerate(guesses):
        guess_return, _ = replay(theta0, theta_dot0, guess)
        candidates = [(guess_return, f"guess {i} as is", np.asarray(guess))]
        total, controls, status, defect = optimizer.solve(theta0, theta_dot0, guess)
        if status in ("Solve_Succeeded", "Solved_To_Acceptable_Level") and defect <= max_defect:
            candidates.append((total, f"optimized guess {i}", controls))
        for value, source, plan in candidates:
            if value > best["return"]:
                best = {"return": float(value), "source": source, "controls": plan.tolist()}
    return best


# ---------------------------------------------------------------------- the MPC on Pendulum-v1
@dataclass(frozen=True)
class BenchmarkConfig:
    """One run: ``checkpoint`` (``None`` with ``true_model``), MPC ``horizon``, episodes, seed, reference."""

    checkpoint: str = resolve_scene("pendulum").default_checkpoint  # Pendulum-v1's physics is the pendulum scene's
    true_model: bool = False
    horizon: int = 30
    episodes: int = 100
    seed: int = 0
    reference: bool = True
    newton_iters: int | None = None
    multistart: bool = True
    terminal_energy_weight: float | None = None
    solver: str = "ipopt"
    rti_cold_solver: str = "rti"

    def __post_init__(self) -> None:
        if self.episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {self.episodes}")
        if self.horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {self.horizon}")


def build_mpc(config: BenchmarkConfig) -> Any:
    """The MPC on the learned model (or the closed-form pendulum) with :func:`benchmark_settings`, on
    the ``pendulum`` scene's task (Pendulum-v1's physics; its goal, rest and torque bounds)."""
    from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc

    env = scene_env("pendulum", config.checkpoint, config.true_model)
    model = scene_model(env, config.checkpoint, config.true_model, config.newton_iters)
    if abs(model.step_size - DT) > 1e-12:
        raise ValueError(f"{config.checkpoint}: needs h = {DT} s, got h = {model.step_size}")
    settings = benchmark_settings(config.horizon, config.terminal_energy_weight, config.multistart)
    return scene_mpc(env, model, replace(settings, solver=config.solver, rti_cold_solver=config.rti_cold_solver))


def run_v1_episode(env: Any, controller: Any, seed: int) -> dict[str, Any]:
    """One 200-step episode of ``controller`` on ``env`` (Pendulum-v1) reset with ``seed``."""
    from fvin_mpc.envs.pendulum_v1 import state_from_v1_observation

    observation, _ = env.reset(seed=seed)
    controller.reset()
    theta0, theta_dot0 = (float(x) for x in env.unwrapped.state)
    total, controls, wall, failures = 0.0, [], [], 0
    for _ in range(EPISODE_STEPS):
        start = time.perf_counter()
        u, info = controller(state_from_v1_observation(observation))
        wall.append(time.perf_counter() - start)
        failures += not info.get("success", True)
        observation, reward, terminated, truncated, _ = env.step(np.asarray(u, dtype=np.float32))
        total += float(reward)
        controls.append(float(np.clip(u[0], -MAX_TORQUE, MAX_TORQUE)))
        if terminated or truncated:
            break
    final = angle_normalize(float(env.unwrapped.state[0]))
    return {"seed": seed, "theta0": theta0, "theta_dot0": theta_dot0, "return": total, "controls": controls,
            "final_angle": float(final), "upright_at_end": bool(abs(final) < 0.1),
            "failures": int(failures), "controller_time_s": wall}


_WORKER: dict[str, Any] = {}


def _init_worker(config: BenchmarkConfig) -> None:
    import gymnasium

    _WORKER.update(config=config, env=gymnasium.make("Pendulum-v1"), controller=build_mpc(config),
                   optimizer=EpisodeOptimizer() if config.reference else None)


def run_seed(seed: int) -> dict[str, Any]:
    """MPC episode on ``seed`` and (if configured) the per-seed reference."""
    record = run_v1_episode(_WORKER["env"], _WORKER["controller"], seed)
    if _WORKER["config"].reference:
        theta0, theta_dot0 = record["theta0"], record["theta_dot0"]
        guesses = [np.array(record["controls"]), heuristic_controls(theta0, theta_dot0, 1.0),
                   heuristic_controls(theta0, theta_dot0, -1.0)]
        reference = reference_return(theta0, theta_dot0, guesses, _WORKER["optimizer"])
        record["reference_return"] = reference["return"]
        record["reference_source"] = reference["source"]
    return record


def run_benchmark(config: BenchmarkConfig, workers: int = 1, progress: bool = True, backend: str = "process",
                  address: str | None = None) -> list[dict[str, Any]]:
    """Episodes ``seed … seed + episodes − 1``; ``workers > 1`` uses a process pool, ``backend="ray"``
    Ray actors (``address``: the cluster; :func:`fvin_mpc.studies.pool.run_tasks`)."""
    from fvin_mpc.studies.pool import run_tasks

    if workers > 1 or backend != "process":
        build_mpc(config)  # compiles the MPC's library into the disk cache once, before the workers load it
    seeds = [(config.seed + i,) for i in range(config.episodes)]
    return run_tasks(run_seed, seeds, _init_worker, (config,), workers, progress, "Pendulum-v1",
                     backend=backend, address=address)


def summarize(records: list[dict[str, Any]]) -> dict[str, Any]:
    returns = np.array([r["return"] for r in records])
    calls_ms = 1e3 * np.concatenate([r["controller_time_s"] for r in records])
    summary = {
        "episodes": len(records), "return_mean": float(returns.mean()), "return_std": float(returns.std()),
        "return_median": float(np.median(returns)), "return_min": float(returns.min()),
        "upright_at_end": int(sum(r["upright_at_end"] for r in records)),
        "failed_solves": int(sum(r["failures"] for r in records)),
        "controller_time_median_ms": float(np.median(calls_ms)), "controller_time_p95_ms": float(np.percentile(calls_ms, 95)),
    }
    if all("reference_return" in r for r in records):
        reference = np.array([r["reference_return"] for r in records])
        gap = reference - returns
        summary.update(reference_mean=float(reference.mean()), reference_std=float(reference.std()),
                       gap_mean=float(gap.mean()), gap_median=float(np.median(gap)), gap_max=float(gap.max()),
                       gap_p90=float(np.percentile(gap, 90)), mpc_beats_reference=int((gap < -1e-3).sum()))
    return summary


def plot_returns(records: list[dict[str, Any]], path: Path, label: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seeds = np.array([r["seed"] for r in records])
    figure, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    axes[0].plot(seeds, [r["return"] for r in records], "o", ms=3, label=label)
    if all("reference_return" in r for r in records):
        axes[0].plot(seeds, [r["reference_return"] for r in records], "x", ms=4, label="optimized episode (reference)")
        axes[1].hist([r["reference_return"] - r["return"] for r in records], bins=30)
        axes[1].set_xlabel("reference return − MPC return")
        axes[1].set_ylabel("episodes")
        axes[1].set_title("gap per seed")
    axes[0].axhline(ZOO_BEST["mean"], color="tab:red", ls="--", label=f"zoo {ZOO_BEST['algorithm']} mean")
    axes[0].set_xlabel("seed")
    axes[0].set_ylabel("episode return")
    axes[0].legend(loc="lower left", fontsize=8)
    axes[0].grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def write_markdown(summary: dict[str, Any], records: list[dict[str, Any]], config: BenchmarkConfig, command: str,
                   path: Path) -> None:
    """``path`` (``.md``) and its ``.json`` twin through the one report writer."""
    from fvin_mpc.studies.report import write_report

    model = "closed-form pendulum (true model)" if config.true_model else f"learned `{config.checkpoint}`"
    lines = [
             "| controller | episodes | mean return ± std | median | worst | upright at end | failed solves "
             "| controller ms median / p95 |", "|---|---|---|---|---|---|---|---|",
             f"| MPC ({config.solver}) on {model}, N = {config.horizon}{', multi-start' if config.multistart else ''} | {summary['episodes']} | {summary['return_mean']:.1f} ± "
             f"{summary['return_std']:.1f} | {summary['return_median']:.1f} | {summary['return_min']:.1f} "
             f"| {summary['upright_at_end']}/{summary['episodes']} | {summary['failed_solves']} "
             f"| {summary['controller_time_median_ms']:.1f} / {summary['controller_time_p95_ms']:.1f} |"]
    if "reference_mean" in summary:
        lines.append(f"| optimized episode on the exact dynamics (reference) | {summary['episodes']} | "
                     f"{summary['reference_mean']:.1f} ± {summary['reference_std']:.1f} | | | | | |")
    lines.append(f"| rl-baselines3-zoo best ({ZOO_BEST['algorithm']}) | {ZOO_BEST['episodes']} | {ZOO_BEST['mean']} ± "
                 f"{ZOO_BEST['std']} | | | | | |")
    if "reference_mean" in summary:
        lines += ["", f"Gap to the reference (reference − MPC, per seed): mean {summary['gap_mean']:.2f}, median "
                  f"{summary['gap_median']:.2f}, p90 {summary['gap_p90']:.2f}, max {summary['gap_max']:.2f}; the MPC "
                  f"beats the reference on {summary['mpc_beats_reference']} seeds."]
    lines += ["", f"![returns per seed]({path.with_suffix('.png').name})", "", "## How this was measured", "",
              "* Plant: the unmodified `gymnasium.make(\"Pendulum-v1\")` (g = 10), episodes of 200 steps, "
              f"`env.reset(seed=i)` for i = {config.seed} … {config.seed + config.episodes - 1}; the return is the sum "
              "of the env's rewards.",
              "* Model: " + ("the closed-form rod (the continuous-time physics, no learning)." if config.true_model else
                             f"`{config.checkpoint}`, trained on the MuJoCo `pendulum` scene, whose physics are "
                             "Pendulum-v1's (θ̈ = 15 sin θ + 3u with θ = 0 upright, |u| ≤ 2) integrated accurately "
                             "(RK4 at 5 ms). It never saw Pendulum-v1."),
              "* Model mismatch: Pendulum-v1 is a *discrete* system — semi-implicit Euler at dt = 0.05 and θ̇ "
              "clipped to ±8 rad/s after every step — while the model predicts the continuous motion. The MPC "
              "bounds its predicted |ω| by 8 rad/s.",
              "* MPC cost = the benchmark's reward: 4 sin²(angle/2) (≈ angle²) + 0.1 ω² + 0.001 u² per stage "
              f"(`benchmark_settings`), terminal weights 40 and 1, terminal energy-deficit weight "
              f"{benchmark_settings(config.horizon, config.terminal_energy_weight).terminal_energy_weight:g}, "
              f"horizon {config.horizon} "
              f"({config.horizon * DT:.2f} s)" + (", cold solves from several first guesses "
                                                    "(`MPCSettings.cold_starts`)." if config.multistart else "."),
              "* Reference: the whole episode optimized open loop on the exact discrete dynamics (direct multiple "
              "shooting, IPOPT, the speed clip as the bound |θ̇| ≤ 8), started from the MPC's own controls and two "
              "energy-pumping guesses (closed-loop heuristics on the exact dynamics); the best of the guesses' "
              "exact returns and the optimized trajectories' costs (every step of those satisfies the exact update "
              "to 1e-6; an open-loop replay of 10 s near the unstable upright equilibrium is no check, it amplifies "
              "rounding by ~e^39). It is a local optimum, so an *approximate* upper bound (the MPC beating it on a seed would "
              "show that), and trajectories that would hit the clip are excluded from it.",
              "* rl-baselines3-zoo: its benchmark table (`benchmark.md`) over 750 evaluation episodes with its "
              "own seeds; not the same episodes as here.", "", "## Per seed", "",
              "| seed | θ₀ | θ̇₀ | MPC return | reference | gap |", "|---|---|---|---|---|---|"]
    for r in records:
        ref = r.get("reference_return")
        lines.append(f"| {r['seed']} | {r['theta0']:+.2f} | {r['theta_dot0']:+.2f} | {r['return']:.1f} | "
                     + (f"{ref:.1f} | {ref - r['return']:.2f} |" if ref is not None else "— | — |"))
    slim = [{k: v for k, v in r.items() if k not in ("controls", "controller_time_s")} for r in records]
    write_report(path.with_suffix(""), f"Pendulum-v1 with the MPC on the {model}",
                 {"config": config.__dict__, "summary": summary, "zoo_best": ZOO_BEST, "episodes": slim},
                 "\n".join(lines), command)
