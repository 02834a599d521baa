"""The pendulum's bob doubles while held upright: ``python -m benchmarks.adaptation_scenarios``.

A change of the plant with an oracle (docs/adaptation.md), on the ``pendulum`` scene: the real-time MPC (the
scene's RTI presets) holds the pendulum upright from a seeded start near it (angle within ±0.05 rad, rate within
±0.2 rad/s); at ``--change-at`` (2 s) every mass and inertia of the plant doubles (``ScenePhysics.mass_change``)
and, at the same instant, the rod's rate jumps by ``--knock`` rad/s (``impulse_delta_omega`` at ``impulse_at_s``;
sign drawn per seed). The knock is there because a uniform body held still at upright reveals no mass change at
all: gravity's torque and the inertia double together, the torque that holds it is zero either way, and the only
effect — the motor is half as strong relative to the body — shows only when the body moves. Without it the scenario
measures nothing (docs/adaptation.md: the unknocked hold changes by 1e-5 rad). The default knock (0.3 rad/s) is one
the doubled bob can be caught from; at 1 rad/s it falls in every arm, the oracle's included, and "recovery" is a
new swing-up (docs/adaptation.md reports both).

Four arms per model (``--models``: the closed form read off the unchanged MJCF, and the shipped learned
checkpoint), ``--runs`` seeded runs each:

* ``none`` — neither the input-disturbance estimate (``disturbance_gain = 0``) nor adaptation;
* ``estimate`` — the disturbance estimate only (the presets' gain);
* ``adaptation`` — :class:`fvin_mpc.control.adaptation.AdaptiveRTI` only (mass fitted from a 40-transition
  window, one Levenberg–Marquardt step per period, pushed as ``gain_scale = 1/mass``);
* ``both`` — the two together;
* ``oracle`` — the disturbance estimate and the model switched to the true changed mass at the change (told
  when and what: the closed form with the changed parameters, the issue's oracle) — the recovery a
  controller that knew could reach, the physics' own share of it (a body twice as heavy knocked by the same
  rate has half the motor's authority to come back with).

The oracle ("unchanged"): the same seeds and the same knock on the plant whose mass does not change, under
the ``estimate`` arm (the shipped controller). Figures per run: hold error before the change (RMS angle from
upright over the second before it), after it (RMS over the last ``--tail`` seconds), the recovery time (from
the change until the angle stays within ``max(1.2 × the unchanged run's largest angle over the same tail,
0.01 rad)`` for the rest of the episode; ∞ if it never does), the estimated mass ``--change-at + 2 s``
(the true value: 2, relative to the model's body) and the deadline misses. Latency: ``--latency measured``
(default; the controller's measured compute delays its torque) or ``none`` (waiting mode).

Each finished (model, arm, plant) is cached as JSON under ``--cache-dir`` (keyed by every option that changes
it) so that a stopped run resumes; ``--out-dir`` gets ``adaptation-scenarios.{md,json}``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import shlex
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from fvin_mpc.control.adaptation import AdaptiveRTI, nominal_estimate, rti_parameters
from fvin_mpc.control.closed_loop import run_episode, time_inside_for_good
from fvin_mpc.control.model_export import CompileCount, cache_dir
from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings
from fvin_mpc.core.errors import run_command
from fvin_mpc.envs.scenes import SCENES
from fvin_mpc.studies.report import markdown_table, write_report

SCENE = "pendulum"
ARMS = ("none", "estimate", "adaptation", "both", "oracle")
MODELS = ("closed-form", "learned")
#: The recovery threshold never goes below this (rad): a hold within 0.6° is held.
RECOVERY_FLOOR = 0.01
#: Part of every cache key: raise it when what a cell computes changes (the cache cannot see code changes).
#: 3: the disturbance estimate's default gain 0.1 (was 0.5).
CACHE_VERSION = 3
#: The true mass after the change, relative to the model's body.
TRUE_MASS = 2.0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.adaptation_scenarios", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    parser.add_argument("--arms", nargs="+", default=list(ARMS), choices=ARMS)
    parser.add_argument("--runs", type=int, default=20, help="seeded runs per arm (default: %(default)s)")
    parser.add_argument("--duration", type=float, default=6.0, help="episode length, s (default: %(default)s)")
    parser.add_argument("--change-at", type=float, default=2.0, help="when the bob doubles, s (default: %(default)s)")
    parser.add_argument("--knock", type=float, default=0.3,
                        help="rate jump at the change, rad/s (default: %(default)s)")
    parser.add_argument("--tail", type=float, default=1.0, help="the after-change hold error's window, s, at the "
                        "episode's end (default: %(default)s)")
    add_loop_options(parser)
    parser.add_argument("--cache-dir", default=str(cache_dir() / "adaptation-scenarios"), help="default: %(default)s")
    parser.add_argument("--out-dir", default="docs/adaptation", help="default: %(default)s")
    return parser


def add_loop_options(parser: argparse.ArgumentParser) -> None:
    """The options of an adapting closed loop that this benchmark and the payload benchmark share."""
    parser.add_argument("--window", type=int, default=40, help="the adaptation's window (default: %(default)s)")
    parser.add_argument("--latency", default="measured", choices=("measured", "none"), help="default: %(default)s")
    parser.add_argument("--control-cost", default="effect", choices=("effect", "command"),
                        help="MPCSettings.control_cost: what the control weight charges once the model's parameters "
                             "move (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="run i uses seed SEED + i (default: %(default)s)")


#: The arms whose model parameters move during a flight: only there does ``--control-cost`` change the controller
#: (with the exported model's own parameters both costs are the same problem), so only their cells carry it in the
#: cache key — the cells cached before the option existed were flown with ``"command"``.
PARAMETER_ARMS = ("adaptation", "both", "oracle")


def cost_key(args: argparse.Namespace, arm: str) -> list[str]:
    """The control cost's part of a cell's cache key: empty where the cost cannot matter or is the old one."""
    return [args.control_cost] if arm in PARAMETER_ARMS and args.control_cost != "command" else []


class OracleSwitch:
    """The wrapped real-time MPC's model switched to the true ``changed`` estimate (e.g. ``{"mass": 2}``; the
    rest nominal) from ``change_at`` on (told by ``set_time``)."""

    def __init__(self, controller: Any, change_at: float, changed: dict[str, float]) -> None:
        self.controller, self.change_at = controller, change_at
        model = controller.model
        self._nominal = rti_parameters(model, nominal_estimate(model))
        self._changed = rti_parameters(model, {**nominal_estimate(model), **changed})

    def reset(self) -> None:
        self.controller.reset()
        self.controller.set_parameters(self._nominal)

    def set_time(self, time_s: float) -> None:
        if time_s >= self.change_at - 1e-9:
            self.controller.set_parameters(self._changed)
        self.controller.set_time(time_s)  # the reference's clock, and a skipped period's forgotten prediction

    def __call__(self, x: Any) -> Any:
        return self.controller(x)

    def prepare(self) -> None:
        self.controller.prepare()

    def __getattr__(self, name: str) -> Any:
        if name == "controller":
            raise AttributeError(name)
        return getattr(self.controller, name)


def start(seed: int) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    return {"qpos": [math.pi + rng.uniform(-0.05, 0.05)], "qvel": [rng.uniform(-0.2, 0.2)]}


def run_cell(args: argparse.Namespace, model_name: str, arm: str, changed: bool) -> list[dict[str, Any]]:
    """``--runs`` episodes of one (model, arm, plant); cached."""
    from tqdm.auto import tqdm

    key = json.dumps([CACHE_VERSION, model_name, arm, changed, args.runs, args.duration, args.change_at, args.knock,
                      args.window, args.latency, args.seed] + cost_key(args, arm))
    path = Path(args.cache_dir) / f"{hashlib.sha256(key.encode()).hexdigest()[:16]}.json"
    if path.is_file():
        return json.loads(path.read_text())["runs"]
    physics = replace(SCENES[SCENE].physics, impulse_delta_omega=args.knock, impulse_at_s=args.change_at,
                      mass_change=(args.change_at, TRUE_MASS if changed else 1.0))
    true_model = model_name == "closed-form"
    env = scene_env(SCENE, true_model=true_model, physics=physics)
    model = scene_model(env, true_model=true_model)
    overrides = {} if arm in ("estimate", "both", "oracle") else {"disturbance_gain": 0.0}
    rti = scene_mpc(env, model, scene_mpc_settings(env, solver="rti", control_cost=args.control_cost, **overrides))
    controller = AdaptiveRTI(rti, window=args.window) if arm in ("adaptation", "both") else rti
    if arm == "oracle":
        controller = OracleSwitch(rti, args.change_at, {"mass": TRUE_MASS})
    runs = []
    for i in tqdm(range(args.runs), desc=f"{model_name} {arm} {'changed' if changed else 'unchanged'}", leave=False):
        compiles = CompileCount.calls
        episode, _ = run_episode(env, controller, args.duration, reset_options=start(args.seed + i),
                                 seed=args.seed + i, latency=args.latency)
        t, angle = episode.time, np.abs(episode.angle_from_goal)
        run = {"seed": args.seed + i, "time": t.tolist(), "angle": angle.tolist(),
               "deadline_misses": int(episode.deadline_misses), "compile_calls": CompileCount.calls - compiles,
               "busy_ms_max": float(np.nanmax(episode.busy_s) * 1e3) if args.latency == "measured" else None}
        if isinstance(controller, AdaptiveRTI):
            history = [(entry[0], entry[1]["mass"], entry[2]) for entry in controller.history]
            run["mass"] = [[h[0], h[1]] for h in history]
            run["update_ms_median"] = float(np.median([h[2] for h in history]) * 1e3)
        runs.append(run)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"key": key, "runs": runs}))
    return runs


def rms(t: np.ndarray, angle: np.ndarray, low: float, high: float) -> float:
    window = (t >= low - 1e-9) & (t < high - 1e-9)
    return float(np.sqrt(np.mean(angle[window] ** 2)))


def recovery_time(t: np.ndarray, angle: np.ndarray, change_at: float, threshold: float) -> float:
    """From the change until the angle stays within ``threshold``; ∞ if it is outside at the end."""
    outside = (t >= change_at - 1e-9) & (angle > threshold)
    if not outside.any():
        return 0.0
    inside_from = time_inside_for_good(t, outside)
    return math.inf if inside_from is None else inside_from - change_at


def mass_at(run: dict[str, Any], time_s: float) -> float | None:
    if "mass" not in run:
        return None
    times = np.array([entry[0] for entry in run["mass"]])
    masses = np.array([entry[1] for entry in run["mass"]])
    return float(masses[np.searchsorted(times, time_s - 1e-9)]) if times[-1] >= time_s - 1e-9 else None


def summarize(args: argparse.Namespace, model_name: str, arm: str, runs: list[dict[str, Any]],
              unchanged: list[dict[str, Any]]) -> dict[str, Any]:
    before, after, recovery, masses, misses, references, own, final = [], [], [], [], 0, [], [], []
    end = args.duration
    for run, reference in zip(runs, unchanged):
        t, angle = np.array(run["time"]), np.array(run["angle"])
        t_ref, angle_ref = np.array(reference["time"]), np.array(reference["angle"])
        tail = (t_ref >= end - args.tail - 1e-9)
        threshold = max(1.2 * float(angle_ref[tail].max()), RECOVERY_FLOOR)
        before.append(rms(t, angle, args.change_at - 1.0, args.change_at))
        after.append(rms(t, angle, end - args.tail, end + 1.0))
        references.append(rms(t_ref, angle_ref, end - args.tail, end + 1.0))
        recovery.append(recovery_time(t, angle, args.change_at, threshold))
        own.append(recovery_time(t_ref, angle_ref, args.change_at, threshold))
        mass = mass_at(run, args.change_at + 2.0)
        if mass is not None:
            masses.append(mass)
            final.append(run["mass"][-1][1])
        misses += run["deadline_misses"]
    recovery, extra = np.array(recovery), np.array(recovery) - np.array(own)
    row = {
        "model": model_name, "arm": arm, "runs": len(runs),
        "hold error before, rad (median)": float(np.median(before)),
        "hold error after, rad (median)": float(np.median(after)),
        "(worst)": float(np.max(after)),
        "unchanged, rad (median)": float(np.median(references)),
        "recovery s (median)": float(np.median(recovery)),
        "recovery s (worst)": float(np.max(recovery)),
        "recovered within 2 s": f"{int(np.sum(recovery <= 2.0))}/{len(runs)}",
        "unchanged recovery s (median)": float(np.median(own)),
        "later than unchanged, s (median)": float(np.median(extra)),
        "(worst) ": float(np.max(extra)),
        "deadline misses": misses if args.latency == "measured" else "n/a (waiting)",
        "compile calls": int(sum(run["compile_calls"] for run in runs)),
    }
    if masses:
        error = np.abs(np.array(masses) / TRUE_MASS - 1.0)
        row["mass at +2 s (median)"] = float(np.median(masses))
        row["|mass error| (worst)"] = float(error.max())
        row["mass within 5 %"] = f"{int(np.sum(error <= 0.05))}/{len(masses)}"
        row["mass at the end (median)"] = float(np.median(final))
        row["within 5 % at the end"] = f"{int(np.sum(np.abs(np.array(final) / TRUE_MASS - 1.0) <= 0.05))}/{len(final)}"
        row["LM update ms (median)"] = float(np.median([run["update_ms_median"] for run in runs]))
    return row


def run_arms(args: argparse.Namespace, run_cell: Callable[..., list[dict[str, Any]]],
             summarize: Callable[..., dict[str, Any]]) -> list[dict[str, Any]]:
    """Per model: the unchanged plant under the ``estimate`` arm (every arm's reference), then each arm on the
    changed plant, one summary row each (``run_cell(args, model, arm, changed)``, ``summarize(args, model, arm,
    runs, unchanged)``)."""
    rows = []
    for model_name in args.models:
        unchanged = run_cell(args, model_name, "estimate", changed=False)
        rows.append(summarize(args, model_name, "unchanged plant (estimate)", unchanged, unchanged))
        for arm in args.arms:
            rows.append(summarize(args, model_name, arm, run_cell(args, model_name, arm, changed=True), unchanged))
            print(f"{model_name} {arm}: {rows[-1]}", file=sys.stderr)
    return rows


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    return run_arms(args, run_cell, summarize)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.runs < 1 or args.duration <= args.change_at + 2.0 or args.tail <= 0.0:
        raise ValueError("need --runs >= 1, --duration past --change-at + 2 s and --tail > 0")
    rows = run(args)
    command = "python -m benchmarks.adaptation_scenarios " + " ".join(
        shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    columns = ["model", "arm", "runs", "hold error before, rad (median)", "hold error after, rad (median)", "(worst)",
               "unchanged, rad (median)", "recovery s (median)", "recovery s (worst)", "recovered within 2 s",
               "unchanged recovery s (median)", "later than unchanged, s (median)", "(worst) ",
               "mass at +2 s (median)", "|mass error| (worst)", "mass within 5 %", "mass at the end (median)",
               "within 5 % at the end", "LM update ms (median)",
               "deadline misses", "compile calls"]
    mode = ("measured latency (the controller's compute delays its torque; the shared, loaded machine)"
            if args.latency == "measured" else "waiting mode (the simulator waits for the controller)")
    body = "\n".join([
        f"The `{SCENE}` scene held upright by the real-time MPC; at {args.change_at:g} s every mass and inertia "
        f"doubles and the rate jumps by {args.knock:g} rad/s; {args.runs} seeded runs of {args.duration:g} s per "
        f"arm; {mode}; the MPC's control cost: {args.control_cost} (`MPCSettings.control_cost`). "
        f"\"unchanged\": the same seeds and knock on the plant whose mass stays (the `estimate` arm), "
        f"the oracle the recovery is measured against (threshold max(1.2 × its largest angle over the last "
        f"{args.tail:g} s, {RECOVERY_FLOOR} rad)). Hold errors are RMS angles from upright: before = the second "
        f"before the change, after = the last {args.tail:g} s. Recovery is timed from the change; the unchanged "
        f"plant's own recovery from the same knock beside it, and how much later the changed plant's is (same "
        f"seed). Mass: the adaptation's estimate 2 s after the "
        f"change (true: {TRUE_MASS:g}). Compile calls: code generation or compiler runs during the episodes.",
        "",
        markdown_table(rows, columns),
        "",
    ])
    write_report(Path(args.out_dir) / "adaptation-scenarios", "The bob doubles while held upright",
                 {"rows": rows}, body, command)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
