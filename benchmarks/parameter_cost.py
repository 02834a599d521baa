"""What the model parameters as run-time inputs cost: ``python -m benchmarks.parameter_cost``.

Per scene and model, two real-time controllers that differ only in ``RTIOptions.model_parameters``: the
parameters an input of the compiled functions (the default; :mod:`fvin_mpc.core.model_parameters`) or
baked in as constants (what the generated code was before: CasADi folds the constants, a symbol costs its
operations). Both run the same states — those of one closed-loop episode of the first controller in the
waiting mode, replayed — each period one after the other in alternating order, so both see the same
machine load; the wall clock of each phase is taken per period and the figures are medians and the
ratio inputs / constants within this one run:

* ``linearize``: the library's compiled ``rti_linearize_blocks`` alone (a buffered call) — where the model is;
* ``feedback``, ``period``: the controller's library, one ``ctypes`` call per phase.

The wall-clock budgets are set so that they never bind: both variants do the same iterations. Timings move
with the machine's load; compare the ratios.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fvin_mpc._cli import run_command
from fvin_mpc.control.closed_loop import run_episode
from fvin_mpc.control.flight import quadrotor_model, quadrotor_mpc, quadrotor_mpc_settings, recovery_starts
from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings
from fvin_mpc.envs import QuadrotorEnv
from fvin_mpc.envs.scenes import resolve_scene

SCENES = ("pendulum", "spherical_pendulum", "quadrotor")
#: Budgets that never bind (s): both variants do the same iterations.
UNBOUNDED = {"cold_budget_s": 600.0, "budget_s": 600.0}
DURATION_S = {"pendulum": 6.0, "spherical_pendulum": 6.0, "quadrotor": 3.0}


def controller_pair(scene: str, true_model: bool, seed: int) -> tuple[Any, dict[str, Any], dict[str, Any], int]:
    """``(env, {variant: controller}, reset options, env seed)``; variants ``inputs`` and ``constants``."""
    pairs = {}
    if resolve_scene(scene).goal_set.attitude_at_rest:
        env = scene_env(scene, true_model=true_model)
        model = scene_model(env, true_model=true_model)
        for variant, parametric in (("inputs", True), ("constants", False)):
            settings = scene_mpc_settings(env, solver="rti").updated(rti={**UNBOUNDED, "model_parameters": parametric})
            pairs[variant] = scene_mpc(env, model, settings)
        return env, pairs, {"random": True}, seed
    env = QuadrotorEnv(resolve_scene(scene))
    model = quadrotor_model(env, true_model=true_model)
    for variant, parametric in (("inputs", True), ("constants", False)):
        settings = quadrotor_mpc_settings().updated(rti={**UNBOUNDED, "model_parameters": parametric})
        pairs[variant] = quadrotor_mpc(env, model, settings)
    options, seed = recovery_starts(env.unwrapped.goal_state[:3], count=3, seed=seed)[2]
    return env, pairs, options, seed


def timed(call: Any, *arguments: Any) -> float:
    start = time.perf_counter()
    call(*arguments)
    return time.perf_counter() - start


def measure(scene: str, true_model: bool, seed: int) -> dict[str, Any]:
    env, controllers, options, seed = controller_pair(scene, true_model, seed)
    episode, _ = run_episode(env, controllers["inputs"], DURATION_S.get(scene, 6.0), options, seed)
    states = np.asarray(episode.states, dtype=float)
    times: dict[str, dict[str, list[float]]] = {v: {"linearize": [], "feedback": [], "period": []}
                                                for v in controllers}
    for controller in controllers.values():
        controller.reset()
    for k, x in enumerate(states):
        order = list(controllers) if k % 2 == 0 else list(controllers)[::-1]
        for variant in order:
            controller, record = controllers[variant], times[variant]
            start = time.perf_counter()
            controller.feedback(x)
            feedback = time.perf_counter() - start
            controller.prepare()
            record["feedback"].append(feedback)
            record["period"].append(time.perf_counter() - start)
            plan = controller.plan  # the prepared plan, linearized once more for the timing of the call alone
            record["linearize"].append(timed(controller.linearize, plan))
    first = controllers["inputs"]
    row: dict[str, Any] = {"scene": scene, "model": first.model.name, "horizon": first.horizon,
                           "parameters": first.model.model_parameters.size, "periods": len(states)}
    for phase in times["inputs"]:
        # the first (cold) period is not a period of the loop's steady state
        inputs, constants = (1e6 * float(np.median(times[v][phase][1:])) for v in ("inputs", "constants"))
        row[phase] = {"inputs_us": inputs, "constants_us": constants, "ratio": inputs / constants}
    return row


def markdown(rows: list[dict[str, Any]]) -> str:
    phases = ("linearize", "feedback", "period")
    lines = ["| scene | model | N | parameters | " + " | ".join(f"{p} µs: inputs / constants (ratio)" for p in phases)
             + " |", "|---|---|---|---|" + "---|" * len(phases)]
    for row in rows:
        cells = [f"{row[p]['inputs_us']:.0f} / {row[p]['constants_us']:.0f} ({row[p]['ratio']:.2f}×)" for p in phases]
        lines.append(f"| {row['scene']} | {row['model']} | {row['horizon']} | {row['parameters']} | "
                     + " | ".join(cells) + " |")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.parameter_cost", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", choices=SCENES, default=["pendulum", "quadrotor"], help="scenes")
    parser.add_argument("--models", nargs="+", choices=["learned", "closed-form"], default=["learned", "closed-form"],
                        help="the checkpoint, the closed form, or both")
    parser.add_argument("--out", type=Path, default=Path("docs/bench/parameter_cost.json"), help="JSON results")
    parser.add_argument("--seed", type=int, default=0, help="the episode's random start")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from tqdm.auto import tqdm

    args = build_parser().parse_args(argv)
    cases = [(scene, model) for scene in args.scenes for model in args.models]
    rows = [measure(scene, model == "closed-form", args.seed) for scene, model in tqdm(cases, desc="scenes")]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"command": "python -m benchmarks.parameter_cost", "cpus": os.cpu_count(),
                                    "load_average": os.getloadavg(), "rows": rows}, indent=1))
    print(markdown(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
