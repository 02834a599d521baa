"""Which model number predicts control: ``python -m benchmarks.measure_vs_control``.

Wanted: a model measure that predicts closed-loop control where the validation loss does not
(docs/excitation.md). Once every family member succeeds, a family report has nothing left to predict
(docs/scene-families.md), so this study makes models of different quality on purpose: for each of the
first ``--scenes`` members of a family (the family filter's, from ``--seed-offset``), one ``collect``
(defaults), then ``train`` (defaults, one torch thread) stopped after each of ``--iterations``
Levenberg–Marquardt iterations (``0`` = the default, which stops by itself). Every model is run with
the scene's default MPC (RTI, **waiting mode**: the simulator waits for the controller — a
model-quality figure, not a real-time one) from the family report's starts beside the closed form.

For each model: the selected iteration's swing measure and validation loss (the checkpoint's
``training.selected``; the validation windows are the same for every model of a scene: one data set,
one split), and the learned / closed-form cost ratio (median over the starts) and the share of the
closed form's successes it missed. Reported: Spearman's rank correlation of each number with each
outcome, **within each scene** (the mean over scenes: does the better-measured of two models of the
same scene control better?) and **pooled** over all models of all scenes. Scenes' cached results live
under ``--cache-dir``: a stopped run resumes.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import shlex
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from benchmarks.scene_families import report_starts, run_episodes
from fvin_mpc import collect, train
from fvin_mpc.control.family_filter import feasible, swingup_duration
from fvin_mpc.envs.families import write_family
from fvin_mpc.studies.report import markdown_table, write_report

#: LM iterations each model's training is stopped after (0: the default, stopped by its own criteria).
DEFAULT_ITERATIONS = (1, 2, 4, 0)
PREDICTORS = ("measure", "validation")
OUTCOMES = ("cost_ratio", "missed_share")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.measure_vs_control", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--family", choices=("hinge", "ball"), default="hinge")
    parser.add_argument("--scenes", type=int, default=6, help="family members (default: %(default)s)")
    parser.add_argument("--seed-offset", type=int, default=9000, help="first seed drawn (default: %(default)s)")
    parser.add_argument("--starts", type=int, default=5, help="starts per model (default: %(default)s)")
    parser.add_argument("--iterations", type=int, nargs="+", default=list(DEFAULT_ITERATIONS),
                        help="training iterations per model, 0 = the default (default: %(default)s)")
    parser.add_argument("--max-duration", type=float, default=20.0, help="longest episode, s (default: %(default)s)")
    parser.add_argument("--cache-dir", type=Path, default=Path("build/measure-vs-control"),
                        help="default: %(default)s")
    parser.add_argument("--out-dir", type=Path, default=Path("docs/measure-vs-control"), help="default: %(default)s")
    return parser


def run_model(scene: Path, data: Path, stem: Path, iterations: int, starts: int, seed: int,
              max_duration: float) -> dict[str, Any]:
    """Train one model on ``data`` (``iterations`` LM iterations, 0 = default) and run it beside the closed form."""
    import torch

    from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings

    torch.set_num_threads(1)
    cap = ["--iterations", str(iterations)] if iterations else []
    with contextlib.redirect_stdout(io.StringIO()):
        train.main(["--data", str(data), "--out", str(stem), "--quiet", "--threads", "1", *cap])
    selected = json.loads(Path(f"{stem}.json").read_text())["training"]["selected"]
    env = scene_env(str(scene), checkpoint=str(stem))
    learned = scene_mpc(env, scene_model(env, str(stem)), scene_mpc_settings(env, solver="rti"))
    duration = min(swingup_duration(env), max_duration)
    episodes = run_episodes(env, learned, report_starts(env, starts, seed), duration, "none")
    env.close()
    return {"iterations": iterations, "measure": selected["measure"], "validation": selected["validation"],
            "episodes": episodes}


def closed_form(scene: Path, starts: int, seed: int, max_duration: float, control_period: float) -> list[dict]:
    from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings

    env = scene_env(str(scene), true_model=True, control_period=control_period)
    mpc = scene_mpc(env, scene_model(env, true_model=True), scene_mpc_settings(env, solver="rti"))
    duration = min(swingup_duration(env), max_duration)
    episodes = run_episodes(env, mpc, report_starts(env, starts, seed), duration, "none")
    env.close()
    return episodes


def outcomes(learned: list[dict], closed: list[dict]) -> dict[str, float]:
    ratios = [a["cost"] / b["cost"] for a, b in zip(learned, closed) if b["cost"] > 0]
    closed_up = sum(b["swung_up"] for b in closed)
    both = sum(a["swung_up"] and b["swung_up"] for a, b in zip(learned, closed))
    return {"cost_ratio": float(np.median(ratios)),
            "missed_share": 1.0 - both / closed_up if closed_up else float("nan"),
            "learned_up": sum(a["swung_up"] for a in learned), "closed_up": closed_up}


def correlations(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Spearman's rho of each predictor with each outcome: within each scene (mean, and the scenes it
    was defined on: both sides not constant) and pooled over all rows."""
    from scipy.stats import spearmanr

    result: dict[str, Any] = {}
    scenes = sorted({row["seed"] for row in rows})
    for predictor in PREDICTORS:
        for outcome in OUTCOMES:
            within = []
            for seed in scenes:
                x = np.array([r[predictor] for r in rows if r["seed"] == seed], dtype=float)
                y = np.array([r[outcome] for r in rows if r["seed"] == seed], dtype=float)
                if len(x) >= 3 and np.ptp(x) > 0 and np.ptp(y) > 0 and np.all(np.isfinite(y)):
                    within.append(float(spearmanr(x, y)[0]))
            x = np.array([r[predictor] for r in rows], dtype=float)
            y = np.array([r[outcome] for r in rows], dtype=float)
            usable = np.isfinite(y)
            pooled = float(spearmanr(x[usable], y[usable])[0]) if usable.sum() >= 4 and np.ptp(y[usable]) > 0 else None
            result[f"{predictor}_vs_{outcome}"] = {"within_mean": float(np.mean(within)) if within else None,
                                                    "within_scenes": len(within), "pooled": pooled}
    return result


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(10, 4))
    for axis, predictor, label in zip(axes, PREDICTORS, ("swing measure", "validation loss")):
        for seed in sorted({r["seed"] for r in rows}):
            mine = [r for r in rows if r["seed"] == seed]
            axis.loglog([r[predictor] for r in mine], [r["cost_ratio"] for r in mine], "o-", label=str(seed), ms=4)
        axis.set_xlabel(label)
        axis.set_ylabel("learned / closed-form cost (median over starts)")
        axis.grid(True, which="both", alpha=0.3)
    axes[0].legend(title="scene", fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if any(n < 0 for n in args.iterations):
        raise SystemExit("--iterations must be >= 0 (0: the default training)")
    rows: list[dict[str, Any]] = []
    members = 0
    for seed in range(args.seed_offset, args.seed_offset + 5 * args.scenes):
        if members >= args.scenes:
            break
        work = args.cache_dir / args.family / str(seed)
        work.mkdir(parents=True, exist_ok=True)
        (scene,) = write_family(args.family, [seed], work)
        verdict = work / "filter.json"
        if not verdict.exists():
            verdict.write_text(json.dumps(feasible(scene)[1], indent=1, default=float) + "\n")
        if not json.loads(verdict.read_text())["ok"]:
            print(f"{args.family} {seed}: filter out", file=sys.stderr)
            continue
        members += 1
        data = work / "data.npz"
        if not data.exists():
            with contextlib.redirect_stdout(io.StringIO()):
                collect.main(["--scene", str(scene), "--out", str(data), "--quiet"])
        closed_path = work / "closed_form.json"
        for iterations in args.iterations:
            record = work / f"result_{iterations}.json"
            if not record.exists():
                result = run_model(scene, data, work / f"model_{iterations}", iterations, args.starts, seed,
                                   args.max_duration)
                record.write_text(json.dumps(result, indent=1, default=float) + "\n")
            result = json.loads(record.read_text())
            if not closed_path.exists():  # at the models' step (the data's control period)
                period = _step_size(work / f"model_{iterations}")
                episodes = closed_form(scene, args.starts, seed, args.max_duration, period)
                closed_path.write_text(json.dumps(episodes, indent=1, default=float) + "\n")
            closed = json.loads(closed_path.read_text())
            row = {"seed": seed, "iterations": iterations or "default", "measure": result["measure"],
                   "validation": result["validation"], **outcomes(result["episodes"], closed)}
            rows.append(row)
            print(f"{args.family} {seed} iterations {row['iterations']}: measure {row['measure']:.3g}, "
                  f"validation {row['validation']:.3g}, cost ratio {row['cost_ratio']:.2f}, "
                  f"up {row['learned_up']}/{row['closed_up']}", file=sys.stderr)
    if not rows:
        return 0
    result = correlations(rows)
    command = "python -m benchmarks.measure_vs_control " + " ".join(
        shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    args.out_dir.mkdir(parents=True, exist_ok=True)
    plot(rows, args.out_dir / "measure-vs-control.png")
    table = [{"predictor": p, "outcome": o, "within a scene (mean ρ)": _rho(result[f"{p}_vs_{o}"]["within_mean"]),
              "scenes defined": result[f"{p}_vs_{o}"]["within_scenes"],
              "pooled ρ": _rho(result[f"{p}_vs_{o}"]["pooled"])} for p in PREDICTORS for o in OUTCOMES]
    body = (f"{args.family} family, {members} members from seed {args.seed_offset} (the family filter's), "
            f"{len(args.iterations)} models each ({', '.join(str(n or 'default') for n in args.iterations)} "
            f"training iterations), {args.starts} starts per model, RTI in waiting mode (model quality, not real "
            "time). Positive ρ: a worse number goes with a worse outcome.\n\n"
            + markdown_table(table, list(table[0])) + "\n\nPer model:\n\n"
            + markdown_table(rows, ["seed", "iterations", "measure", "validation", "cost_ratio", "missed_share",
                                    "learned_up", "closed_up"])
            + "\n\n![cost ratio against each number](measure-vs-control.png)\n")
    write_report(args.out_dir / "measure-vs-control", "Which model number predicts control",
                 {"rows": rows, "correlations": result}, body, command)
    return 0


def _rho(value: float | None) -> str:
    return "—" if value is None else f"{value:+.2f}"


def _step_size(stem: Path) -> float:
    return float(json.loads(Path(f"{stem}.json").read_text())["model"]["step_size"])


if __name__ == "__main__":
    raise SystemExit(main())
