"""The quadrotor picks up a payload (or wears a rotor) mid-flight: ``python -m benchmarks.payload_adaptation``.

A free body's plant changed with an oracle (docs/adaptation.md), on the built-in ``quadrotor`` (0.5 kg, four rotors
of 0–2.5 N): the real-time MPC (``fly``'s settings) flies the figure-eight (0.5 m, 3 s a loop) from hover; at a
seeded time ``--change-at + U(0, 1) s`` (so that each run meets the change at another point of the loop) every mass
and inertia of the plant becomes ``--mass-scale`` (1.5) times the craft's and its centre of mass moves by
``--shift`` (2 cm straight down: a payload hung under the craft) — ``ScenePhysics.mass_change``; nothing announces
it. The observed state is the plant's centre of mass, which jumps with the payload.

Arms per model (``--models``: the closed form read off the unchanged MJCF, and the shipped learned
checkpoint), ``--runs`` seeded runs each:

* ``none`` — neither the input-disturbance estimate (``disturbance_gain = 0``) nor adaptation;
* ``estimate`` — the disturbance estimate only (``fly``'s gain: the shipped controller);
* ``adaptation`` — :class:`fvin_mpc.control.adaptation.AdaptiveRTI` only (the free body's default set: the
  mass, which scales the model's mass matrix and potential together; a 40-transition window, one
  Levenberg–Marquardt step per period, in the period's spare time);
* ``both`` — the two together;
* ``oracle`` — the disturbance estimate and the model switched at the change to the true mass and inertia
  (``mass = inertia = --mass-scale``; told when and what). The shifted centre of mass is not in it: a model
  of the centre of mass has no such parameter.

"unchanged": the same seeds on the plant that stays (``estimate`` arm). Figures per run: the figure-eight's RMS
position error before the change (the 2 s before it), over the 2 s after it, and from 2 s after it to the end
(``--after`` s), that last one against the unchanged run's over the same window (the issue's target: within
1.2×); the time from the change until the error stays within ``max(1.2 × the unchanged run's largest error over
that window, 5 mm)`` to the end (∞ if never); the mass estimate 2 s after the change (true: ``--mass-scale``,
relative to the model's own body — the gains pinned at 1 fix the free scale: the rotors' thrust constants are
taken as known); deadline misses; compile calls during the episodes. Latency ``measured`` (default: the
controller's compute delays its thrust) or ``none`` (waiting mode).

``--scene X.xml --checkpoint C``: any free-flying craft instead (e.g. a flyer-family member, docs/flyers.md),
its figure-eight scaled to it. ``--change rotor``: instead, rotor ``--rotor`` delivers ``--rotor-scale`` (0.7) of
its command from the change on (``ScenePhysics.actuator_change``); the oracle is told that rotor's gain.
``--task hover`` holds the hover point instead of flying the figure-eight. ``--free gain0 gain1 gain2 gain3``
fits the rotors' gains instead of the mass (the free scale then pins the mass: a uniform payload is all four
rotors weaker alike). ``--low-rank 1 --free lowrank`` (learned model only) fits rank-1 corrections of the
networks' output layers instead (the rotors' force and torque networks: 24 numbers on the built-in craft;
``fvin_mpc.core.model_parameters.low_rank_blocks``), a black-box set beside the physical ones. The mass figure is
the estimate's mass over the rotors' mean gain in every case.

Each finished (model, arm, plant) is cached under ``--cache-dir``; ``--out-dir`` gets
``payload-adaptation.{md,json}``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shlex
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from benchmarks.adaptation_scenarios import (
    OracleSwitch,
    add_loop_options,
    cost_key,
    mass_at,
    recovery_time,
    rms,
    run_arms,
)
from fvin_mpc.control.adaptation import AdaptiveRTI
from fvin_mpc.control.closed_loop import run_episode
from fvin_mpc.control.flight import hover_reference
from fvin_mpc.control.model_export import CompileCount, cache_dir
from fvin_mpc.core.errors import UsageError, run_command
from fvin_mpc.envs.quadrotor_env import QuadrotorEnv
from fvin_mpc.studies.flight_report import figure_eight, make_controller
from fvin_mpc.studies.report import markdown_table, write_report

SCENE = "quadrotor"
ARMS = ("none", "estimate", "adaptation", "both", "oracle")
MODELS = ("closed-form", "learned")
#: The recovery threshold never goes below this (m).
RECOVERY_FLOOR = 0.005
#: Part of every cache key: raise it when what a cell computes changes.
#: 2: the quadrotor's cold call bounded to 2 iterations (was 10); the collector kept out of the controller's time.
CACHE_VERSION = 2


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.payload_adaptation", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default=SCENE, help="a free-flying craft: built-in name or MJCF path "
                        "(default: %(default)s)")
    parser.add_argument("--checkpoint", default=None, help="the learned model (default: the scene's)")
    parser.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    parser.add_argument("--arms", nargs="+", default=list(ARMS), choices=ARMS)
    parser.add_argument("--runs", type=int, default=20, help="seeded runs per arm (default: %(default)s)")
    parser.add_argument("--change-at", type=float, default=4.0,
                        help="earliest change, s; each run adds U(0, 1) s (default: %(default)s)")
    parser.add_argument("--after", type=float, default=6.0,
                        help="seconds flown after the change (default: %(default)s)")
    parser.add_argument("--mass-scale", type=float, default=1.5, help="mass and inertia after the change, relative "
                        "(default: %(default)s)")
    parser.add_argument("--shift", type=float, nargs=3, default=[0.0, 0.0, -0.02],
                        help="centre-of-mass shift in the body frame, m (default: 2 cm down)")
    parser.add_argument("--change", choices=("payload", "rotor"), default="payload",
                        help="payload: --mass-scale and --shift; rotor: actuator --rotor delivers --rotor-scale of "
                             "its command (default: %(default)s)")
    parser.add_argument("--rotor", type=int, default=0, help="the worn rotor (default: %(default)s)")
    parser.add_argument("--rotor-scale", type=float, default=0.7, help="its share of the thrust (default: %(default)s)")
    parser.add_argument("--task", choices=("figure-eight", "hover"), default="figure-eight",
                        help="default: %(default)s")
    parser.add_argument("--free", nargs="+", default=None,
                        help="the adaptation's free parameters (default: the estimator's, the mass; e.g. "
                             "gain0 gain1 gain2 gain3, or lowrank with --low-rank)")
    parser.add_argument("--low-rank", type=int, default=0,
                        help="the learned model's output-layer corrections of this rank among its run-time "
                             "parameters (default: %(default)s, none)")
    add_loop_options(parser)
    parser.add_argument("--cache-dir", default=str(cache_dir() / "payload-adaptation"), help="default: %(default)s")
    parser.add_argument("--out-dir", default="docs/adaptation/payload", help="default: %(default)s")
    return parser


def change_time(args: argparse.Namespace, seed: int) -> float:
    """When run ``seed``'s payload comes: ``--change-at`` plus a seeded share of a second, on a 20 ms period."""
    return args.change_at + round(float(np.random.default_rng(seed).uniform(0.0, 1.0)) / 0.02) * 0.02


