"""Random scene families through the whole pipeline: ``python -m benchmarks.scene_families``.

Per family (``--family hinge|ball``), seeds from ``--seed-offset`` on are drawn
(:mod:`fvin_mpc.envs.families`) and filtered: a draw enters the family only if the closed-form MPC
swings it up from hanging at rest (:func:`fvin_mpc.control.family_filter.feasible`, waiting mode, never
looking at a learned model). For each of the first ``--scenes`` members: collect → train →
evaluate, each with the defaults of ``python -m fvin_mpc.collect`` / ``python -m fvin_mpc.train`` /
``python -m fvin_mpc.swingup`` (library calls of the same commands; training on one torch thread),
then ``--starts`` episodes of the learned-model MPC beside the closed-form MPC from the same starts
(start 0 hanging at rest, the others seeded random orientations with |ω| ≤ 2 rad/s, as
``swingup --init random``), each for the swing-up command's duration for the scene
(:func:`fvin_mpc.control.family_filter.swingup_duration`) capped at ``--max-duration``.

Each finished scene is cached as JSON in ``--cache-dir`` (the filter's verdict per seed too), so a
stopped run resumes where it stopped. The report — per family: scenes and starts that succeed
(learned, closed form), learned cost over closed-form cost per start (median, worst), time per
controller call and deadline misses, and wall time of collect + train + build per scene — is
written to ``--out-dir`` as ``scene-families.md`` (with the command that produced it) and
``scene-families.png``.

By default both models are controlled by the real-time iteration (``--solver rti``) with
``--latency measured``: the controller's compute time is charged to the plant (the torque computed
from a state is applied that long after it, the previous torque until then), and a call longer than
the scene's control period is a deadline miss — the issue's targets. ``--latency none`` is the
waiting mode (the simulator waits for the controller: model-quality figures, not real time;
deadline misses are then "not measured"). ``--quick`` is the test suite's small version: no
feasibility filter (the first seeds are the members), 12 × 8 transitions, 2 training iterations,
horizon 5 without compiling, 0.3 s episodes, waiting mode.

Seeds: development used 0–11 and 1000–1011 (tests/test_families.py); the report's default
``--seed-offset`` is 9000 (5000–5019 and 7000–7023 were earlier reports, whose failures the defaults
and the model were changed for).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fvin_mpc import collect, train
from fvin_mpc._cli import add_relinearize_argument
from fvin_mpc.control.family_filter import feasible, run_judged, swingup_duration
from fvin_mpc.envs.families import write_family

DEFAULT_SEED_OFFSET = 9000
DEVELOPMENT_SEEDS = ("0–11, 1000–1011, 5000–5019 and 7000–7023 (earlier reports, read while changing the defaults "
                     "and the model); of the report seeds, hinge 9002 and 9008 and ball 9002, 9003 and 9012 failed "
                     "in earlier passes of this report and were diagnosed, so they are no longer unseen")
MAX_DURATION_S = 20.0
QUICK = {
    "collect": ["--trajectories", "12", "--steps", "8"],
    "train": ["--iterations", "2"],
    "mpc": {"horizon": 5, "compile": "none", "cold_starts": ("rollout+",)},
    "duration_s": 0.3,
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.scene_families",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--family", choices=("hinge", "ball"), default="hinge")
    parser.add_argument("--scenes", type=int, default=5, help="family members to run (default: %(default)s)")
    parser.add_argument("--starts", type=int, default=3, help="starts per scene (default: %(default)s)")
    parser.add_argument(
        "--seed-offset", type=int, default=DEFAULT_SEED_OFFSET, help="first seed drawn (default: %(default)s)"
    )
    parser.add_argument("--max-draws", type=int, default=None, help="stop after this many draws (default: 5 × scenes)")
    parser.add_argument(
        "--filter-draws",
        type=int,
        default=0,
        help="first run the filter on this many draws from --seed-offset (its rejection rate is reported)",
    )
    parser.add_argument(
        "--max-duration",
        type=float,
        default=MAX_DURATION_S,
        help="longest evaluation episode, s (default: %(default)s)",
    )
    parser.add_argument(
        "--max-horizon",
        type=int,
        default=None,
        help="skip members whose closed-form MPC horizon (steps) exceeds this; the report lists them",
    )
    parser.add_argument(
        "--latency",
        default=None,
        help="measured (default: compute time charged to the plant) | none (waiting mode; --quick's default)",
    )
    parser.add_argument(
        "--solver",
        choices=("rti", "ipopt"),
        default="rti",
        help="the MPC of both models, learned and closed form (default: %(default)s)",
    )
    add_relinearize_argument(parser)  # its own cache
    parser.add_argument(
        "--out-dir", type=Path, default=None,
        help="where the report goes (default: docs/scene-families-FAMILY; docs/scene-families.md is the hand-written "
        "overview)"
    )
    parser.add_argument("--cache-dir", type=Path, default=Path("build/families-cache"), help="default: %(default)s")
    parser.add_argument("--quick", action="store_true", help="the small version for the test suite (see above)")
    parser.add_argument("--no-report", action="store_true", help="run and cache, write no report")
    return parser


# ----------------------------------------------------------------------------- one scene
def run_episodes(env: Any, controller: Any, starts: list[dict | None], duration: float, latency: Any) -> list[dict]:

    results = []
    for index, options in enumerate(starts):
        episode, metrics = run_judged(env, controller, duration, options, latency=latency, seed=index)
        times = 1e3 * episode.controller_time_s[np.isfinite(episode.controller_time_s)]
        results.append(
            {
                "start": index,
                "swung_up": bool(metrics["swung_up"]),
                "time_to_upright_s": metrics["time_to_upright_s"],
                "hold_error_rad": metrics["hold_error_rad"],
                "cost": metrics["accumulated_cost"],
                "call_ms_median": float(np.median(times)),
                "call_ms_p99": float(np.percentile(times, 99)),
                "call_ms_max": float(times.max()),
                "deadline_misses": metrics["deadline_misses"],
                "controller_failures": metrics["controller_failures"],
                "judged_on": metrics["judged_on"],
            }
        )
    return results


def report_starts(env: Any, count: int, seed: int) -> list[dict | None]:
    """Start 0 hanging at rest; the others as ``swingup --init random`` (uniform orientation, |ω| ≤ 2)."""
    base = env.unwrapped
    starts: list[dict | None] = [None]
    for k in range(1, count):
        base.reset(seed=seed * 1000 + k, options={"random": True, "max_omega": 2.0})
        starts.append({"qpos": base.data.qpos.copy(), "qvel": base.data.qvel.copy()})
    return starts


def run_scene(
    kind: str,
    seed: int,
    scene_path: Path,
    work: Path,
    starts: int,
    quick: bool,
    latency: Any,
    max_duration: float,
    solver: str = "rti",
    relinearize_every: int | None = None,
) -> dict[str, Any]:
    """Collect → train → build → evaluate one scene; the record cached for it."""
    import contextlib
    import io

    import torch

    from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings

    torch.set_num_threads(1)
    data, stem = work / f"{kind}_{seed}.npz", work / f"{kind}_{seed}_model"
    record: dict[str, Any] = {
        "family": kind,
        "seed": seed,
        "scene": str(scene_path),
        "latency": latency,
        "solver": solver,
        "quick": quick,
    }
    record["facts"] = json.loads(scene_path.with_suffix(".json").read_text())
    quiet = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(quiet):
        collect.main(["--scene", str(scene_path), "--out", str(data), "--quiet", *(QUICK["collect"] if quick else [])])
    t1 = time.perf_counter()
    with contextlib.redirect_stdout(quiet):
        train.main(
            ["--data", str(data), "--out", str(stem), "--quiet", "--threads", "1", *(QUICK["train"] if quick else [])]
        )
    t2 = time.perf_counter()
    overrides: dict[str, Any] = {**(QUICK["mpc"] if quick else {}), "solver": solver}
    if relinearize_every is not None:
        overrides["rti"] = {"relinearize_every": relinearize_every}
    env = scene_env(str(scene_path), checkpoint=str(stem))
    learned_model = scene_model(env, str(stem))
    learned = scene_mpc(env, learned_model, scene_mpc_settings(env, **overrides))
    t3 = time.perf_counter()
    true_env = scene_env(str(scene_path), true_model=True)
    closed = scene_mpc(true_env, scene_model(true_env, true_model=True), scene_mpc_settings(true_env, **overrides))
    duration = QUICK["duration_s"] if quick else min(swingup_duration(env), max_duration)
    start_list = report_starts(env, starts, seed)
    record.update(
        collect_s=t1 - t0,
        train_s=t2 - t1,
        build_s=t3 - t2,
        pipeline_s=t3 - t0,
        duration_s=duration,
        control_period_s=float(env.unwrapped.dt),
        horizon=learned.settings.horizon,
        training=json.loads(Path(f"{stem}.json").read_text()).get("training", {})
        if Path(f"{stem}.json").exists()
        else {},
        learned=run_episodes(env, learned, start_list, duration, latency),
        closed_form=run_episodes(true_env, closed, start_list, duration, latency),
    )
    record["training"] = {
        k: record["training"].get(k)
        for k in ("iterations", "stopped", "final_validation_loss", "wall_clock_s", "selected")
    }
    env.close()
    true_env.close()
    return record


# ----------------------------------------------------------------------------- the family run
def mode_name(args: argparse.Namespace) -> str:
    """The cache folder of a mode: the verdicts and records depend on the solver, the latency and the kept
    Jacobians they were run with."""
    kept = "" if args.rti_relinearize_every is None else f"-relinearize{args.rti_relinearize_every}"
    return f"{args.solver}-{args.latency}{kept}"


def run(args: argparse.Namespace) -> list[dict[str, Any]]:

    # The verdicts and records depend on the mode they were run in: one cache per solver and latency.
    cache = args.cache_dir / args.family / ("quick" if args.quick else "full") / mode_name(args)
    scenes_dir, work = cache / "scenes", cache / "work"
    work.mkdir(parents=True, exist_ok=True)
    max_draws = args.max_draws or 5 * args.scenes
    records: list[dict[str, Any]] = []
    filter_facts: dict[int, dict[str, Any]] = {}
    skipped: list[tuple[int, int]] = []
    args.skipped = skipped

    def verdict_of(seed: int, path: Path) -> dict[str, Any]:
        verdict = args.cache_dir / args.family / f"filter_{seed}.json"
        if verdict.exists():
            facts = json.loads(verdict.read_text())
        else:
            _, facts = feasible(path)
            verdict.write_text(json.dumps(facts, indent=2) + "\n")
        filter_facts[seed] = facts
        print(
            f"{args.family} {seed}: filter {'in' if facts['ok'] else 'out'} ({facts.get('wall_s', 0):.0f} s)",
            file=sys.stderr,
        )
        return facts

    if not args.quick:
        for seed in range(args.seed_offset, args.seed_offset + args.filter_draws):
            (path,) = write_family(args.family, [seed], scenes_dir)
            verdict_of(seed, path)
    for seed in range(args.seed_offset, args.seed_offset + max_draws):
        if len(records) >= args.scenes:
            break
        (path,) = write_family(args.family, [seed], scenes_dir)
        if not args.quick and not verdict_of(seed, path)["ok"]:
            continue
        horizon = filter_facts.get(seed, {}).get("horizon")
        if args.max_horizon is not None and horizon is not None and horizon > args.max_horizon:
            skipped.append((seed, horizon))
            print(
                f"{args.family} {seed}: skipped, horizon {horizon} > --max-horizon {args.max_horizon}", file=sys.stderr
            )
            continue
        done = cache / f"scene_{seed}.json"
        if done.exists():
            record = json.loads(done.read_text())
        else:
            record = run_scene(
                args.family, seed, path, work, args.starts, args.quick, args.latency, args.max_duration, args.solver,
                args.rti_relinearize_every,
            )
            done.write_text(json.dumps(record, indent=2) + "\n")
        print(
            f"{args.family} {seed}: learned {sum(e['swung_up'] for e in record['learned'])}/{len(record['learned'])}, "
            f"closed form {sum(e['swung_up'] for e in record['closed_form'])}/{len(record['closed_form'])}",
            file=sys.stderr,
        )
        records.append(record)
    args.filter_facts = filter_facts
    return records


def summarize(records: list[dict[str, Any]], filter_facts: dict[int, dict[str, Any]] | None = None) -> dict[str, Any]:
    """The report's numbers for one family."""
    filter_verdicts = {seed: bool(facts["ok"]) for seed, facts in (filter_facts or {}).items()}
    learned = [e for r in records for e in r["learned"]]
    closed = [e for r in records for e in r["closed_form"]]
    ratios = [a["cost"] / b["cost"] for r in records for a, b in zip(r["learned"], r["closed_form"]) if b["cost"] > 0]
    calls = lambda eps, key: [e[key] for e in eps]  # noqa: E731
    misses = lambda eps: sum(e["deadline_misses"] for e in eps if isinstance(e["deadline_misses"], int))  # noqa: E731
    rejected = [s for s, ok in (filter_verdicts or {}).items() if not ok]
    # The issue's targets count the learned model on the starts the closed form swings up.
    both = [(a["swung_up"], b["swung_up"]) for r in records for a, b in zip(r["learned"], r["closed_form"])]
    closed_up = sum(b for _, b in both)
    learned_where_closed = sum(a and b for a, b in both)

    def scene_share(record: dict[str, Any]) -> float:
        pairs = [(a["swung_up"], b["swung_up"]) for a, b in zip(record["learned"], record["closed_form"])]
        wins = sum(b for _, b in pairs)
        return sum(a and b for a, b in pairs) / wins if wins else float("nan")

    shares = [scene_share(r) for r in records]
    return {
        "scenes": len(records),
        "scenes_all_starts_learned": sum(all(e["swung_up"] for e in r["learned"]) for r in records),
        "scenes_all_starts_closed": sum(all(e["swung_up"] for e in r["closed_form"]) for r in records),
        "starts": len(learned),
        "starts_learned": sum(e["swung_up"] for e in learned),
        "starts_closed": sum(e["swung_up"] for e in closed),
        "cost_ratio_median": float(np.median(ratios)) if ratios else None,
        "cost_ratio_worst": float(np.max(ratios)) if ratios else None,
        "call_ms_median_learned": float(np.median(calls(learned, "call_ms_median"))) if learned else None,
        "call_ms_p99_learned": float(np.max(calls(learned, "call_ms_p99"))) if learned else None,
        "call_ms_median_closed": float(np.median(calls(closed, "call_ms_median"))) if closed else None,
        "call_ms_p99_closed": float(np.max(calls(closed, "call_ms_p99"))) if closed else None,
        "deadline_misses_learned": misses(learned) if records and records[0]["latency"] != "none" else "not measured",
        "deadline_misses_closed": misses(closed) if records and records[0]["latency"] != "none" else "not measured",
        "pipeline_s_median": float(np.median([r["pipeline_s"] for r in records])) if records else None,
        "pipeline_s_max": float(np.max([r["pipeline_s"] for r in records])) if records else None,
        "starts_learned_where_closed": learned_where_closed,
        "starts_closed_up": closed_up,
        "learned_share_where_closed": learned_where_closed / closed_up if closed_up else None,
        "scenes_below_four_of_five": [r["seed"] for r, share in zip(records, shares) if share < 0.8],
        "draws_filtered": len(filter_verdicts or {}),
        "draws_rejected": len(rejected),
        "rejection_rate": len(rejected) / len(filter_verdicts) if filter_verdicts else None,
    }


