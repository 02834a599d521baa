"""How the controllers stand up to a plant their model does not describe: ``python -m benchmarks.robustness``.

On the pendulum scenes (``--scenes``, default ``pendulum pendulum_damped``), the learned model's MPC
(the scene's shipped checkpoint) beside the closed-form model's MPC (the body read off the *unchanged*
MJCF) and energy shaping on either model, from the same seeded starts
(:func:`fvin_mpc.studies.starts.episode_starts`: start 0 hanging at rest, the others uniform orientations
with |ω| ≤ 2 rad/s), under each condition:

* ``nominal`` — the scene as declared;
* ``gyro-0.02``, ``gyro-0.1`` — Gaussian noise of that σ (rad/s) on the observed angular velocity, every
  body axis (a three-axis gyro: also about the axes the hinge cannot turn);
* ``gyro-0.1-hinge-axis`` — the same noise on the rate about the hinge's axis only (a gyro on the axis);
* ``encoder-12bit`` — the hinge angle observed through a 12-bit absolute encoder;
* ``delay-1-period`` — the torque reaches the joint one control period after it is commanded,
  on top of whatever the latency mode charges; nothing in the controller knows;
* ``mass+30``, ``mass-30`` — the plant's body 30 % heavier / lighter, mass and inertia alike (its
  MJCF body scaled; the models keep the nominal body);
* ``knock-2`` — once the body has held within 0.1 rad of upright for 1 s, its angular velocity
  jumps by 2 rad/s (sign drawn per start); such starts run ``--knock-extra`` seconds longer so that
  the recovery and the 3 s hold fit.

Every perturbation is a declared effect of the plant (:class:`fvin_mpc.envs.ScenePhysics`), so the
controllers are built once on the nominal scene and run unchanged on each perturbed plant. Success is
the evaluation's criterion (upright within 0.1 rad from some time on, held within 0.05 rad over the
last 3 s; :func:`fvin_mpc.control.family_filter.run_judged`); cost the env's accumulated quadratic cost.
The seed of start ``i`` also seeds its noise and knock, so every controller meets the same draws.

Latency: ``--latency measured`` (default) charges each call's wall-clock time to the plant (the torque
acts that long after its observation) and counts calls longer than the control period as deadline
misses; ``--latency none`` is the waiting mode (model quality only). MPCs use ``--solver`` (default
``rti``, the real-time iteration with the scene's presets).

Diagnostics (``--controllers mpc-learned+recold mpc-true+recold``, not run by default): the same MPCs,
reset once per episode — the next call a cold start — when a knocked body has fallen more than 1.5 rad
from upright; whether a stale warm start is what keeps a knocked body down.

Each finished (scene, condition, controller) is cached as JSON in ``--cache-dir`` so that a stopped run
resumes; ``--out-dir`` gets ``robustness.{md,json,png}`` (success rate and cost per condition).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fvin_mpc._cli import add_relinearize_argument
from fvin_mpc.control.family_filter import run_judged
from fvin_mpc.control.scene import scene_energy_shaping, scene_env, scene_model, scene_mpc, scene_mpc_settings
from fvin_mpc.core.errors import UsageError, run_command
from fvin_mpc.envs import RigidBodyEnv
from fvin_mpc.envs.rigid_body_env import geodesic_angle
from fvin_mpc.envs.scenes import SCENES, resolve_scene
from fvin_mpc.studies.report import machine
from fvin_mpc.studies.starts import episode_starts

#: Condition name → the declared plant effects (``ScenePhysics`` fields; ``"period"`` is the control period).
CONDITIONS: dict[str, dict[str, Any]] = {
    "nominal": {},
    "gyro-0.02": {"gyro_noise_std": 0.02},
    "gyro-0.1": {"gyro_noise_std": 0.1},
    "gyro-0.1-hinge-axis": {"gyro_noise_std": 0.1, "gyro_axes": "joint"},
    "encoder-12bit": {"encoder_bits": 12},
    "delay-1-period": {"actuation_delay_s": "period"},
    "mass+30": {"mass_scale": 1.3},
    "mass-30": {"mass_scale": 0.7},
    "knock-2": {"impulse_delta_omega": 2.0},
}
CONTROLLERS = ("mpc-learned", "mpc-true", "energy-learned", "energy-true")
#: Diagnostic variants, not run by default: the MPC forced to one cold start once a knocked body has fallen
#: further than :data:`FALLEN_RAD` from upright (whether a stale warm start is what keeps it down).
DIAGNOSTICS = ("mpc-learned+recold", "mpc-true+recold")
FALLEN_RAD = 1.5
#: The issue's target: learned success within this many percentage points of the closed form's.
TARGET_POINTS = 5.0


#: Part of every cell's cache path: raise it when what a cell computes changes (the cache cannot see code changes).
#: 2: the disturbance estimate's default gain 0.1 (was 0.5).
CACHE_VERSION = 2


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.robustness", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", default=["pendulum", "pendulum_damped"],
                        help="built-in hinge scenes, each with its shipped model (default: %(default)s)")
    parser.add_argument("--starts", type=int, default=50, help="starts per condition (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the starts, noise, knocks (default: %(default)s)")
    parser.add_argument("--duration", type=float, default=10.0, help="seconds per episode (default: %(default)s)")
    parser.add_argument("--knock-extra", type=float, default=5.0,
                        help="extra seconds of the knock condition's episodes (default: %(default)s)")
    parser.add_argument("--conditions", nargs="+", choices=tuple(CONDITIONS), default=list(CONDITIONS))
    parser.add_argument("--controllers", nargs="+", choices=CONTROLLERS + DIAGNOSTICS, default=list(CONTROLLERS),
                        help="default: the four controllers; the +recold variants are diagnostics (see the docstring)")
    parser.add_argument("--solver", choices=("rti", "ipopt"), default="rti", help="the MPCs' (default: %(default)s)")
    add_relinearize_argument(parser)  # its own cache
    parser.add_argument("--latency", choices=("measured", "none"), default="measured",
                        help="measured: compute time charged to the plant; none: waiting mode (default: %(default)s)")
    parser.add_argument("--cache-dir", type=Path, default=Path("build/robustness-cache"), help="default: %(default)s")
    parser.add_argument("--out-dir", type=Path, default=Path("docs/robustness"), help="default: %(default)s")
    parser.add_argument("--no-report", action="store_true", help="run and cache, write no report")
    return parser


def _controller(name: str, scene: str, solver: str, relinearize_every: int | None = None) -> tuple[Any, float]:
    """The controller ``name`` built on the *nominal* scene, and the control period it plans at
    (``relinearize_every``: the real-time MPC's ``RTIOptions`` field, ``None`` the scene's)."""
    learned = name.removesuffix("+recold").endswith("-learned")
    env = scene_env(scene) if learned else scene_env(scene, true_model=True)
    model = scene_model(env) if learned else scene_model(env, true_model=True)
    if name.startswith("mpc"):
        rti = {} if relinearize_every is None else {"rti": {"relinearize_every": relinearize_every}}
        controller = scene_mpc(env, model, scene_mpc_settings(env, solver=solver, **rti))
    else:
        controller = scene_energy_shaping(env, model)
    period = float(env.unwrapped.dt)
    env.close()
    return controller, period


class RecoldAfterFall:
    """``controller``, reset once per episode (its next call a cold start) when the plant has been knocked
    and the observed orientation is more than :data:`FALLEN_RAD` from the goal."""

    def __init__(self, controller: Any, env: Any) -> None:
        self.controller, self.env, self.recolded = controller, env, False

    def reset(self) -> None:
        self.recolded = False
        self.controller.reset()

    def prepare(self) -> None:
        self.controller.prepare()

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, dict[str, Any]]:
        base = self.env.unwrapped
        if not self.recolded and base.knocked and geodesic_angle(x[:4], base.goal) > FALLEN_RAD:
            self.controller.reset()
            self.recolded = True
        return self.controller(x)


def plant(scene: str, condition: str, period: float) -> Any:
    """The scene's env stepping at ``period`` with the condition's effects declared on top of its physics."""
    spec = resolve_scene(scene)
    effects = {k: (period if v == "period" else v) for k, v in CONDITIONS[condition].items()}
    return RigidBodyEnv(scene=spec, physics=replace(spec.physics, **effects), control_period=period)


def run_cell(args: argparse.Namespace, scene: str, condition: str, name: str, controller: Any,
             period: float) -> dict[str, Any]:
    """The episodes of one controller under one condition, from the shared starts."""
    from tqdm.auto import tqdm

    env = plant(scene, condition, period)
    if name.endswith("+recold"):
        controller = RecoldAfterFall(controller, env)
    duration = args.duration + (args.knock_extra if "impulse_delta_omega" in CONDITIONS[condition] else 0.0)
    episodes = []
    for start in tqdm(episode_starts(args.starts, args.seed, (2.0,)), desc=f"{scene} {condition} {name}", leave=False):
        episode, metrics = run_judged(env, controller, duration, start.reset_options, latency=args.latency,
                                      seed=start.seed)
        feedback = 1e3 * episode.feedback_s[np.isfinite(episode.feedback_s)]
        busy = 1e3 * episode.busy_s[np.isfinite(episode.busy_s)]
        episodes.append({
            "start": start.index,
            "swung_up": bool(metrics["swung_up"]),
            "time_to_upright_s": metrics["time_to_upright_s"],
            "hold_error_rad": metrics["hold_error_rad"],
            "cost": metrics["accumulated_cost"],
            "knocked": bool(env.unwrapped.knocked),
            "recolded": bool(getattr(controller, "recolded", False)),
            "feedback_ms_median": float(np.median(feedback)),
            "feedback_ms_max": float(feedback.max()),
            "busy_ms_max": float(busy.max()),
            "deadline_misses": metrics["deadline_misses"],
            "controller_failures": metrics["controller_failures"],
        })
    env.close()
    return {"scene": scene, "condition": condition, "controller": name, "duration_s": duration,
            "episodes": episodes}


def run(args: argparse.Namespace) -> dict[tuple[str, str, str], dict[str, Any]]:
    """Every (scene, condition, controller) cell, from the cache where it is there."""
    cells: dict[tuple[str, str, str], dict[str, Any]] = {}
    for scene in args.scenes:
        kept = "" if args.rti_relinearize_every is None else f"-relinearize{args.rti_relinearize_every}"
        cache = args.cache_dir / f"{scene}-default-v{CACHE_VERSION}" / f"{args.solver}-{args.latency}{kept}" / (
            f"seed{args.seed}-starts{args.starts}-T{args.duration:g}")
        cache.mkdir(parents=True, exist_ok=True)
        for name in args.controllers:
            controller = period = None
            for condition in args.conditions:
                path = cache / f"{condition}__{name}.json"
                if path.exists():
                    cells[scene, condition, name] = json.loads(path.read_text())
                    continue
                if controller is None:
                    controller, period = _controller(name, scene, args.solver, args.rti_relinearize_every)
                start = time.perf_counter()
                cell = run_cell(args, scene, condition, name, controller, period)
                cell["wall_s"] = time.perf_counter() - start
                path.write_text(json.dumps(cell, indent=1) + "\n")
                cells[scene, condition, name] = cell
                up = sum(e["swung_up"] for e in cell["episodes"])
                print(f"{scene} {condition} {name}: {up}/{len(cell['episodes'])} up ({cell['wall_s']:.0f} s)",
                      file=sys.stderr)
    return cells


def summarize(cell: dict[str, Any]) -> dict[str, Any]:
    episodes = cell["episodes"]
    costs = np.array([e["cost"] for e in episodes])
    misses = [e["deadline_misses"] for e in episodes]
    return {
        "success_pct": 100.0 * np.mean([e["swung_up"] for e in episodes]),
        "cost_mean": float(costs.mean()),
        "cost_median": float(np.median(costs)),
        "knocked": sum(e["knocked"] for e in episodes),
        "hold_error_median_rad": float(np.median([e["hold_error_rad"] for e in episodes])),
        "hold_error_p90_rad": float(np.percentile([e["hold_error_rad"] for e in episodes], 90)),
        "reached_upright": sum(e["time_to_upright_s"] is not None for e in episodes),
        "deadline_misses": sum(misses) if all(isinstance(m, int) for m in misses) else "not measured",
        "feedback_ms_median": float(np.median([e["feedback_ms_median"] for e in episodes])),
        "feedback_ms_max": float(np.max([e["feedback_ms_max"] for e in episodes])),
        "busy_ms_max": float(np.max([e.get("busy_ms_max", np.nan) for e in episodes])),
        "controller_failures": sum(e["controller_failures"] for e in episodes),
    }


def write_report(args: argparse.Namespace, cells: dict[tuple[str, str, str], dict[str, Any]], command: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary = {"/".join(key): summarize(cell) for key, cell in cells.items()}
    scenes = [scene for scene in args.scenes if any(key[0] == scene for key in cells)]
    figure, axes = plt.subplots(len(scenes), 2, figsize=(13, 4.4 * len(scenes)), squeeze=False)
    width = 0.8 / len(args.controllers)
    tables, timing = [], []
    pairs = [kind for kind in ("mpc", "energy") if {f"{kind}-learned", f"{kind}-true"} <= set(args.controllers)]
    for row_axes, scene in zip(axes, scenes):
        conditions = [c for c in args.conditions if all((scene, c, n) in cells for n in args.controllers)]
        for j, name in enumerate(args.controllers):
            x = np.arange(len(conditions)) + (j - (len(args.controllers) - 1) / 2) * width
            row_axes[0].bar(x, [summary[f"{scene}/{c}/{name}"]["success_pct"] for c in conditions], width, label=name)
            row_axes[1].bar(x, [summary[f"{scene}/{c}/{name}"]["cost_median"] for c in conditions], width, label=name)
        for ax, label in zip(row_axes, ("success %", "median accumulated cost")):
            ax.set_xticks(range(len(conditions)), conditions, rotation=30, ha="right")
            ax.set_ylabel(label)
            ax.set_title(scene)
        row_axes[0].legend(fontsize=8, loc="lower left")

        header = ["condition"] + [f"{n} success % / median cost" for n in args.controllers] + [
            f"{kind}: learned − closed form (points)" for kind in pairs]
        lines = [f"### `{scene}`", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        for c in conditions:
            row = [c]
            for n in args.controllers:
                s = summary[f"{scene}/{c}/{n}"]
                row.append(f"{s['success_pct']:.0f} / {s['cost_median']:.0f}")
            for kind in pairs:
                gap = (summary[f"{scene}/{c}/{kind}-learned"]["success_pct"]
                       - summary[f"{scene}/{c}/{kind}-true"]["success_pct"])
                row.append(f"{gap:+.0f}" + ("" if gap >= -TARGET_POINTS else " (**target not met**)"))
            lines.append("| " + " | ".join(row) + " |")
        tables += [*lines, ""]
        for c in conditions:
            for n in args.controllers:
                s = summary[f"{scene}/{c}/{n}"]
                timing.append(f"| {scene} | {c} | {n} | {s['reached_upright']} | {s['hold_error_median_rad']:.3f} / "
                              f"{s['hold_error_p90_rad']:.3f} | "
                              f"{s['feedback_ms_median']:.2f} / {s['feedback_ms_max']:.1f} | "
                              f"{s['busy_ms_max']:.1f} | {s['deadline_misses']} | "
                              f"{s['knocked'] if c == 'knock-2' else '—'} | {s['controller_failures']} |")
    figure.suptitle(f"{args.starts} starts per condition, MPC solver {args.solver}, latency {args.latency}")
    figure.tight_layout()
    args.out_dir.mkdir(parents=True, exist_ok=True)
    figure.savefig(args.out_dir / "robustness.png", dpi=80)
    plt.close(figure)

    mode = ("measured latency: each call's wall-clock time is charged to the plant, and a call longer than the "
            "control period is a deadline miss" if args.latency == "measured" else
            "waiting mode: the simulator waits for the controller (model quality, not real time)")
    body = "\n".join([
        f"{args.starts} seeded starts per condition (seed {args.seed}), {args.duration:g} s episodes "
        f"({args.duration + args.knock_extra:g} s for `knock-2`), MPC solver `{args.solver}`, {mode}. "
        "Timings come from a shared, loaded 2-core machine (other jobs running).",
        "",
        "Success % and median accumulated cost per condition (the target: the learned controller's success within "
        f"{TARGET_POINTS:g} points of the closed form's, here for the MPC and for energy shaping):",
        "",
        *tables,
        "![success and cost per condition](robustness.png)",
        "",
        "Per cell: starts upright within 0.1 rad from some time on (the hold criterion aside), the largest angle "
        "over the last 3 s (median / p90 over the starts; success needs ≤ 0.05 rad), compute per controller "
        "call, deadline misses, knocked starts:",
        "",
        "| scene | condition | controller | reached upright | hold error rad median / p90 | feedback ms median / max | "
        "feedback + preparation ms max | deadline misses | knocked starts | controller failures |",
        "|---|---|---|---|---|---|---|---|---|---|",
        *timing,
        "",
    ])
    stem = args.out_dir / "robustness"
    # Per start only what the tables are made of (the whole episodes stay in the cache).
    rounded = lambda value: round(value, 4) if isinstance(value, float) else value  # noqa: E731
    per_start = {"/".join(key): {field: [rounded(e[field]) for e in cell["episodes"]]
                                 for field in ("swung_up", "cost", "hold_error_rad", "time_to_upright_s")}
                 for key, cell in cells.items()}
    stem.with_suffix(".json").write_text(json.dumps(
        {"command": command, "machine": machine(), "summary": summary, "per_start": per_start}) + "\n")
    stem.with_suffix(".md").write_text(f"# Robustness: the learned controller under plant perturbations\n\n"
                                       f"Produced by `{command}`\n\n{body}")


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.starts < 1:
        raise UsageError(f"--starts must be >= 1, got {args.starts}")
    if args.rti_relinearize_every is not None and args.solver != "rti":
        raise UsageError("--rti-relinearize-every needs the real-time iteration (--solver rti)")
    unknown = [scene for scene in args.scenes if scene not in SCENES]
    if unknown:
        raise UsageError(f"--scenes {unknown}: expected built-in pivoted scenes, some of {sorted(SCENES)}")
    cells = run(args)
    if not args.no_report:
        command = "python -m benchmarks.robustness " + " ".join(
            shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
        write_report(args, cells, command)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