def true_change(args: argparse.Namespace) -> dict[str, float]:
    """The oracle's estimate after the change: the payload's mass (its inertia with it), or the worn rotor's gain."""
    if args.change == "payload":
        return {"mass": args.mass_scale}  # every mass and inertia: the estimate's mass scales both
    return {f"gain{args.rotor}": args.rotor_scale}


def true_mass(args: argparse.Namespace) -> float:
    """The effective mass after the change (:func:`effective_mass` of :func:`true_change`): the payload's, or
    for a worn rotor 1 over the rotors' mean strength."""
    if args.change == "payload":
        return args.mass_scale
    rotors = QuadrotorEnv(args.scene).unwrapped.model.nu
    return rotors / (rotors - 1.0 + args.rotor_scale)


def effective_mass(estimate: dict[str, float]) -> float:
    """The estimated mass with the free scale fixed by the rotors' mean strength taken as known: ``mass`` over
    the mean of the gains (a fit of the gains alone says a uniformly heavier craft by weaker rotors, all alike)."""
    gains = [value for name, value in estimate.items() if name.startswith("gain")]
    return float(estimate["mass"] / np.mean(gains))


def scene_physics(scene: str) -> Any:
    """The effects ``scene`` declares (an MJCF path's as the env reads them off the file)."""
    env = QuadrotorEnv(scene)
    physics = env.unwrapped.physics
    env.close()
    return physics


