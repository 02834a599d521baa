"""Closed-loop evaluation of the controllers over seeded episodes: ``python -m fvin_mpc.evaluate``.

The command line of :mod:`fvin_mpc.studies.evaluation`, whose docstring (the method) is this command's ``--help``.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path
from typing import Sequence

import fvin_mpc.studies.evaluation as evaluation_module
from fvin_mpc._cli import (
    add_backend_arguments,
    add_closed_loop_arguments,
    add_scene_arguments,
    backend_options,
    check_craft_period,
    check_output_file,
    check_output_folder,
    checked_scene_and_checkpoint,
    duration_s,
    exit_status,
    mpc_overrides,
    nonnegative_float,
    run_command,
    seed_value,
)
from fvin_mpc.core.checkpoint import checkpoint_exists
from fvin_mpc.envs.scenes import existing_scene
from fvin_mpc.studies.evaluation import (
    CONTROLLERS,
    DEFAULT_MAX_OMEGA,
    EvaluationConfig,
    evaluate,
    make_env,
    summary_table,
    write_report,
)
from fvin_mpc.studies.pool import TasksFailed
from fvin_mpc.studies.report import json_text

#: The files a report writes into ``--out-dir`` (a pivot's evaluation, a free body's flight report): replaced
#: only with ``--force``.
REPORT_FILES = ("evaluation.json", "evaluation.md", "time_to_upright.png", "phase_portraits.png", "quadrotor.json",
                "quadrotor.md", "recovery.png", "figure_eight.png")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.evaluate", description=evaluation_module.__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, newton_iters=False)
    parser.add_argument("--episodes", type=int, default=50, help="episodes per controller (default: %(default)s)")
    parser.add_argument(
        "--duration", type=duration_s, default=10.0, help="seconds per episode (default: %(default)s)"
    )
    parser.add_argument("--controllers", default=",".join(CONTROLLERS),
                        help="comma-separated subset of: %(default)s")
    parser.add_argument("--seed", type=seed_value, default=0,
                        help="base seed of the initial states (default: %(default)s)")
    parser.add_argument("--max-omega", type=nonnegative_float, default=DEFAULT_MAX_OMEGA,
                        help="largest |ω| of the random initial states, rad/s (default: %(default)s)")
    add_backend_arguments(parser)
    parser.add_argument("--out-dir", type=Path, default=Path("evaluation"),
                        help="where evaluation.{json,md} and the plots go (default: %(default)s; the study shipped in "
                             "docs/evaluation is rewritten only when named, with --force)")
    parser.add_argument("--force", action="store_true", help="replace the report files already in --out-dir")
    parser.add_argument("--json", type=Path, default=None, help="also write the JSON result here")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_closed_loop_arguments(parser)
    return parser


def _check_scene_and_checkpoint(config: EvaluationConfig) -> None:
    """The scene, and the checkpoint if a learned controller will run, before any episode: a missing
    default checkpoint is no error here (the learned controllers are skipped), a wrong one is."""

    learned = any(name.endswith("-learned") for name in config.controllers)
    explicit = config.checkpoint is not None
    if learned and (explicit or checkpoint_exists(existing_scene(config.scene).default_checkpoint)):
        checked_scene_and_checkpoint(config.scene, config.checkpoint, command="evaluate")
    else:
        checked_scene_and_checkpoint(config.scene, true_model=True, command="evaluate")


def _check_outputs(args: argparse.Namespace) -> Path | None:
    """``--out-dir`` and ``--json``, checked after the inputs and before any episode; the ``--json`` path."""
    check_output_folder(args.out_dir, "--out-dir", args.force, REPORT_FILES)
    return check_output_file(args.json, "--json")


def _evaluate_free_body(args: argparse.Namespace, argv: list[str]) -> int:
    """A free body's evaluation is fly's report (the study's docstring): both models where a checkpoint is."""
    import fvin_mpc.studies.flight_report as flight

    spec = existing_scene(args.scene)
    learned = args.checkpoint is not None or checkpoint_exists(spec.default_checkpoint)
    _, checkpoint = checked_scene_and_checkpoint(args.scene, args.checkpoint, true_model=not learned)
    check_craft_period(spec, checkpoint)
    _check_outputs(args)
    models = flight.MODELS if learned else ("closed-form",)
    results = flight.side_by_side(args.out_dir, argv, args.episodes, args.seed, args.latency, args.checkpoint,
                                  models=models, progress=not args.quiet, scene=args.scene,
                                  program="python -m fvin_mpc.evaluate")
    flight.print_rows([model["summary"] for model in results["models"].values()])
    print(f"wrote {args.out_dir / 'quadrotor.md'}", file=sys.stderr)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if not existing_scene(args.scene).goal_set.attitude_at_rest:
            return _evaluate_free_body(args, argv)
        config = EvaluationConfig(
            scene=args.scene, checkpoint=args.checkpoint, episodes=args.episodes, duration_s=args.duration,
            controllers=tuple(n.strip() for n in args.controllers.split(",") if n.strip()), seed=args.seed,
            max_omega=args.max_omega, control_period=args.control_period,
            mpc=tuple((name, value) for name, value in mpc_overrides(args).items() if value is not None),
            latency=args.latency)
        backend = backend_options(args)
        _check_scene_and_checkpoint(config)
        make_env(config).close()  # fails early on a scene the env cannot simulate
        json_path = _check_outputs(args)
        result = evaluate(config, workers=args.workers, progress=not args.quiet, **backend)
    except (ValueError, FileNotFoundError, TasksFailed) as error:
        return exit_status(error)
    if not result.summary:
        print("error: no controller applies to this scene", file=sys.stderr)
        return 2
    command = "python -m fvin_mpc.evaluate " + " ".join(shlex.quote(a) for a in argv)
    written = write_report(result, args.out_dir, command.strip())
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json_text(result.to_json(), indent=1) + "\n")
        written.append(json_path)
    print(summary_table(result))
    print("wrote " + ", ".join(str(p) for p in written), file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
