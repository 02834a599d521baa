"""A heavier craft told its mass, its control charged in newtons or by its effect:
``python -m benchmarks.heavier_craft_weights``.

The figure-eight of the built-in ``quadrotor`` flown by ``fly``'s real-time MPC, waiting mode (the simulator waits
for the controller: this is about the optimal-control problem, not timing), on four plants and models:

* the unchanged craft with its own model;
* the craft ``--mass-scale`` (1.5) times as heavy in mass and inertia from the first period on
  (``ScenePhysics.mass_change`` at 0 s, so the figure-eight stays the unchanged craft's), its model told exactly
  that (the run-time parameters of :func:`fvin_mpc.control.adaptation.rti_parameters`), the MPC's weights as
  tuned — the payload benchmark's oracle without the switch;
* the same with the control weight divided by the mass scale, and by its square.

Each under both control costs (``MPCSettings.control_cost``): ``"command"`` charges the thrust in newtons,
``"effect"`` (the default) charges its effect, the thrust over the model's mass ratio.

The dynamics are homogeneous in mass, inertia, potential and thrust, so a craft ``b`` times as heavy flies exactly
like the unchanged one on thrusts ``b`` times as large. A cost in newtons charges those thrusts ``b²`` times as much:
only a control weight divided by ``b²`` leaves its optimum — and the closed loop — the unchanged craft's (up to the
thrust bounds, which do not scale). The effect cost does that division itself, from the model's parameters.
Prints one JSON row per case: the RMS position error from ``--settle`` s on.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from typing import Sequence

import numpy as np

from fvin_mpc.control.adaptation import nominal_estimate, rti_parameters
from fvin_mpc.control.closed_loop import run_episode
from fvin_mpc.control.flight import scaled_control_weight
from fvin_mpc.core.errors import run_command
from fvin_mpc.envs.quadrotor_env import QuadrotorEnv
from fvin_mpc.envs.scenes import resolve_scene
from fvin_mpc.studies.flight_report import figure_eight, make_controller


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.heavier_craft_weights", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", default=["closed-form", "learned"], choices=("closed-form", "learned"))
    parser.add_argument("--mass-scale", type=float, default=1.5, help="default: %(default)s")
    parser.add_argument("--duration", type=float, default=10.0, help="seconds flown (default: %(default)s)")
    parser.add_argument("--settle", type=float, default=4.0, help="the RMS error's window starts here, s "
                        "(default: %(default)s)")
    parser.add_argument("--control-costs", nargs="+", default=["command", "effect"], choices=("command", "effect"),
                        help="MPCSettings.control_cost values to fly (default: both)")
    return parser


def fly(model_name: str, scale: float, weight_power: float, control_cost: str, args: argparse.Namespace) -> float:
    """RMS position error (m) of one figure-eight: the plant and the model ``scale`` times as heavy, the control
    weight divided by ``scale ** weight_power``, the cost ``control_cost``."""
    physics = resolve_scene("quadrotor").physics
    if scale != 1.0:
        physics = replace(physics, mass_change=(0.0, scale))
    env = QuadrotorEnv("quadrotor", physics=physics)
    weight = np.asarray(scaled_control_weight(env.unwrapped.scales), dtype=float) / scale ** weight_power
    controller = make_controller(env, model_name, control_weight=weight.item() if weight.ndim == 0 else tuple(weight),
                                 control_cost=control_cost)
    controller.set_parameters(rti_parameters(controller.model, {**nominal_estimate(controller.model),
                                                                "mass": scale}))
    reference = figure_eight(env)
    controller.set_reference(reference)
    episode, _ = run_episode(env, controller, args.duration, {"hover": True}, latency="none", progress=False)
    wanted, _ = reference(episode.time)
    error = np.linalg.norm(episode.states[:, :3] - wanted[:, :3], axis=1)[episode.time >= args.settle]
    env.close()
    return float(np.sqrt(np.mean(error ** 2)))


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    for model_name in args.models:
        for control_cost in args.control_costs:
            for label, scale, power in (("unchanged", 1.0, 0.0), ("heavier, weights as tuned", args.mass_scale, 0.0),
                                        ("heavier, control weight / mass", args.mass_scale, 1.0),
                                        ("heavier, control weight / mass²", args.mass_scale, 2.0)):
                rms = fly(model_name, scale, power, control_cost, args)
                row = {"model": model_name, "control_cost": control_cost, "case": label,
                       "rms_position_mm": round(1e3 * rms, 4)}
                print(json.dumps(row, ensure_ascii=False), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