def run_cell(args: argparse.Namespace, model_name: str, arm: str, changed: bool) -> list[dict[str, Any]]:
    """``--runs`` flights of one (model, arm, plant); cached."""
    from tqdm.auto import tqdm

    key = json.dumps([CACHE_VERSION, model_name, arm, changed, args.runs, args.change_at, args.after,
                      args.mass_scale, list(args.shift), args.window, args.latency, args.seed]
                     + ([] if (args.change, args.task, args.free) == ("payload", "figure-eight", None) else
                        [args.change, args.rotor, args.rotor_scale, args.task, args.free])
                     + ([] if (args.scene, args.checkpoint) == (SCENE, None) else [args.scene, args.checkpoint])
                     + cost_key(args, arm)
                     + ([f"low rank {args.low_rank}"] if args.low_rank else [])
                     # the estimate's mass scales the inertia too since these cells (before: mass and potential),
                     # and the mass alone is fitted on the translation's rows (adaptation.TRANSLATION_ROWS)
                     + (["mass scales inertia", "mass on translation"] if arm in ("adaptation", "both") else [])
                     # a moved centre is simulated with the general mass matrix since (envs.scenes.build_model)
                     + (["moving centre compiled"] if any(args.shift) else []))
    path = Path(args.cache_dir) / f"{hashlib.sha256(key.encode()).hexdigest()[:16]}.json"
    if path.is_file():
        return json.loads(path.read_text())["runs"]
    runs, declared = [], scene_physics(args.scene)
    for i in tqdm(range(args.runs), desc=f"{model_name} {arm} {'changed' if changed else 'unchanged'}", leave=False):
        seed = args.seed + i
        at = change_time(args, seed)
        physics = declared
        if changed and args.change == "payload":
            physics = replace(declared, mass_change=(at, args.mass_scale, tuple(args.shift)))
        elif changed:
            physics = replace(declared, actuator_change=(at, args.rotor, args.rotor_scale))
        env = QuadrotorEnv(args.scene, physics=physics)
        overrides = {} if arm in ("estimate", "both", "oracle") else {"disturbance_gain": 0.0}
        rti = make_controller(env, model_name, args.checkpoint, low_rank=args.low_rank,
                              control_cost=args.control_cost, **overrides)
        controller: Any = rti
        if arm in ("adaptation", "both"):
            controller = AdaptiveRTI(rti, window=args.window, free=args.free)
        elif arm == "oracle":
            controller = OracleSwitch(rti, at, true_change(args))
        reference = figure_eight(env) if args.task == "figure-eight" else hover_reference(env)
        controller.set_reference(reference)
        compiles = CompileCount.calls
        episode, _ = run_episode(env, controller, at + args.after, {"hover": True}, seed=seed, latency=args.latency)
        wanted, _ = reference(episode.time)
        error = np.linalg.norm(episode.states[:, :3] - wanted[:, :3], axis=1)
        run = {"seed": seed, "change_at": at, "time": episode.time.tolist(), "error": error.tolist(),
               "deadline_misses": int(episode.deadline_misses), "compile_calls": CompileCount.calls - compiles,
               "busy_ms_max": float(np.nanmax(episode.busy_s) * 1e3) if args.latency == "measured" else None}
        if isinstance(controller, AdaptiveRTI):
            history = [(entry[0], effective_mass(entry[1]), entry[2]) for entry in controller.history]
            run["mass"] = [[h[0], h[1]] for h in history]
            run["update_ms_median"] = float(np.median([h[2] for h in history]) * 1e3)
        runs.append(run)
        env.close()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"key": key, "runs": runs}))
    return runs


