"""Train an S3FVIN on trajectory data: ``python -m fvin_mpc.train``.

Loss: multi-step rollout over windows of ``--window`` steps, the sign-invariant
orientation error ``4(1 − ⟨q̂, q⟩²)`` (≈ squared angle error in rad²) plus
``--omega-weight``·‖ω̂ − ω‖², averaged over windows and steps. Trajectories are split
into train/validation sets before windowing. Default optimizer: Levenberg–Marquardt
on the stacked residuals (tens of iterations, seconds); ``--optimizer adam`` is the
former full-batch Adam. Training stops early once the validation loss stops improving.
See docs/training.md.

Free-body data (metadata ``configuration_space: R3xS3``, from ``python -m fvin_mpc.collect
--scene quadrotor``) train the R³ × S³ model instead: the arguments then go to
``python -m fvin_mpc.learning.training_r3s3`` (its options: ``--help`` there; docs/quadrotor.md).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

_START = time.perf_counter()

from fvin_mpc.core.data import load_data  # noqa: E402
from fvin_mpc.core.free_body_data import is_free_body_data  # noqa: E402
from fvin_mpc.core.networks import VARIANTS, ModelConfig  # noqa: E402
from fvin_mpc._cli import run_command  # noqa: E402
from fvin_mpc.learning.training import (  # noqa: E402
    DEFAULT_DATA, DEFAULT_ITERATIONS, OPTIMIZERS, TrainSettings, default_output_stem, package_versions,
    refuse_to_overwrite, safe_thread_count, scene_has_joint_damping, train,
)


def build_parser() -> argparse.ArgumentParser:
    """The options for pivoted (S³) data; free-body data take those of
    :func:`fvin_mpc.learning.training_r3s3.build_parser`."""
    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.train", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="data file from fvin_mpc.collect (default: %(default)s)")
    parser.add_argument("--out", type=Path, default=None,
                        help="checkpoint stem (default: checkpoints/<scene stem>_<variant>, e.g. checkpoints/arm_sign-invariant "
                             "for data collected from /any/path/arm.xml, the scene's default model; data in a file "
                             "named otherwise, e.g. data/arm_big.npz, give checkpoints/arm_big_<variant>). The default "
                             "never replaces an existing checkpoint (a shipped one included) unless --force")
    parser.add_argument("--force", action="store_true",
                        help="let the default --out replace an existing checkpoint")
    parser.add_argument("--variant", choices=VARIANTS, default="sign-invariant", help="model variant (default: %(default)s)")
    parser.add_argument("--hidden-width", type=int, default=ModelConfig.hidden_width, help="width of every hidden layer (default: %(default)s)")
    parser.add_argument("--hidden-layers", type=int, default=ModelConfig.hidden_layers, help="hidden layers per MLP (default: %(default)s)")
    parser.add_argument("--newton-iters", type=int, default=ModelConfig.newton_iters, help="Newton iterations K per step (default: %(default)s)")
    parser.add_argument("--dissipation", action=argparse.BooleanOptionalAction, default=None,
                        help="learn a damping term −Dω (default: on when the data's scene declares joint damping)")
    parser.add_argument("--optimizer", choices=OPTIMIZERS, default=TrainSettings.optimizer,
                        help="lm: Levenberg–Marquardt (default), lbfgs: full-batch L-BFGS, adam: full-batch Adam")
    parser.add_argument("--iterations", type=int, default=None,
                        help="most iterations (default: " + ", ".join(f"{k} {v}" for k, v in DEFAULT_ITERATIONS.items())
                             + "); early stopping usually ends sooner")
    parser.add_argument("--patience", type=int, default=TrainSettings.patience,
                        help="stop after this many validation evaluations without a relative improvement of "
                             "--min-improvement; 0: never stop early (default: %(default)s)")
    parser.add_argument("--min-improvement", type=float, default=TrainSettings.min_improvement,
                        help="relative validation-loss decrease that counts as progress (default: %(default)s)")
    parser.add_argument("--target-loss", type=float, default=None, help="stop once the validation loss is at most this")
    parser.add_argument("--time-limit", type=float, default=None, help="stop after this many seconds of training")
    parser.add_argument("--eval-every", type=int, default=None, help="iterations between validation evaluations (default: lm/lbfgs 1, adam 25)")
    parser.add_argument("--jacobian-windows", type=int, default=TrainSettings.jacobian_windows,
                        help="windows sampled per LM iteration for the Gauss–Newton matrix (default: %(default)s)")
    parser.add_argument("--lr", type=float, default=TrainSettings.learning_rate, help="Adam learning rate (default: %(default)s)")
    parser.add_argument("--window", type=int, default=TrainSettings.window, help="rollout steps per training window (default: %(default)s)")
    parser.add_argument("--omega-weight", type=float, default=TrainSettings.omega_weight,
                        help="weight of the angular-velocity error (default: %(default)s)")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch intra-op threads (default: the cores the 1-minute load average leaves at least half free, "
                             "at least 1; "
                             f"now {safe_thread_count()})")
    parser.add_argument("--compile", action="store_true",
                        help="torch.compile the step (adam/lbfgs only): ≈75–200 s of compilation, then ≈3× faster iterations")
    parser.add_argument("--seed", type=int, default=0, help="seed of the initialization, split and LM samples (default: %(default)s)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def main(argv: list[str] | None = None) -> int:
    # Which model the data call for decides which options apply: read --data alone first.
    peek = argparse.ArgumentParser(add_help=False)
    peek.add_argument("--data", type=Path, default=DEFAULT_DATA)
    if is_free_body_data(peek.parse_known_args(argv)[0].data):
        from fvin_mpc.learning import training_r3s3

        return training_r3s3.main(argv)
    parser = build_parser()
    args = parser.parse_args(argv)

    from fvin_mpc.core.checkpoint import save_checkpoint

    data = load_data(args.data)
    out = args.out or default_output_stem(data, args.data, args.variant)
    if args.out is None:
        refuse_to_overwrite(out, args.force)
    dissipation = args.dissipation
    if dissipation is None:
        dissipation = bool(scene_has_joint_damping(data.metadata))
    config = ModelConfig(
        variant=args.variant, control_dim=int(data.u.shape[2]), hidden_width=args.hidden_width,
        hidden_layers=args.hidden_layers, step_size=data.control_period, newton_iters=args.newton_iters,
        dissipation=dissipation,
    )
    try:
        settings = TrainSettings(
            optimizer=args.optimizer, iterations=args.iterations, learning_rate=args.lr, window=args.window,
            omega_weight=args.omega_weight, seed=args.seed, eval_every=args.eval_every, patience=args.patience,
            min_improvement=args.min_improvement, target_loss=args.target_loss, jacobian_windows=args.jacobian_windows,
            threads=args.threads, compile=args.compile, time_limit_s=args.time_limit,
        )
    except ValueError as error:
        parser.error(str(error))
    model, report = train(data, config, settings, progress=not args.quiet)
    scene = data.metadata.get("scene", "unknown")
    report["dissipation_chosen"] = "given" if args.dissipation is not None else "scene joint damping"
    report["process_to_train_end_s"] = time.perf_counter() - _START
    report["process_cpu_to_train_end_s"] = time.process_time()  # CPU seconds since the process started
    stem = save_checkpoint(
        out, config, model.numpy_weights(), scene=scene, body=data.metadata.get("body"),
        data={"path": str(args.data), "trajectories": data.num_trajectories, "transitions": data.num_transitions,
              "seed": data.metadata.get("seed"), "control_period": data.control_period},
        training=report, versions=package_versions(),
    )
    print(json.dumps({"checkpoint": str(stem), "optimizer": report["optimizer"], "iterations": report["iterations"],
                      "stopped": report["stopped"], "dissipation": dissipation, "threads": report["threads"],
                      "final_train_loss": report["final_train_loss"],
                      "final_validation_loss": report["final_validation_loss"],
                      "wall_clock_s": round(report["wall_clock_s"], 1),
                      "process_s": round(time.perf_counter() - _START, 1)}, indent=2))
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