def predictors_of_control(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Across scenes: Spearman's rank correlation of the selected iteration's swing measure and of its
    validation loss with the scene's closed-loop outcome — the median learned / closed-form cost ratio
    and the share of the closed form's successes the learned model missed (higher is worse for all
    four). ``None`` where fewer than 4 scenes have both numbers or one side is constant."""
    from scipy.stats import spearmanr

    rows = []
    for record in records:
        selected = (record.get("training") or {}).get("selected") or {}
        ratios = [a["cost"] / b["cost"] for a, b in zip(record["learned"], record["closed_form"]) if b["cost"] > 0]
        wins = [(a["swung_up"], b["swung_up"]) for a, b in zip(record["learned"], record["closed_form"])]
        closed_up = sum(b for _, b in wins)
        if "measure" not in selected or not ratios or not closed_up:
            continue
        missed = 1.0 - sum(a and b for a, b in wins) / closed_up
        rows.append((selected["measure"], selected["validation"], float(np.median(ratios)), missed))
    result: dict[str, Any] = {"scenes": len(rows)}
    values = np.array(rows, dtype=float).reshape(len(rows), 4)
    for column, name in ((0, "swing_measure"), (1, "validation_loss")):
        for target, outcome in ((2, "cost_ratio"), (3, "missed_share")):
            x, y = values[:, column], values[:, target]
            usable = len(rows) >= 4 and np.ptp(x) > 0 and np.ptp(y) > 0
            result[f"{name}_vs_{outcome}"] = float(spearmanr(x, y)[0]) if usable else None
    return result


#: The issue's wall-time target per scene for collect + train + build (s).
PIPELINE_TARGET_S = {"hinge": 90.0, "ball": 300.0}


def _targets(s: dict[str, Any], args: argparse.Namespace) -> list[str]:
    """The issue's targets, each with this run's figure and whether it is met."""
    def verdict(ok: bool | None) -> str:
        return "not measured" if ok is None else ("met" if ok else "**not met**")

    share = s["learned_share_where_closed"]
    misses = s["deadline_misses_learned"]
    limit = PIPELINE_TARGET_S[args.family]
    return [
        "Targets (the issue's; this run's figures):",
        "",
        f"* learned succeeds on ≥ 95 % of the starts the closed form swings up: "
        f"{s['starts_learned_where_closed']}/{s['starts_closed_up']}"
        f" ({'—' if share is None else f'{100 * share:.0f} %'}) — {verdict(None if share is None else share >= 0.95)};",
        "* every scene on at least 4 of 5 such starts: "
        + (", ".join(map(str, s["scenes_below_four_of_five"])) + " below" if s["scenes_below_four_of_five"] else "all")
        + f" — {verdict(not s['scenes_below_four_of_five'])};",
        "* learned / closed-form cost per start ≤ 1.10 at the median: "
        + ("—" if s["cost_ratio_median"] is None else f"{s['cost_ratio_median']:.2f}")
        + f" — {verdict(None if s['cost_ratio_median'] is None else s['cost_ratio_median'] <= 1.10)};",
        f"* zero deadline misses at each scene's control period: learned {misses}, closed form "
        f"{s['deadline_misses_closed']} — {verdict(None if isinstance(misses, str) else misses == 0)};",
        f"* collect + train + build ≤ {limit:.0f} s per scene: at most "
        + ("—" if s["pipeline_s_max"] is None else f"{s['pipeline_s_max']:.0f} s")
        + f" — {verdict(None if s['pipeline_s_max'] is None else s['pipeline_s_max'] <= limit)} "
        "(on the loaded machine, not the idle one the target names).",
    ]


def write_report(
    records: list[dict[str, Any]], summary: dict[str, Any], args: argparse.Namespace, command: str
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    args.out_dir.mkdir(parents=True, exist_ok=True)
    figure, axes = plt.subplots(1, 2, figsize=(11, 4))
    for i, record in enumerate(records):
        for a, b in zip(record["learned"], record["closed_form"]):
            ratio = a["cost"] / b["cost"] if b["cost"] > 0 else np.nan
            axes[0].scatter(
                i, ratio, marker="o" if a["swung_up"] else "x", color="tab:blue" if b["swung_up"] else "tab:red"
            )
        axes[1].bar(i, record["collect_s"], color="tab:gray")
        axes[1].bar(i, record["train_s"], bottom=record["collect_s"], color="tab:orange")
        axes[1].bar(i, record["build_s"], bottom=record["collect_s"] + record["train_s"], color="tab:green")
    labels = [str(r["seed"]) for r in records]
    for ax in axes:
        ax.set_xticks(range(len(records)), labels)
        ax.set_xlabel("scene seed")
    axes[0].axhline(1.0, color="k", lw=0.5)
    axes[0].set_yscale("log")
    axes[0].set_ylabel("learned cost / closed-form cost per start")
    axes[0].set_title("o learned swung up, x not; red: closed form did not")
    axes[1].set_ylabel("s (collect grey, train orange, build green)")
    axes[1].set_title("wall time per scene")
    figure.tight_layout()
    png = args.out_dir / "scene-families.png"
    figure.savefig(png, dpi=90)
    plt.close(figure)

    s = summary
    fmt = lambda v, spec=".2f": "—" if v is None else (v if isinstance(v, str) else format(v, spec))  # noqa: E731
    lines = [
        f"# Random scene families: the {args.family} family through the whole pipeline",
        "",
        f"Produced by `{command}` (seeds from {args.seed_offset}; development used seeds {DEVELOPMENT_SEEDS}).",
        f"Latency mode **{args.latency}**"
        + (
            ": the simulator waits for the controller — model-quality figures, not real "
            "time; deadline misses are not measured."
            if args.latency == "none"
            else ": the controller's compute time is charged to the plant (a torque is applied that long after "
            "the state it was computed from), and a call longer than the scene's control period is a deadline miss."
        ),
        "Timings are from the shared 2-core CPU machine (other jobs running).",
        "",
        "The scenes are drawn by `fvin_mpc.envs.families` (its docstring gives the ranges: mass 0.1–5 kg as a point "
        "mass, rod or composite with rigid child bodies; centre of mass 0.1–1.5 m from the pivot; hinge axis ≥ 30° "
        "from gravity; upright at any `qpos`; damping ratio 0–0.5; optional armature; torque bound 0.15–1.5× the "
        "largest gravity torque; timestep 1–20 ms; gravity 1.6–9.81 m/s²), filtered by the closed-form MPC (below), "
        "then each member goes through `collect` → `train` (defaults, one torch thread) → the learned-model MPC "
        f"beside the closed-form MPC (the scene's default settings, solver {args.solver}"
        + ("" if args.rti_relinearize_every is None else f", relinearize_every {args.rti_relinearize_every}")
        + ") from the same starts. "
        "Cost is the env's "
        "accumulated quadratic cost over the same episode; success is the evaluation's criterion (upright within "
        "0.1 rad from some time on, held within 0.05 rad over the last 3 s).",
        "",
        "| family | scenes | scenes all starts up (learned / closed form) | starts up (learned / closed form) | "
        "learned / closed-form cost per start (median, worst) | call ms median / worst p99 (learned; closed form) | "
        "deadline misses | collect + train + build s (median, max) | filter rejection |",
        "|---|---|---|---|---|---|---|---|---|",
        f"| {args.family} | {s['scenes']} | {s['scenes_all_starts_learned']} / {s['scenes_all_starts_closed']} | "
        f"{s['starts_learned']}/{s['starts']} / {s['starts_closed']}/{s['starts']} | "
        f"{fmt(s['cost_ratio_median'])}, {fmt(s['cost_ratio_worst'])} | "
        f"{fmt(s['call_ms_median_learned'], '.1f')} / {fmt(s['call_ms_p99_learned'], '.1f')}; "
        f"{fmt(s['call_ms_median_closed'], '.1f')} / {fmt(s['call_ms_p99_closed'], '.1f')} | "
        f"{s['deadline_misses_learned']} | {fmt(s['pipeline_s_median'], '.0f')}, {fmt(s['pipeline_s_max'], '.0f')} | "
        f"{s['draws_rejected']}/{s['draws_filtered']} |",
        "",
        *_targets(s, args),
        "",
        "Per scene (start 0 hangs at rest; the others are seeded random orientations, |ω| ≤ 2 rad/s):",
        "",
        "| seed | kind | mass kg | com m | axis from gravity ° | ζ | armature | torque bound / gravity torque | dt ms | "  # noqa: E501 (a table row / MJCF written as it reads)
        "integrator | learned up | closed form up | cost ratio per start | episode s | collect / train / build s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in records:
        f = r["facts"]
        ratios = ", ".join(
            fmt(a["cost"] / b["cost"]) if b["cost"] > 0 else "—" for a, b in zip(r["learned"], r["closed_form"])
        )
        lines.append(
            f"| {r['seed']} | {f['kind']} | {f['mass_kg']:.2f} | {f['com_distance_m']:.2f} | "
            f"{fmt(f.get('axis_from_gravity_deg'), '.0f')} | {f['damping_ratio']:.2f} | {f['armature']:.3g} | "
            f"{f['torque_bound_ratio']:.2f} | {1e3 * f['timestep_s']:.1f} | {f['integrator']} | "
            f"{sum(e['swung_up'] for e in r['learned'])}/{len(r['learned'])} | "
            f"{sum(e['swung_up'] for e in r['closed_form'])}/{len(r['closed_form'])} | {ratios} | {r['duration_s']:.1f} | "  # noqa: E501 (a table row / MJCF written as it reads)
            f"{r['collect_s']:.0f} / {r['train_s']:.0f} / {r['build_s']:.0f} |"
        )
    if getattr(args, "skipped", None):
        lines += [
            "",
            "Members skipped by `--max-horizon` (their learned-model IPOPT calls would take too long for this run): "
            + ", ".join(f"{seed} (horizon {horizon})" for seed, horizon in args.skipped)
            + ".",
        ]
    lines += ["", f"![cost ratio and wall time per scene]({png.name})", ""]
    predictors = predictors_of_control(records)
    rho = lambda key: fmt(predictors[key], "+.2f")  # noqa: E731
    lines += [
        "## What predicts control: the swing measure or the validation loss",
        "",
        f"Spearman's rank correlation across the {predictors['scenes']} scenes whose training recorded a swing "
        "measure (`train --select measure`, the default; the selected iteration's measure and validation loss) with "
        "the scene's median learned / closed-form cost ratio and with the share of the closed form's successes the "
        "learned model missed. Positive: a worse number goes with a worse outcome.",
        "",
        "| predictor | vs cost ratio | vs missed share |",
        "|---|---|---|",
        f"| swing measure (energy error over a full-torque swing) | {rho('swing_measure_vs_cost_ratio')} | "
        f"{rho('swing_measure_vs_missed_share')} |",
        f"| validation loss | {rho('validation_loss_vs_cost_ratio')} | {rho('validation_loss_vs_missed_share')} |",
        "",
    ]
    if args.filter_facts:
        lines += [
            "## The feasibility filter",
            "",
            "Each draw is run with the closed-form MPC (`python -m fvin_mpc.swingup --scene PATH --true-model`'s "
            "controller, through the library) from hanging at rest, waiting mode, for the swing-up command's "
            "duration for the scene (the motor's torque counted through its gear), at most "
            "40 s, stopped early once held within 0.05 rad for 3 s; it enters the family if it is upright within "
            "0.1 rad and held within 0.05 rad over the last 3 s. It never looks at a learned model.",
            "",
            f"Rejected {s['draws_rejected']} of {s['draws_filtered']} draws "
            f"({fmt(100 * s['rejection_rate'] if s['rejection_rate'] is not None else None, '.0f')} %).",
            "",
            "| seed | kind | mass kg | com m | axis from gravity ° | ζ | torque bound / gravity torque | dt ms | integrator | "  # noqa: E501 (a table row / MJCF written as it reads)
            "in | upright at s | hold error rad | horizon | solve ms median | simulated s | wall s |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for seed in sorted(args.filter_facts):
            v = args.filter_facts[seed]
            mode = mode_name(args)
            scene_facts = args.cache_dir / args.family / "full" / mode / "scenes" / f"{args.family}_{seed}.json"
            f = json.loads(scene_facts.read_text())
            lines.append(
                f"| {seed} | {f['kind']} | {f['mass_kg']:.2f} | {f['com_distance_m']:.2f} | "
                f"{fmt(f.get('axis_from_gravity_deg'), '.0f')} | {f['damping_ratio']:.2f} | {f['torque_bound_ratio']:.2f} | "  # noqa: E501 (a table row / MJCF written as it reads)
                f"{1e3 * f['timestep_s']:.1f} | {f['integrator']} | {'yes' if v['ok'] else 'no'} | "
                f"{fmt(v.get('time_to_upright_s'))} | {fmt(v.get('hold_error_rad'), '.3f')} | {v.get('horizon', '—')} | "  # noqa: E501 (a table row / MJCF written as it reads)
                f"{fmt(v.get('solve_time_ms_median'), '.0f')} | {fmt(v.get('simulated_s'), '.1f')} | {fmt(v.get('wall_s'), '.0f')} |"  # noqa: E501 (a table row / MJCF written as it reads)
            )
        lines.append("")
    (args.out_dir / "scene-families.md").write_text("\n".join(lines))


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.latency is None:
        args.latency = "none" if args.quick else "measured"
    if args.rti_relinearize_every is not None and args.solver != "rti":
        raise ValueError("--rti-relinearize-every needs the real-time iteration (--solver rti)")
    latency: Any = args.latency if args.latency in ("none", "measured") else float(args.latency)
    args.latency = latency
    args.out_dir = args.out_dir or Path("docs") / f"scene-families-{args.family}"
    records = run(args)
    summary = summarize(records, args.filter_facts)
    print(json.dumps(summary, indent=2))
    if not args.no_report:
        command = "python -m benchmarks.scene_families " + " ".join(
            shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:])
        )
        write_report(records, summary, args, command)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
