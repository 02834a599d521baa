"""Learning in the loop on several scenes: ``python -m benchmarks.loop_efficiency``.

Runs :func:`fvin_mpc.studies.learning_loop.run_loop` (``python -m fvin_mpc.learn``'s defaults) on
each scene given — MJCF paths or built-in names (``--scene``, repeatable) and members of a random
family (``--family hinge --seeds 9002 9003``, written by :mod:`fvin_mpc.envs.families`) — caching each
finished scene's ``learn.json`` under ``--cache-dir`` so that a stopped run resumes and one scene per
command fits a time limit. Then writes ``--out-dir``/``learning-loop-runs.{md,json}`` (one row per
scene: closed form up on the evaluation starts, outcome, training transitions to success, rounds,
evaluation steps not trained on, learned over closed-form cost, wall time) and
``learning-loop-runs.png`` (learned starts up against training transitions, one line per scene).

Closed loops run in waiting mode (the simulator waits for the controller): model-quality figures.
Seeds: the family report's seeds start at 9000 (benchmarks/scene_families.py; 5000–5019 and 7000–7023
were earlier reports); development of the loop used the weak damped pendulum of ``tests/data`` and no
family seed.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from functools import partial
from pathlib import Path
from typing import Any, Sequence

from fvin_mpc.envs.families import write_family
from fvin_mpc.envs.flyer_family import write_flyers
from fvin_mpc.studies.learning_loop import LoopSettings, run_loop, write_loop_report
from fvin_mpc.studies.report import markdown_table, write_report


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.loop_efficiency", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", action="append", default=[], help="MJCF path or built-in name (repeatable)")
    parser.add_argument("--family", choices=("hinge", "ball", "flyer"), default=None,
                        help="add members of this family (flyer: envs/flyer_family.py's crafts)")
    parser.add_argument("--seeds", type=int, nargs="*", default=[], help="the family members' seeds")
    parser.add_argument("--seed", type=int, default=0, help="the loop's seed (default: %(default)s)")
    parser.add_argument("--cache-dir", type=Path, default=Path("build/learning-loop"), help="default: %(default)s")
    parser.add_argument("--out-dir", type=Path, default=Path("docs"), help="default: %(default)s")
    parser.add_argument("--no-run", action="store_true", help="report the cached scenes only")
    return parser


def scenes(args: argparse.Namespace) -> list[tuple[str, str]]:
    """``(name, scene)`` pairs: the given scenes, then the family members written into the cache."""
    chosen = [(Path(scene).stem, scene) for scene in args.scene]
    if args.family is not None:
        write = write_flyers if args.family == "flyer" else partial(write_family, args.family)
        for path in write(args.seeds, args.cache_dir / "scenes"):
            chosen.append((path.stem, str(path)))
    return chosen


def row(name: str, result: dict[str, Any]) -> dict[str, Any]:
    """One scene's line. ``transitions to success``: the first round that succeeds wherever the closed form does
    (a record from before the cost stop ended at that round);
    ``to stop``: the round that also met the cost tolerance (a record from before the tolerance was a default
    stopped at success). The learned figures are the final checkpoint's round."""
    closed = result["closed_form"]
    kept = result["rounds"][result.get("final_round", -1)]
    tolerance = result["settings"].get("cost_tolerance")
    return {
        "scene": name,
        "closed form up": f"{closed['closed_up']}/{closed['starts']}",
        "outcome": result["outcome"],
        "transitions to success": result["transitions_to_success"] or "—",
        "cost tolerance": tolerance or "—",
        "transitions to stop": result.get("transitions_to_stop", result["transitions_to_success"]) or "—",
        "stopped by": stop_reason(result),
        "training transitions": result["training_transitions"],
        "rounds": len(result["rounds"]),
        "final round": kept["round"],
        "learned up (final)": f"{kept['learned_up']}/{kept['starts']}",
        "cost learned / closed form (sum)": kept["cost_learned"] / kept["cost_closed"],
        "median cost ratio per start": kept["cost_ratio_median"] if kept["cost_ratio_median"] is not None else "—",
        "evaluation steps (not trained on)": result["evaluation_transitions"],
        "wall s": result["wall_s"],
    }


def stop_reason(result: dict[str, Any]) -> str:
    """Why the loop ended: the cost within the tolerance, the cost no longer falling, or success alone (a
    record from before the cost rules), else its outcome."""
    last = result["rounds"][-1]
    if result["outcome"] != "success":
        return result["outcome"]
    if "within_cost" not in last:
        return "success"
    return "cost within tolerance" if last["within_cost"] else "cost plateau"


def plot(results: dict[str, dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(11, 4))
    for i, (name, result) in enumerate(results.items()):
        rounds = result["rounds"]
        x = [r["transitions"] for r in rounds]
        axes[0].plot(x, [r["learned_up"] / r["starts"] for r in rounds], "o-", color=f"C{i}", label=name)
        axes[0].axhline(result["closed_form"]["closed_up"] / rounds[0]["starts"], color=f"C{i}", ls=":", lw=1)
        axes[1].plot(x, [r["cost_learned"] / r["cost_closed"] for r in rounds], "o-", color=f"C{i}", label=name)
    axes[0].set_ylabel("starts swung up (share)")
    axes[0].set_title("dotted: closed form", fontsize=9)
    axes[1].set_ylabel("learned / closed-form cost (sum)")
    axes[1].axhline(1.0, color="k", lw=0.8)
    axes[1].set_yscale("log")
    for ax in axes:
        ax.set_xlabel("training transitions from the plant")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=90)
    plt.close(figure)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    results: dict[str, dict[str, Any]] = {}
    for name, scene in scenes(args):
        work = args.cache_dir / f"{name}_seed{args.seed}"
        record = work / "learn.json"
        if not record.exists():
            if args.no_run:
                continue
            result = run_loop(scene, LoopSettings(seed=args.seed), work,
                              log=lambda message: print(message, file=sys.stderr))
            write_loop_report(result, work, f"python -m fvin_mpc.learn --scene {scene} --seed {args.seed}")
        results[name] = json.loads(record.read_text())
        print(f"{name}: {results[name]['outcome']} at {results[name]['training_transitions']} transitions",
              file=sys.stderr)
    if not results:
        return 0
    command = "python -m benchmarks.loop_efficiency " + " ".join(
        shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    args.out_dir.mkdir(parents=True, exist_ok=True)
    plot(results, args.out_dir / "learning-loop-runs.png")
    rows = [row(name, result) for name, result in results.items()]
    body = ("Waiting mode (the simulator waits for the controller): model quality, not real time. The machine "
            "was shared (2 cores, other jobs running): wall times are loaded-machine figures.\n\n"
            + markdown_table(rows, list(rows[0])) + "\n\n![success and cost against transitions]"
            "(learning-loop-runs.png)\n")
    write_report(args.out_dir / "learning-loop-runs", "Learning in the loop: the runs",
                 {"scenes": {name: {k: v for k, v in r.items() if k != "rounds"} | {"rounds": [
                     {k: v for k, v in x.items() if k != "learned"} for x in r["rounds"]]}
                     for name, r in results.items()}}, body, command)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
