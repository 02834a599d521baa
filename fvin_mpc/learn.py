"""Learn a scene's model in the loop: ``python -m fvin_mpc.learn --scene X.xml``.

Starts from a small excitation batch (the default collector of ``python -m fvin_mpc.collect``, the
swing excitation; ``--excitation random`` for random torques), trains the
scene's default model (``python -m fvin_mpc.train``'s defaults), then repeats: run the scene's task
with the learned MPC on fixed evaluation starts (never trained on) beside the closed-form MPC
(computed once); stop once the learned controller swings up from every start the closed form swings
up from at no more than ``--cost-tolerance`` (1.05) times its summed cost (or, once it does, when a round
no longer lowers that cost by ``--min-cost-gain``, 2 %), or when the transition budget is spent; else run
the learned MPC with exploration noise on
the plant from fresh starts, add those transitions and retrain from the previous weights.

A free body (``--scene`` a craft on a free joint) runs ``fly``'s task: the first batch is ``collect``'s
random-excitation bursts from the MJCF alone, the evaluation is recovery to hover from ``fly``'s starts
beside the closed form, and exploration flies the learned MPC with noise from random tumbling starts.

Every plant transition gathered for training counts (excitation and exploration); evaluation
episodes are reported separately and never trained on. Closed loops run in waiting mode (the
simulator waits for the controller: model-quality figures, not real time).

Writes to ``--out-dir`` (default ``learn/<scene>``): ``data.npz`` (exactly the transitions counted),
``round_<k>`` checkpoints, ``final`` (the best round's — successful, then the most starts up, then the
lowest cost — as an ordinary checkpoint: ``python -m fvin_mpc.swingup --scene X.xml
--checkpoint learn/X/final``), ``learn.json``, ``learn.md`` (a table per round) and ``learn.png``
(success and cost against transitions). See fvin_mpc/studies/learning_loop.py and docs/learning-loop.md.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path
from typing import Sequence

from fvin_mpc._cli import (
    add_mpc_arguments,
    check_output_folder,
    check_scene_env,
    duration_s,
    mpc_overrides,
    nonnegative_float,
    nonnegative_int,
    positive_float,
    positive_int,
    require_torch,
    run_command,
    seed_value,
)
from fvin_mpc.envs.scenes import existing_scene
from fvin_mpc.studies.learning_loop import (
    EXCITATIONS,
    FREE_BODY_DEFAULTS,
    FREE_BODY_EXCITATION,
    PIVOTED_DEFAULTS,
    LoopSettings,
    run_loop,
    write_loop_report,
)

#: What the loop writes into its folder: replaced only with ``--force``.
LOOP_FILES = ("data.npz", "round_*", "final.*", "learn.json", "learn.md", "learn.png")


def build_parser() -> argparse.ArgumentParser:
    defaults = LoopSettings()
    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.learn", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default="pendulum", help="built-in scene name or MJCF path (default: %(default)s)")
    pivoted, free = PIVOTED_DEFAULTS, FREE_BODY_DEFAULTS
    parser.add_argument("--budget", type=positive_int, default=None,
                        help=f"most training transitions from the plant (default: pivoted bodies {pivoted['budget']}, "
                             f"free bodies {free['budget']})")
    parser.add_argument("--excitation", choices=(*EXCITATIONS, FREE_BODY_EXCITATION), default=None,
                        help="collector of the first batch: a pivoted body's swings (collect's default) or random "
                             "torques; a free body's bursts (random-excitation bursts from the MJCF alone, "
                             f"collect's default) (default: {pivoted['excitation']}, or {free['excitation']})")
    parser.add_argument("--excitation-trajectories", type=positive_int, default=None,
                        help=f"trajectories of the first batch (default: pivoted bodies "
                             f"{pivoted['excitation_trajectories']}, free bodies {free['excitation_trajectories']})")
    parser.add_argument("--segment-steps", type=positive_int, default=defaults.segment_steps,
                        help="control periods per stored trajectory (default: %(default)s)")
    parser.add_argument("--explore-episodes", type=positive_int, default=defaults.explore_episodes,
                        help="exploration episodes per round (default: %(default)s)")
    parser.add_argument("--explore-segments", type=positive_int, default=defaults.explore_segments,
                        help="length of an exploration episode in trajectories of --segment-steps "
                             "(default: %(default)s)")
    parser.add_argument("--exploration-noise", type=nonnegative_float, default=defaults.exploration_noise,
                        help="exploration noise as a share of the torque bound (default: %(default)s)")
    parser.add_argument("--evaluation-starts", type=positive_int, default=defaults.evaluation_starts,
                        help="fixed evaluation starts: hanging at rest, then random; a free body: fly's recovery "
                             "starts (default: %(default)s)")
    parser.add_argument("--evaluation-duration", type=duration_s, default=None,
                        help="seconds per evaluation episode (default: the swing-up command's for the scene; a free "
                             "body: fly's recovery episode for the craft)")
    parser.add_argument("--max-rounds", type=nonnegative_int, default=defaults.max_rounds,
                        help="most rounds after the first (default: %(default)s)")
    parser.add_argument("--train-iterations", type=positive_int, default=None,
                        help="most training iterations per round (default: the training command's)")
    parser.add_argument("--cost-tolerance", type=_tolerance, default=defaults.cost_tolerance,
                        help="stop only once the learned cost summed over the starts is also at most this times "
                             "the closed form's; 'none': success alone stops (default: %(default)s)")
    parser.add_argument("--min-cost-gain", type=nonnegative_float, default=defaults.min_cost_gain,
                        help="once successful, also stop when a round lowers the summed cost by less than this "
                             "share of the best successful round's (default: %(default)s)")
    parser.add_argument("--time-limit", type=positive_float, default=None,
                        help="seconds: end (before exploring) when another round as long as the last would "
                             "end past this (default: none)")
    parser.add_argument("--seed", type=seed_value, default=0,
                        help="seeds excitation, exploration, training (default: 0)")
    parser.add_argument("--out-dir", type=Path, default=None,
                        help="default: learn/<scene name>; a folder holding a loop's files is replaced only with "
                             "--force")
    parser.add_argument("--force", action="store_true", help="replace the files of an earlier loop in --out-dir")
    parser.add_argument("--quiet", action="store_true", help="no progress display")
    add_mpc_arguments(parser)
    return parser


def _tolerance(text: str) -> float | None:
    if text.strip().lower() == "none":
        return None
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a number >= 1 or 'none', got {text!r}") from None
    if not 1.0 <= value < float("inf"):
        raise argparse.ArgumentTypeError(f"a number >= 1 or 'none', got {text!r}")
    return value


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    require_torch("learn")
    spec = existing_scene(args.scene)
    settings = LoopSettings(
        budget=args.budget, excitation=args.excitation, excitation_trajectories=args.excitation_trajectories,
        segment_steps=args.segment_steps,
        explore_episodes=args.explore_episodes, explore_segments=args.explore_segments,
        exploration_noise=args.exploration_noise, evaluation_starts=args.evaluation_starts,
        evaluation_duration_s=args.evaluation_duration, max_rounds=args.max_rounds,
        train_iterations=args.train_iterations, seed=args.seed, time_limit_s=args.time_limit,
        cost_tolerance=args.cost_tolerance, min_cost_gain=args.min_cost_gain,
        mpc={k: v for k, v in mpc_overrides(args).items() if v is not None},
    )
    out_dir = check_output_folder(args.out_dir or Path("learn") / spec.name, "--out-dir", args.force, LOOP_FILES)
    check_scene_env(spec)  # the physics the loop will simulate, before the closed form runs
    log = (lambda message: None) if args.quiet else (lambda message: print(message, file=sys.stderr))
    result = run_loop(args.scene, settings, out_dir, progress=not args.quiet, log=log)
    command = "python -m fvin_mpc.learn " + " ".join(shlex.quote(a) for a in (argv if argv is not None
                                                                               else sys.argv[1:]))
    write_loop_report(result, out_dir, command)
    print(json.dumps({key: result[key] for key in ("scene", "outcome", "transitions_to_success", "transitions_to_stop",
                                                   "training_transitions", "final_round",
                                                   "evaluation_transitions", "final_checkpoint", "wall_s")}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