def summarize(args: argparse.Namespace, model_name: str, arm: str, runs: list[dict[str, Any]],
              unchanged: list[dict[str, Any]]) -> dict[str, Any]:
    before, transient, after, references, recovery, masses, final, misses = [], [], [], [], [], [], [], 0
    for run, reference in zip(runs, unchanged):
        at, end = run["change_at"], run["change_at"] + args.after
        t, error = np.array(run["time"]), np.array(run["error"])
        t_ref, error_ref = np.array(reference["time"]), np.array(reference["error"])
        tail = (t_ref >= at + 2.0 - 1e-9)
        threshold = max(1.2 * float(error_ref[tail].max()), RECOVERY_FLOOR)
        before.append(rms(t, error, at - 2.0, at))
        transient.append(rms(t, error, at, at + 2.0))
        after.append(rms(t, error, at + 2.0, end + 1.0))
        references.append(rms(t_ref, error_ref, at + 2.0, end + 1.0))
        recovery.append(recovery_time(t, error, at, threshold))
        mass = mass_at(run, at + 2.0)
        if mass is not None:
            masses.append(mass)
            final.append(run["mass"][-1][1])
        misses += run["deadline_misses"]
    ratio = np.array(after) / np.array(references)
    recovery = np.array(recovery)
    row = {
        "model": model_name, "arm": arm, "runs": len(runs),
        "RMS before, mm": 1e3 * float(np.median(before)),
        "RMS first 2 s after, mm": 1e3 * float(np.median(transient)),
        "RMS from +2 s, mm": 1e3 * float(np.median(after)),
        "(worst) ": 1e3 * float(np.max(after)),
        "unchanged, mm": 1e3 * float(np.median(references)),
        "ratio to unchanged (median)": float(np.median(ratio)),
        "(worst)": float(np.max(ratio)),
        "within 1.2×": f"{int(np.sum(ratio <= 1.2))}/{len(runs)}",
        "recovery s (median)": float(np.median(recovery)),
        "recovered within 2 s": f"{int(np.sum(recovery <= 2.0))}/{len(runs)}",
        "deadline misses": misses if args.latency == "measured" else "n/a (waiting)",
        "compile calls": int(sum(run["compile_calls"] for run in runs)),
    }
    if masses:
        error = np.abs(np.array(masses) / true_mass(args) - 1.0)
        row["mass at +2 s (median)"] = float(np.median(masses))
        row["|mass error| (worst)"] = float(error.max())
        row["mass within 5 %"] = f"{int(np.sum(error <= 0.05))}/{len(masses)}"
        row["mass at the end (median)"] = float(np.median(final))
        row["LM update ms (median)"] = float(np.median([run["update_ms_median"] for run in runs]))
    return row


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.runs < 1 or args.after <= 2.0 or not args.mass_scale > 0.0:
        raise UsageError("need --runs >= 1, --after > 2 s and --mass-scale > 0")
    if args.low_rank and args.models != ["learned"]:
        raise UsageError("--low-rank corrects the learned model's networks: add --models learned")
    rows = run_arms(args, run_cell, summarize)
    command = "python -m benchmarks.payload_adaptation " + " ".join(
        shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    columns = ["model", "arm", "runs", "RMS before, mm", "RMS first 2 s after, mm", "RMS from +2 s, mm", "(worst) ",
               "unchanged, mm", "ratio to unchanged (median)", "(worst)", "within 1.2×", "recovery s (median)",
               "recovered within 2 s", "mass at +2 s (median)", "|mass error| (worst)", "mass within 5 %",
               "mass at the end (median)", "LM update ms (median)", "deadline misses", "compile calls"]
    mode = ("measured latency (the controller's compute delays its thrust; the shared machine)"
            if args.latency == "measured" else "waiting mode (the simulator waits for the controller)")
    shift_cm = ", ".join(f"{100 * v:g}" for v in args.shift)
    if args.change == "payload":
        what = (f"every mass and inertia becomes {args.mass_scale:g}× and the centre of mass moves by ({shift_cm}) "
                f"cm in the body frame")
        title = f"A payload picked up mid {args.task}"
    else:
        what = f"rotor {args.rotor} delivers {args.rotor_scale:g} of its command (thrust and yaw reaction)"
        title = f"A rotor worn mid {args.task}"
    task = "the figure-eight" if args.task == "figure-eight" else "hover"
    body = "\n".join([
        f"The `{args.scene}` craft flies {task}; at {args.change_at:g}–{args.change_at + 1:g} s (seeded) {what}; "
        f"{args.runs} seeded runs per arm, {args.after:g} s flown after the change; {mode}. Adaptation's free "
        f"parameters: {', '.join(args.free) if args.free else 'the default (the mass)'}; the MPC's control cost: "
        f"{args.control_cost} (`MPCSettings.control_cost`). "
        f"\"unchanged\": the same seeds on the plant that stays (`estimate` arm). RMS position errors against "
        f"{task}: the 2 s before the change, the 2 s after it, and from 2 s after it to the end (its ratio "
        f"to the unchanged run's over the same window: the issue's target is 1.2×). Recovery: from the change until "
        f"the error stays within max(1.2 × the unchanged run's largest error from +2 s, {1e3 * RECOVERY_FLOOR:g} "
        f"mm). Mass: the adaptation's estimate 2 s after the change, the mass over the rotors' mean gain (the free "
        f"scale fixed by taking the rotors' mean strength as known; true {true_mass(args):.3g}, relative to the "
        f"model's body). Compile calls: code generation or compiler runs during the flights.",
        "",
        markdown_table(rows, columns),
        "",
    ])
    write_report(Path(args.out_dir) / "payload-adaptation", title, {"rows": rows}, body, command)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
