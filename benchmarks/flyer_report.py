"""The free-flyer family through the whole pipeline: ``python -m benchmarks.flyer_report``.

Seeds from ``--seed-offset`` on are drawn (:mod:`fvin_mpc.envs.flyer_family`) and filtered: a draw
enters the family only if the closed-form MPC (``fly --model closed-form``, the craft read off its
MJCF) recovers it to hover from every one of ``--starts`` recovery starts (fly's starts and criterion:
upside down at rest, upside down tumbling, then random attitudes tumbling at up to 10 rad/s; within
0.1 m and 0.1 rad from some time on), never looking at a learned model. For each of the first
``--scenes`` members: ``collect`` → ``train`` → build, each with the commands' defaults (library calls;
training on one torch thread), then the learned-model MPC from the same starts and both models on the
craft's figure-eight (:func:`fvin_mpc.control.flight.scaled_figure_eight`).

As :mod:`benchmarks.scene_families`: each finished scene and each filter verdict is cached as JSON in
``--cache-dir`` (a stopped run resumes; the filter, always in waiting mode, and each member's data and
checkpoint are shared by both latency modes, so ``--latency measured`` after a waiting run only flies;
``--cached-only`` assembles the report from what runs over other seed ranges left there), the
report — per scene and for the family: starts recovered
(learned / closed form), figure-eight RMS (learned / closed form), time per controller call, deadline
misses, collect + train + build wall time, the filter's rejection rate — goes to ``--out-dir`` as
``flyer-family.md`` with the command that produced it, and ``flyer-family.png``.

``--latency none`` (default) is the waiting mode: model-quality figures, not real time (deadline
misses are then "not measured"); ``--latency measured`` charges the controller's compute time.

Seeds: development used 0–39 (tests/test_quadrotor_mjcf.py) and 5000–5015; the report's default
``--seed-offset`` is 7000.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import shlex
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fvin_mpc import collect, train
from fvin_mpc._cli import add_relinearize_argument, run_command
from fvin_mpc.control.flight import recovery_duration
from fvin_mpc.core.quadrotor import from_mujoco
from fvin_mpc.envs.flyer_family import write_flyers
from fvin_mpc.studies.flight_report import make_controller, make_env, run_figure_eight, run_recovery

DEFAULT_SEED_OFFSET = 7000
DEVELOPMENT_SEEDS = "0–39 and 5000–5015"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.flyer_report", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=8, help="family members to run (default: %(default)s)")
    parser.add_argument("--starts", type=int, default=5, help="recovery starts per scene (default: %(default)s)")
    parser.add_argument("--seed-offset", type=int, default=DEFAULT_SEED_OFFSET,
                        help="first seed (default: %(default)s)")
    parser.add_argument("--max-draws", type=int, default=None, help="seeds to try at most (default: 3 × --scenes)")
    parser.add_argument("--latency", choices=["none", "measured"], default="none", help="(default: %(default)s)")
    add_relinearize_argument(parser)  # its own flights in the cache; the filter, data and checkpoints shared
    parser.add_argument("--cache-dir", type=Path, default=Path("build/flyer-family-cache"),
                        help="per-scene JSON and the data and checkpoints (default: %(default)s)")
    parser.add_argument("--out-dir", type=Path, default=Path("docs/flyer-family"),
                        help="report folder (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="seeds the recovery starts (default: %(default)s)")
    parser.add_argument("--train-time-limit", type=float, default=None,
                        help="train's --time-limit in s (default: train's own, none): what keeps collect + train + "
                             "build within a per-command time limit on a loaded machine")
    parser.add_argument("--max-trainings", type=int, default=None,
                        help="stop at the first member whose collect + train would be the (N+1)-th this run starts "
                             "(default: no limit); with 0 and 1 in turn, each run of a per-command time limit "
                             "starts its training at once")
    parser.add_argument("--cached-only", action="store_true",
                        help="skip the draws with no cached filter verdict and the members with no cached flights "
                             "(assemble the report of runs made in pieces, e.g. over two seed ranges at once)")
    return parser


def _recovery(env: Any, controller: Any, starts: int, seed: int, latency: str) -> list[dict[str, Any]]:
    rows, _, _ = run_recovery(env, controller, starts, seed, latency, progress=False)
    keys = ("recovered", "time_to_recover_s", "final_position_m", "final_angle_rad", "solve_time_ms",
            "deadline_misses", "first_period_missed", "controller_failures")
    return [{key: row[key] for key in keys if key in row} for row in rows]


def _figure_eight(env: Any, controller: Any, latency: str) -> dict[str, Any]:
    tracking, _, _ = run_figure_eight(env, controller, latency, progress=False)
    keys = ("rms_position_m", "max_position_m", "deadline_misses", "first_period_missed", "controller_failures",
            "amplitude_m", "period_s")
    return {key: tracking[key] for key in keys if key in tracking}


def hover_margin(scales: Any, low: np.ndarray, high: np.ndarray) -> float:
    """The smallest share of an actuator's range left between its hover control and the nearer bound:
    what the craft has to turn with at hover (a centre of mass far off the rotors' centre can leave a
    rotor near full thrust however large the total thrust-to-weight)."""
    hover = np.asarray(scales.hover_control, dtype=float)
    return float(np.min(np.minimum(hover - low, high - hover) / (high - low)))


#: In waiting mode the RTI's wall-clock budgets are lifted: the cold call runs its counted iterations
#: (``cold_iter`` per first guess). With the 8 ms cold budget the filter's
#: verdict on a draw depended on the machine's load (7013: 5/5, then 4/5 on a busier afternoon).
WAITING_RTI = {"cold_budget_s": float("inf"), "budget_s": float("inf")}


def _controller(env: Any, model: str, latency: str, checkpoint: str | None = None,
                relinearize_every: int | None = None) -> Any:
    """``fly``'s controller of ``model``; in waiting mode bounded by counts only (:data:`WAITING_RTI`);
    ``relinearize_every``: ``RTIOptions.relinearize_every`` (``None``: the default)."""
    rti = {**(WAITING_RTI if latency == "none" else {}),
           **({} if relinearize_every is None else {"relinearize_every": relinearize_every})}
    return make_controller(env, model, checkpoint, **({"rti": rti} if rti else {}))


def filter_verdict(path: Path, starts: int, seed: int) -> dict[str, Any]:
    """The closed-form MPC on ``path``'s craft from ``starts`` recovery starts, in waiting mode (whether the
    physics can be recovered by this controller, not whether it keeps real time): in the family if it
    recovers from all of them (the recoveries are the closed form's waiting-mode results in the report)."""
    env = make_env(scene=path)
    t0 = time.perf_counter()
    try:
        craft = from_mujoco(env.model, env.body_name)
    except ValueError as error:
        return {"ok": False, "reason": str(error)}
    controller = _controller(env, "closed-form", latency="none")
    recovery = _recovery(env, controller, starts, seed, "none")
    figure_eight = _figure_eight(env, controller, "none")
    env.close()
    scales = env.unwrapped.scales
    return {"ok": all(r["recovered"] for r in recovery), "recovery": recovery, "figure_eight": figure_eight,
            "unmodelled": list(craft.unmodelled), "control_period_s": float(env.dt),
            "recovery_duration_s": recovery_duration(scales), "attitude_time_s": scales.attitude_time,
            "yaw_time_s": scales.yaw_time, "thrust_to_weight": scales.thrust_to_weight,
            "hover_margin": hover_margin(scales, env.unwrapped.torque_low, env.unwrapped.torque_high),
            "build_s": float(controller.build_s), "wall_s": time.perf_counter() - t0}


def _pipeline(seed: int, path: Path, work: Path, time_limit: float | None = None) -> tuple[Path, dict[str, float]]:
    """``collect`` → ``train`` for one member, once for both latency modes; its checkpoint and wall times."""
    import torch

    torch.set_num_threads(1)
    data, stem, timings = work / f"flyer_{seed}.npz", work / f"flyer_{seed}_model", work / f"flyer_{seed}_times.json"
    if timings.exists():
        return stem, json.loads(timings.read_text())
    quiet = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(quiet):
        collect.main(["--scene", str(path), "--out", str(data), "--quiet"])
    t1 = time.perf_counter()
    with contextlib.redirect_stdout(quiet):
        train.main(["--data", str(data), "--out", str(stem), "--quiet", "--threads", "1",
                    *([] if time_limit is None else ["--time-limit", str(time_limit)])])
    times = {"collect_s": t1 - t0, "train_s": time.perf_counter() - t1, "load_average": os.getloadavg()[0]}
    timings.write_text(json.dumps(times) + "\n")
    return stem, times


def run_scene(seed: int, path: Path, work: Path, verdict: dict[str, Any], starts: int, seed_starts: int,
              latency: str, train_time_limit: float | None = None,
              relinearize_every: int | None = None) -> dict[str, Any]:
    """Collect → train → build → fly one member; the record cached for it. In measured latency the closed
    form flies again in that mode (the filter's flights wait for the controller)."""
    stem, times = _pipeline(seed, path, work, train_time_limit)
    t2 = time.perf_counter()
    env = make_env(scene=path)
    learned = _controller(env, "learned", latency, str(stem), relinearize_every)
    t3 = time.perf_counter()
    sidecar = json.loads(Path(f"{stem}.json").read_text()) if Path(f"{stem}.json").exists() else {}
    training = sidecar.get("training", {})
    record = {
        "seed": seed, "scene": str(path), "latency": latency,
        "facts": json.loads(path.with_suffix(".json").read_text()),
        "collect_s": times["collect_s"], "train_s": times["train_s"], "build_s": t3 - t2,
        "pipeline_s": times["collect_s"] + times["train_s"] + t3 - t2, "train_load_average": times.get("load_average"),
        "control_period_s": float(env.dt), "horizon": learned.settings.horizon,
        "training": {k: training.get(k) for k in ("iterations", "stopped", "final_validation_loss", "wall_clock_s")},
        "learned": {"recovery": _recovery(env, learned, starts, seed_starts, latency),
                    "figure_eight": _figure_eight(env, learned, latency)},
        "unmodelled": verdict["unmodelled"], "recovery_duration_s": verdict["recovery_duration_s"],
    }
    if latency == "none" and relinearize_every is None:
        record["closed_form"] = {"recovery": verdict["recovery"], "figure_eight": verdict["figure_eight"]}
    else:
        closed = _controller(env, "closed-form", latency, relinearize_every=relinearize_every)
        record["closed_form"] = {"recovery": _recovery(env, closed, starts, seed_starts, latency),
                                 "figure_eight": _figure_eight(env, closed, latency)}
    env.close()
    return record


def run(args: argparse.Namespace) -> tuple[list[dict[str, Any]], dict[int, dict[str, Any]]]:
    cache = args.cache_dir / (args.latency + ("" if args.rti_relinearize_every is None else
                                 f"-relinearize{args.rti_relinearize_every}"))
    scenes_dir, work = args.cache_dir / "scenes", args.cache_dir / "work"
    work.mkdir(parents=True, exist_ok=True)
    cache.mkdir(parents=True, exist_ok=True)
    records, verdicts, trainings = [], {}, 0
    for seed in range(args.seed_offset, args.seed_offset + (args.max_draws or 3 * args.scenes)):
        if len(records) >= args.scenes:
            break
        (path,) = write_flyers([seed], scenes_dir)
        cached = args.cache_dir / f"filter_{seed}.json"
        if cached.exists():
            verdict = json.loads(cached.read_text())
        elif args.cached_only:
            continue
        else:
            verdict = filter_verdict(path, args.starts, args.seed)
            cached.write_text(json.dumps(verdict, indent=1) + "\n")
        verdicts[seed] = verdict
        print(f"flyer {seed}: filter {'in' if verdict['ok'] else 'out'}", file=sys.stderr)
        if not verdict["ok"]:
            continue
        done = cache / f"scene_{seed}.json"
        if done.exists():
            record = json.loads(done.read_text())
        elif args.cached_only:
            continue
        else:
            if not (work / f"flyer_{seed}_times.json").exists():
                if args.max_trainings is not None and trainings >= args.max_trainings:
                    break
                trainings += 1
            record = run_scene(seed, path, work, verdict, args.starts, args.seed, args.latency, args.train_time_limit,
                               args.rti_relinearize_every)
            done.write_text(json.dumps(record, indent=1) + "\n")
        learned = sum(r["recovered"] for r in record["learned"]["recovery"])
        print(f"flyer {seed}: learned {learned}/{args.starts}, figure-eight RMS "
              f"{record['learned']['figure_eight']['rms_position_m']:.4f} m vs "
              f"{record['closed_form']['figure_eight']['rms_position_m']:.4f} m", file=sys.stderr)
        records.append(record)
    return records, verdicts


def summarize(records: list[dict[str, Any]], verdicts: dict[int, dict[str, Any]]) -> dict[str, Any]:
    """The family's numbers against the issue's targets."""
    learned = [r["recovered"] for rec in records for r in rec["learned"]["recovery"]]
    closed = [r["recovered"] for rec in records for r in rec["closed_form"]["recovery"]]
    both = sum(a and b for rec in records for a, b in zip((r["recovered"] for r in rec["learned"]["recovery"]),
                                                           (r["recovered"] for r in rec["closed_form"]["recovery"])))
    ratios = [rec["learned"]["figure_eight"]["rms_position_m"] / rec["closed_form"]["figure_eight"]["rms_position_m"]
              for rec in records]
    rejected = [seed for seed, v in verdicts.items() if not v["ok"]]
    return {
        "scenes": len(records), "starts": len(learned), "recovered_learned": int(sum(learned)),
        "recovered_closed": int(sum(closed)),
        "learned_on_closed_recoveries": both / max(sum(closed), 1),
        "scenes_learned_at_least_4_of_5": sum(sum(r["recovered"] for r in rec["learned"]["recovery"]) >= 4
                                             for rec in records),
        "figure_eight_ratio_median": float(np.median(ratios)) if ratios else None,
        "figure_eight_ratio_worst": float(np.max(ratios)) if ratios else None,
        "pipeline_s_median": float(np.median([r["pipeline_s"] for r in records])) if records else None,
        "pipeline_s_max": float(np.max([r["pipeline_s"] for r in records])) if records else None,
        "figure_eight_within_1_5": sum(ratio <= 1.5 for ratio in ratios),
        "drag_scenes": sum(bool(rec["unmodelled"]) for rec in records),
        "drag_scenes_below_closed_form": sum(bool(rec["unmodelled"]) and ratio < 1.0
                                             for rec, ratio in zip(records, ratios)),
        "deadline_misses_learned": _misses(records, "learned"),
        "deadline_misses_closed": _misses(records, "closed_form"),
        "first_period_misses_learned": _first_period_misses(records, "learned"),
        "first_period_misses_closed": _first_period_misses(records, "closed_form"),
        "draws_filtered": len(verdicts), "draws_rejected": len(rejected),
        "rejection_rate": len(rejected) / len(verdicts) if verdicts else None,
    }


def _misses(records: list[dict[str, Any]], model: str) -> int | None:
    """Deadline misses of ``model`` over every flight of every scene; ``None`` in waiting mode (not measured)."""
    counts = [row.get("deadline_misses") for rec in records
              for row in [*rec[model]["recovery"], rec[model]["figure_eight"]]]
    return int(sum(counts)) if counts and all(isinstance(c, (int, float)) for c in counts) else None


def _first_period_misses(records: list[dict[str, Any]], model: str) -> int | None:
    """How many of ``model``'s deadline misses were a flight's cold first period (a robot runs the cold start
    before its clock starts); ``None`` in waiting mode or for flights cached before this was recorded."""
    flags = [row.get("first_period_missed") for rec in records
             for row in [*rec[model]["recovery"], rec[model]["figure_eight"]]]
    return int(sum(flags)) if flags and all(isinstance(f, bool) for f in flags) else None


def _misses_text(records: list[dict[str, Any]], model: str) -> str:
    """Deadline misses with, in brackets, how many were cold first periods (where recorded)."""
    misses, first = _misses(records, model), _first_period_misses(records, model)
    return "—" if misses is None else f"{misses}" + ("" if first is None else f" ({first})")


def _call_ms(flights: dict[str, Any]) -> float:
    """The median over a model's recovery flights of each flight's median controller call (ms, wall clock)."""
    return float(np.median([row["solve_time_ms"]["median"] for row in flights["recovery"]]))


def write_report(records: list[dict[str, Any]], verdicts: dict[int, dict[str, Any]], summary: dict[str, Any],
                 args: argparse.Namespace, command: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    args.out_dir.mkdir(parents=True, exist_ok=True)
    figure, axes = plt.subplots(1, 2, figsize=(11, 4))
    for i, rec in enumerate(records):
        learned, closed = rec["learned"]["figure_eight"], rec["closed_form"]["figure_eight"]
        axes[0].bar(i - 0.2, 1e3 * learned["rms_position_m"], width=0.4, color="tab:blue")
        axes[0].bar(i + 0.2, 1e3 * closed["rms_position_m"], width=0.4, color="tab:gray")
        axes[1].bar(i, rec["collect_s"], color="tab:gray")
        axes[1].bar(i, rec["train_s"], bottom=rec["collect_s"], color="tab:orange")
        axes[1].bar(i, rec["build_s"], bottom=rec["collect_s"] + rec["train_s"], color="tab:green")
    for ax in axes:
        ax.set_xticks(range(len(records)), [str(r["seed"]) for r in records])
        ax.set_xlabel("craft seed")
    axes[0].set_ylabel("figure-eight RMS (mm): learned blue, closed form grey")
    axes[1].set_ylabel("s (collect grey, train orange, build green)")
    axes[1].axhline(900.0, color="k", lw=0.5)
    figure.tight_layout()
    figure.savefig(args.out_dir / "flyer-family.png", dpi=90)
    plt.close(figure)

    s = summary
    fmt = lambda v, spec=".2f": "—" if v is None else format(v, spec)  # noqa: E731
    lines = [
        "# The free-flyer family through the whole pipeline", "",
        f"Produced by `{command}` (seeds from {args.seed_offset}; development used {DEVELOPMENT_SEEDS}).",
        f"Latency mode **{args.latency}**" + (": the simulator waits for the controller — model-quality figures, "
                                              "not real time; deadline misses are not measured." if args.latency
                                              == "none" else ": the controller's compute time is charged to the "
                                              "plant — real-time figures."),
        f"Timings are from the shared 2-core CPU machine with other jobs running (1-minute load average "
        f"{args.load_average:.1f} when the report was written): wall times are several times an idle machine's.", "",
        "Crafts are drawn by `fvin_mpc.envs.flyer_family` (its docstring gives the ranges), kept if the closed-form "
        "MPC recovers them from every start (in waiting mode), then `collect` (random-excitation bursts, the MJCF "
        "alone) → `train` (defaults, one torch thread) → the learned-model RTI MPC beside the closed-form one (`fly`'s "
        "settings: the control weights, the recovery episode's length and the figure-eight from the craft's own "
        "scales, docs/flyers.md).", "",
        "| scenes | starts recovered (learned / closed form) | learned on the closed form's recoveries | scenes with "
        "learned ≥ 4 of 5 | figure-eight RMS learned / closed form (median, worst) | collect + train + build s "
        "(median, max) | filter rejection |",
        "|---|---|---|---|---|---|---|",
        f"| {s['scenes']} | {s['recovered_learned']}/{s['starts']} / {s['recovered_closed']}/{s['starts']} | "
        f"{100 * s['learned_on_closed_recoveries']:.0f} % | {s['scenes_learned_at_least_4_of_5']}/{s['scenes']} | "
        f"{fmt(s['figure_eight_ratio_median'])}, {fmt(s['figure_eight_ratio_worst'])} | "
        f"{fmt(s['pipeline_s_median'], '.0f')}, {fmt(s['pipeline_s_max'], '.0f')} | "
        f"{s['draws_rejected']}/{s['draws_filtered']} |", "",
        "![flyer family](flyer-family.png)", "",
        f"Figure-eight within 1.5× the closed form's RMS on {s['figure_eight_within_1_5']}/{s['scenes']} scenes; "
        f"below it on {s['drag_scenes_below_closed_form']} of the {s['drag_scenes']} scenes with drag. Deadline misses "
        f"over all flights, learned / closed form: {_misses_text(records, 'learned')} / "
        f"{_misses_text(records, 'closed_form')}"
        + (" (not measured in waiting mode)." if s["deadline_misses_learned"] is None
           else " (in brackets: of them the flights' cold first periods, which a robot runs before its clock starts)."
           if s["first_period_misses_learned"] is not None else "."), "",
        "| seed | mass kg | actuation | rotors | drag | com off / arm | tilt ° | T/W | dt ms | period ms | "
        "recovery s | learned recovered | closed recovered | fig-8 RMS mm learned / closed | fig-8 size m, period s | "
        "call ms median learned / closed | misses learned / closed | collect / train / build s | training |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in records:
        f, le, cl = r["facts"], r["learned"], r["closed_form"]
        lines.append(
            f"| {r['seed']} | {f['mass_kg']:.3g} | {f['actuation']} | {f['rotors']} | "
            f"{'yes' if f['fluid_drag'] else 'no'} | {f['com_offset_arm_fraction']:.2f} | {f['max_tilt_deg']:.1f} | "
            f"{f['thrust_to_weight']:.2f} | "
            f"{1e3 * f['timestep_s']:.1f} | {1e3 * r['control_period_s']:.1f} | "
            f"{r.get('recovery_duration_s', 5.0):g} | "
            f"{sum(x['recovered'] for x in le['recovery'])}/{len(le['recovery'])} | "
            f"{sum(x['recovered'] for x in cl['recovery'])}/{len(cl['recovery'])} | "
            f"{1e3 * le['figure_eight']['rms_position_m']:.1f} / {1e3 * cl['figure_eight']['rms_position_m']:.1f} | "
            f"{2 * le['figure_eight']['amplitude_m']:.2g}, {le['figure_eight']['period_s']:.1f} | "
            f"{_call_ms(le):.1f} / {_call_ms(cl):.1f} | "
            f"{_misses_text([r], 'learned')} / {_misses_text([r], 'closed_form')} | "
            f"{r['collect_s']:.0f} / {r['train_s']:.0f} / {r['build_s']:.0f} | "
            f"{r['training'].get('iterations')} it, val {fmt(r['training'].get('final_validation_loss'), '.1e')} |")
    rejected = {seed: v for seed, v in verdicts.items() if not v["ok"]}
    if rejected:
        lines += ["", "Rejected by the filter (closed-form recoveries):", ""]
        lines += [f"* {seed}: " + (v.get("reason") or f"{sum(x['recovered'] for x in v['recovery'])}/"
                                   f"{len(v['recovery'])} starts recovered in {v['recovery_duration_s']:g} s; "
                                   f"T/W {v['thrust_to_weight']:.2f}, hover margin {100 * v['hover_margin']:.0f} % "
                                   f"of a range, yaw time {1e3 * v['yaw_time_s']:.0f} ms")
                  for seed, v in rejected.items()]
    path = args.out_dir / "flyer-family.md"
    path.write_text("\n".join(lines) + "\n")
    (args.out_dir / "flyer-family.json").write_text(json.dumps({"command": command, "summary": summary,
                                                                "records": records}, indent=1) + "\n")
    return path


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    records, verdicts = run(args)
    args.load_average = os.getloadavg()[0]
    summary = summarize(records, verdicts)
    command = "python -m benchmarks.flyer_report " + " ".join(shlex.quote(a) for a in argv)
    print(json.dumps(summary, indent=1))
    print(f"report: {write_report(records, verdicts, summary, args, command)}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
