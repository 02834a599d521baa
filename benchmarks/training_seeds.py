"""Default training over seeds: ``python -m benchmarks.training_seeds``.

For each scene and seed: ``python -m fvin_mpc.collect --scene S --seed N`` and ``python -m fvin_mpc.train
--seed N`` with their defaults (plus ``--train-args``, e.g. ``"--poor-loss-ratio none"`` for the former
stop rule), each a fresh process, then optionally the scene's own task with its defaults: ``python -m
fvin_mpc.swingup`` on a body on a pivot, ``python -m fvin_mpc.fly`` (recovery) on a free body
(``--control``). One JSON row per run in ``<out>/rows.jsonl`` (validation loss, swing measure,
iterations, stop reason, restarts, the training's verdict, wall times, the control check), appended as
runs finish so that an interrupted study resumes where it stopped; a summary per scene (median and
range over the seeds) is printed and written to ``<out>/summary.md``. Data and checkpoints stay in
``<out>`` (default: a new temporary folder), never in the repository's ``data/`` or ``checkpoints/``.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fvin_mpc.core.space import R3S3
from fvin_mpc.envs.scenes import existing_scene

#: Seconds a control check may take before it counts as a failure (a model IPOPT cannot solve with
#: spends up to a few seconds per period).
CONTROL_TIMEOUT_S = 600.0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.training_seeds", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", default=["pendulum"],
                        help="built-in scene names or MJCF paths (default: %(default)s)")
    parser.add_argument("--seeds", default="0-9", help="seeds of collect and train: N, N-M or N,M,… "
                        "(default: %(default)s)")
    parser.add_argument("--seed", type=int, default=None, help="one seed (overrides --seeds)")
    parser.add_argument("--out", type=Path, default=None, help="folder for data, checkpoints and rows "
                        "(default: a new temporary folder)")
    parser.add_argument("--train-args", default="", help="extra arguments of fvin_mpc.train, one string")
    parser.add_argument("--collect-args", default="", help="extra arguments of fvin_mpc.collect, one string")
    parser.add_argument("--label", default="", help="a name for this configuration, kept in every row")
    parser.add_argument("--threads", type=int, default=1, help="torch threads of every process (default: 1)")
    parser.add_argument("--control", action="store_true",
                        help="also run the scene's task with the trained model (swingup or fly's recovery)")
    parser.add_argument("--fly-episodes", type=int, default=5, help="recovery starts of a free body's check "
                        "(default: %(default)s)")
    parser.add_argument("--control-timeout", type=float, default=CONTROL_TIMEOUT_S,
                        help="seconds a control check may take; longer counts as failed (default: %(default)s)")
    parser.add_argument("--compare", nargs=2, metavar=("LABEL_A", "LABEL_B"), default=None,
                        help="run nothing: print the per-seed table of two labels' rows already in --out")
    return parser


def parse_seeds(text: str) -> list[int]:
    """``"3"`` → [3], ``"0-9"`` → [0, …, 9], ``"1,4,7"`` → [1, 4, 7]."""
    seeds: list[int] = []
    for part in text.split(","):
        low, _, high = part.strip().partition("-")
        seeds.extend(range(int(low), int(high or low) + 1))
    return seeds


def _run(command: list[str], environment: dict[str, str], timeout: float | None = None) -> tuple[int, float, str]:
    """``(returncode, seconds, stderr's last lines)``; returncode ``-9`` when the timeout killed it."""
    start = time.perf_counter()
    try:
        done = subprocess.run(command, env=environment, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              timeout=timeout)
    except subprocess.TimeoutExpired:
        return -9, time.perf_counter() - start, "timeout"
    tail = "\n".join(done.stderr.strip().splitlines()[-3:])
    return done.returncode, time.perf_counter() - start, tail


def _free_body(scene: str) -> bool:
    return existing_scene(scene).space is R3S3


def one_run(scene: str, seed: int, out: Path, args: argparse.Namespace, environment: dict[str, str],
            earlier: Sequence[dict[str, Any]] = ()) -> dict[str, Any]:
    """Collect, train and (optionally) control one seed of ``scene``; the row. A control check of the same
    weights in ``earlier`` rows (another configuration that trained the same model) is reused."""
    stem = Path(scene).stem
    data = out / "data" / f"{stem}_seed{seed}.npz"
    row: dict[str, Any] = {"scene": scene, "seed": seed, "label": args.label, "train_args": args.train_args}
    if not data.exists():  # the same data for every configuration of a study
        data.parent.mkdir(parents=True, exist_ok=True)
        code, seconds, tail = _run([sys.executable, "-m", "fvin_mpc.collect", "--scene", scene, "--seed", str(seed),
                                    "--out", str(data), "--quiet", *shlex.split(args.collect_args)], environment)
        row["collect_s"] = round(seconds, 1)
        if code != 0:
            return {**row, "error": f"collect failed: {tail}"}
    checkpoint = out / "checkpoints" / (args.label or "default") / f"{stem}_seed{seed}"
    code, seconds, tail = _run([sys.executable, "-m", "fvin_mpc.train", "--data", str(data), "--out", str(checkpoint),
                                "--seed", str(seed), "--quiet", "--threads", str(args.threads),
                                *shlex.split(args.train_args)], environment)
    row["train_process_s"] = round(seconds, 1)
    if code != 0:
        return {**row, "error": f"train failed: {tail}"}
    row["train_warnings"] = [line for line in tail.splitlines() if "warning" in line.lower()]
    sidecar = json.loads(checkpoint.with_suffix(".json").read_text())
    training = sidecar["training"]
    swing = training.get("swing") or {}
    row.update(checkpoint=str(checkpoint), iterations=training["iterations"], stopped=training["stopped"],
               final_validation_loss=training["final_validation_loss"],
               swing_energy_error=swing.get("swing_energy_error"), wall_clock_s=round(training["wall_clock_s"], 1),
               restarts=training.get("restarts"), quality=training.get("quality"),
               weights_sha256=sidecar.get("weights_sha256"),
               history=[{key: entry[key] for key in ("iteration", "train", "validation", "measure", "run")
                         if key in entry} for entry in training["history"]])
    if args.control:
        same = next((r for r in earlier if r["scene"] == scene and "control" in r
                     and _weights_digest(r) == row["weights_sha256"]), None)
        row["control"] = ({**same["control"], "reused_from": same["label"]} if same is not None
                          else control_check(scene, checkpoint, out, args, environment))
    return row


def _weights_digest(row: dict[str, Any]) -> str | None:
    """The trained weights' digest of a row (read from its checkpoint for rows that did not record it)."""
    if row.get("weights_sha256") or "checkpoint" not in row:
        return row.get("weights_sha256")
    sidecar = Path(row["checkpoint"]).with_suffix(".json")
    return json.loads(sidecar.read_text()).get("weights_sha256") if sidecar.exists() else None


def control_check(scene: str, checkpoint: Path, out: Path, args: argparse.Namespace,
                  environment: dict[str, str]) -> dict[str, Any]:
    """The scene's task with its defaults: ``swingup`` (swung up, time, hold error) or ``fly``'s recovery."""
    result = checkpoint.with_name(checkpoint.name + "_control.json")
    if _free_body(scene):
        command = [sys.executable, "-m", "fvin_mpc.fly", "--scene", scene, "--checkpoint", str(checkpoint),
                   "--episodes", str(args.fly_episodes), "--json", str(result), "--quiet"]
    else:
        command = [sys.executable, "-m", "fvin_mpc.swingup", "--scene", scene, "--checkpoint", str(checkpoint),
                   "--json", str(result), "--plot", "", "--quiet"]
    code, seconds, tail = _run(command, environment, args.control_timeout)
    check: dict[str, Any] = {"s": round(seconds, 1)}
    if code != 0 or not result.exists():
        return {**check, "success": False, "error": tail}
    summary = json.loads(result.read_text())
    if _free_body(scene):
        episodes = summary if isinstance(summary, list) else summary.get("episodes", [])
        recovered = [bool(e.get("recovered")) for e in episodes]
        return {**check, "success": bool(recovered) and all(recovered),
                "recovered": f"{sum(recovered)}/{len(recovered)}"}
    return {**check, "success": bool(summary["swung_up"]), "time_to_upright_s": summary["time_to_upright_s"],
            "hold_error_rad": summary["hold_error_rad"], "solver_failures": summary["solver_failures"]}


def summarize(rows: list[dict[str, Any]]) -> str:
    """A markdown table per (scene, label): median and range over the seeds."""

    def spread(values: list[float], digits: str = ".2g") -> str:
        values = [v for v in values if v is not None]
        if not values:
            return "—"
        return f"{np.median(values):{digits}} ({min(values):{digits}}–{max(values):{digits}})"

    lines = ["| scene | label | seeds | validation loss median (range) | swing measure median (range) | "
             "iterations | train s | restarts | warned | control |", "|---|---|---|---|---|---|---|---|---|---|"]
    keys = dict.fromkeys((r["scene"], r["label"]) for r in rows)
    for scene, label in keys:
        group = [r for r in rows if (r["scene"], r["label"]) == (scene, label) and "error" not in r]
        failed = [r for r in rows if (r["scene"], r["label"]) == (scene, label) and "error" in r]
        checks = [r["control"]["success"] for r in group if "control" in r]
        warned = sum(bool(r.get("train_warnings")) for r in group)
        lines.append(
            f"| {scene} | {label or 'default'} | {len(group)}{f' (+{len(failed)} failed)' if failed else ''} | "
            f"{spread([r['final_validation_loss'] for r in group])} | "
            f"{spread([r['swing_energy_error'] for r in group])} | "
            f"{spread([r['iterations'] for r in group], '.0f')} | "
            f"{spread([r['train_process_s'] for r in group], '.0f')} | "
            f"{spread([r.get('restarts') or 0 for r in group], '.0f')} | {warned} | "
            f"{f'{sum(checks)}/{len(checks)}' if checks else '—'} |")
    return "\n".join(lines)


def compare(rows: list[dict[str, Any]], scene: str, labels: Sequence[str], seeds: Sequence[int]) -> str:
    """A markdown table, one line per seed: each label's iterations (restarts), validation loss, swing
    measure and control check."""

    def cell(row: dict[str, Any] | None) -> str:
        if row is None:
            return "— | — | — | —"
        if "error" in row:
            return f"{row['error'][:40]} | | |"
        restarts = f" ({row['restarts']} restart{'s' * (row['restarts'] > 1)})" if row.get("restarts") else ""
        measure = row.get("swing_energy_error")
        control = row.get("control")
        check = "—" if control is None else (
            ("yes" if control["success"] else "**no**")
            + (f", {control['time_to_upright_s']:.2f} s" if control.get("time_to_upright_s") else "")
            + (f", {control['solver_failures']} failed solves" if control.get("solver_failures") else ""))
        return (f"{row['iterations']}{restarts} | {row['final_validation_loss']:.3g} | "
                f"{'—' if measure is None else f'{measure:.3g}'} | {check}")

    head = " | ".join(f"{label}: iterations | validation | measure | task" for label in labels)
    lines = [f"| seed | {head} |", "|---" * (1 + 4 * len(labels)) + "|"]
    for seed in seeds:
        found = [next((r for r in rows if r["scene"] == scene and r["seed"] == seed and r["label"] == label), None)
                 for label in labels]
        lines.append(f"| {seed} | " + " | ".join(cell(row) for row in found) + " |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    seeds = [args.seed] if args.seed is not None else parse_seeds(args.seeds)
    if args.compare is not None and args.out is None:
        raise SystemExit("--compare reads the rows of --out: give it")
    out = args.out or Path(tempfile.mkdtemp(prefix="training_seeds_"))
    out.mkdir(parents=True, exist_ok=True)
    rows_path = out / "rows.jsonl"
    rows = [json.loads(line) for line in rows_path.read_text().splitlines()] if rows_path.exists() else []
    if args.compare is not None:
        for scene in args.scenes:
            print(f"{scene}\n\n{compare(rows, scene, args.compare, seeds)}\n")
        return 0
    done = {(r["scene"], r["seed"], r["label"], r["train_args"]) for r in rows}
    threads = str(args.threads)
    environment = {**os.environ, "OMP_NUM_THREADS": threads, "MKL_NUM_THREADS": threads,
                   "OPENBLAS_NUM_THREADS": threads}
    print(f"training_seeds: writing to {out}", file=sys.stderr)
    for scene in args.scenes:
        for seed in seeds:
            if (scene, seed, args.label, args.train_args) in done:
                continue
            row = one_run(scene, seed, out, args, environment, rows)
            rows.append(row)
            with rows_path.open("a") as handle:
                handle.write(json.dumps(row) + "\n")
            brief = {key: row.get(key) for key in ("scene", "seed", "label", "iterations", "final_validation_loss",
                                                   "swing_energy_error", "restarts", "stopped", "train_process_s",
                                                   "error")}
            if "control" in row:
                brief["control"] = row["control"]
            print(json.dumps(brief), flush=True)
    table = summarize([r for r in rows if r["scene"] in args.scenes])
    (out / "summary.md").write_text(table + "\n")
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
