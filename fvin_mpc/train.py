"""Train a learned model on trajectory data of any configuration space: ``python -m fvin_mpc.train``.

The data say their configuration space (``python -m fvin_mpc.collect`` writes it): a body on a
pivot (S³; ``--variant so3-matrix`` or ``so3-quaternion`` trains the paper's SO(3) baseline on the
same data) or a free body (R³ × S³). One loop trains them all.

Loss: multi-step rollout over windows of ``--window`` steps, the sign-invariant
orientation error ``4(1 − ⟨q̂, q⟩²)`` (≈ squared angle error in rad²) plus
``--omega-weight``·‖ω̂ − ω‖² (a free body: its position, velocity and angular velocity errors,
scaled), averaged over windows and steps. Trajectories are split into train/validation sets before
windowing. Default optimizer: Levenberg–Marquardt on the stacked residuals (tens of iterations,
seconds); ``--optimizer adam`` is full-batch Adam. Training stops early once the validation loss
stops improving, unless it stops far above the data's floor (more than ``--poor-loss-ratio`` of the loss
of a model that predicts no motion): such a plateau starts a fresh run from a new initialization
(``--restarts``), and a model that still ends there is reported poor in one line on stderr and in the
checkpoint's ``training.quality``. See docs/training.md (free bodies: docs/quadrotor.md).

A body on a pivot is also measured where its controller needs it (docs/excitation.md): from
hanging at 0.6–1.3× the scene's speed scale, the plant (the data's MJCF, MuJoCo) and the model swing
under full torque along the motion, and the swing measure is the mean difference of the true energy
at the plant's apex, in units of the swing-up's energy span (``swing_energy_error``; the apex angles
beside it). The training window is half the scene's natural period (8–32 steps) unless ``--window``
is given: long enough for a wrong damping to show. The measure is evaluated with the validation
loss, and by default (``--select measure``) the returned iteration is the one with the lowest
measure among those whose validation loss is within twice the best; the report and the
checkpoint's metadata (``training.swing``) carry it.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import fields
from pathlib import Path
from typing import Any

_START = time.perf_counter()

import numpy as np

from fvin_mpc._cli import run_command
from fvin_mpc.core.checkpoint import load_checkpoint, save_checkpoint
from fvin_mpc.core.data import load_data
from fvin_mpc.core.space import S3, space_for_variant, space_of_config, spaces
from fvin_mpc.learning.space_training import default_model_config, train_model, training_for
from fvin_mpc.learning.swing_measure import swing_apex_error, swing_probe, torch_model_step
from fvin_mpc.learning.training import (
    DEFAULT_DATA,
    DEFAULT_ITERATIONS,
    OPTIMIZERS,
    TrainSettings,
    default_output_stem,
    package_versions,
    quality_line,
    refuse_to_overwrite,
    safe_thread_count,
)

#: Every model variant of every registered space.
ALL_VARIANTS = tuple(dict.fromkeys(variant for space in spaces() for variant in space.variants))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.train", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--data", type=Path, default=DEFAULT_DATA, help="data file from fvin_mpc.collect (default: %(default)s)"
    )
    parser.add_argument("--test-data", type=Path, default=None,
                        help="held-out data for the space's report (a free body: the 1 s open-loop error)")
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="checkpoint stem (default: checkpoints/<scene stem>_<variant>, e.g. checkpoints/arm_sign-invariant "
        "for data collected from /any/path/arm.xml, the scene's default model; data in a file "
        "named otherwise, e.g. data/arm_big.npz, give checkpoints/arm_big_<variant>). The default "
        "never replaces an existing checkpoint (a shipped one included) unless --force",
    )
    parser.add_argument("--force", action="store_true",
                        help="let the default --out replace an existing checkpoint")
    parser.add_argument("--variant", choices=ALL_VARIANTS, default=None,
                        help="model variant (default: the data's space's first: sign-invariant on a pivot, "
                             "fixed-inertia for a free body; so3-matrix/so3-quaternion: the SO(3) baseline)")
    parser.add_argument(
        "--hidden-width", type=int, default=None, help="width of every hidden layer (default: the config's)"
    )
    parser.add_argument("--hidden-layers", type=int, default=None, help="hidden layers per MLP (default: the config's)")
    parser.add_argument(
        "--newton-iters", type=int, default=None, help="Newton iterations K per step (default: the config's)"
    )
    parser.add_argument(
        "--dissipation",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="learn a damping term −Dω (S³ models; default: on when the data's scene declares joint damping)",
    )
    parser.add_argument("--trajectories", type=int, default=None, help="train on the first N trajectories only")
    parser.add_argument(
        "--init",
        default=None,
        metavar="CHECKPOINT",
        help="continue training from this checkpoint (its architecture; --variant and the widths are ignored)",
    )
    parser.add_argument(
        "--evaluate",
        default=None,
        metavar="CHECKPOINT",
        help="no training: the space's evaluation of this checkpoint on --test-data (free bodies: open "
        "loop over 0.2, 0.5 and 1 s, learned beside closed form; recovered mass, inertia, hover thrust)",
    )
    parser.add_argument("--optimizer", choices=OPTIMIZERS, default=None,
                        help="lm: Levenberg–Marquardt (default), lbfgs: full-batch L-BFGS, adam: full-batch Adam")
    parser.add_argument("--iterations", type=int, default=None,
                        help="most iterations (default: " + ", ".join(f"{k} {v}" for k, v in DEFAULT_ITERATIONS.items())
                             + "); early stopping usually ends sooner")
    parser.add_argument(
        "--patience",
        type=int,
        default=None,
        help="stop after this many validation evaluations without a relative improvement of "
        "--min-improvement (far above the data's floor: start a fresh run, see --poor-loss-ratio); 0: never "
        f"stop early (default: {TrainSettings.patience}; free bodies 6)",
    )
    parser.add_argument(
        "--min-improvement",
        type=float,
        default=None,
        help=f"relative validation-loss decrease that counts as progress (default: {TrainSettings.min_improvement})",
    )
    parser.add_argument("--target-loss", type=float, default=None, help="stop once the validation loss is at most this")
    parser.add_argument("--time-limit", type=float, default=None, help="stop after this many seconds of training")
    parser.add_argument(
        "--eval-every",
        type=int,
        default=None,
        help="iterations between validation evaluations (default: lm/lbfgs 1, adam 25)",
    )
    parser.add_argument(
        "--jacobian-windows",
        type=int,
        default=None,
        help="windows sampled per LM iteration for the Gauss–Newton matrix (default: "
             f"{TrainSettings.jacobian_windows})",
    )
    parser.add_argument(
        "--lr", type=float, default=None, help=f"Adam learning rate (default: {TrainSettings.learning_rate})"
    )
    parser.add_argument(
        "--window", type=int, default=None,
        help="rollout steps per training window (default: on a pivot half the scene's natural period 2π/ω_s, "
             f"8–32 steps; else {TrainSettings.window})"
    )
    parser.add_argument("--omega-weight", type=float, default=None,
                        help=f"weight of the angular-velocity error (default: {TrainSettings.omega_weight})")
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch intra-op threads (default: free bodies 1; else the cores the 1-minute load average leaves "
        f"at least half free, at least 1; now {safe_thread_count()})",
    )
    parser.add_argument("--select", choices=("measure", "validation"), default=None,
                        help="the iteration returned: measure — the lowest swing measure among those within "
                             "--selection-tolerance of the best validation loss (default on a pivot); validation — "
                             "the lowest validation loss")
    parser.add_argument("--selection-tolerance", type=float, default=None,
                        help="how far above the best validation loss (relative) a selected iteration may be "
                             f"(default: {TrainSettings.selection_tolerance})")
    parser.add_argument("--poor-loss-ratio", type=_ratio_or_none, default=None, metavar="RATIO|none",
                        help="the validation loss, as a share of the data's hold loss (a model predicting no "
                             "motion), above which a model is poor: a plateau there starts a fresh run, and a "
                             "poor model is reported (a warning; the checkpoint's training.quality); none: every "
                             f"plateau is convergence and no verdict (default: {TrainSettings.poor_loss_ratio})")
    parser.add_argument("--restarts", type=int, default=None,
                        help="most fresh runs after a plateau above --poor-loss-ratio, within --iterations and "
                             f"--time-limit (default: {TrainSettings.restarts})")
    parser.add_argument(
        "--compile",
        action="store_true",
        help="torch.compile the step (adam/lbfgs only): ≈75–200 s of compilation, then ≈3× faster iterations",
    )
    parser.add_argument(
        "--seed", type=int, default=0, help="seed of the initialization, split and LM samples (default: %(default)s)"
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


#: Command-line options that are TrainSettings fields (option dest → field).
_SETTINGS_OPTIONS = {"optimizer": "optimizer", "iterations": "iterations", "lr": "learning_rate", "window": "window",
                     "omega_weight": "omega_weight", "eval_every": "eval_every", "patience": "patience",
                     "min_improvement": "min_improvement", "target_loss": "target_loss",
                     "jacobian_windows": "jacobian_windows", "threads": "threads", "time_limit": "time_limit_s",
                     "select": "selection", "selection_tolerance": "selection_tolerance",
                     "poor_loss_ratio": "poor_loss_ratio", "restarts": "restarts"}

#: ``--poor-loss-ratio none``: no verdict (the option's ``None`` already means "not given").
_NO_VERDICT = "none"


def _ratio_or_none(text: str) -> float | str:
    if text.strip().lower() == _NO_VERDICT:
        return _NO_VERDICT
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a number or {_NO_VERDICT!r}, not {text!r}") from None


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)

    if args.evaluate is not None:
        if args.test_data is None:
            parser.error("--evaluate needs --test-data")
        checkpoint = load_checkpoint(args.evaluate)
        evaluate = training_for(checkpoint.space).evaluate
        if evaluate is None:
            parser.error(f"--evaluate: models on {checkpoint.space.description} have no evaluation here")
        print(
            json.dumps({**evaluate(checkpoint, load_data(args.test_data)), "test_data": str(args.test_data)}, indent=2)
        )
        return 0

    data = load_data(args.data)
    if args.trajectories is not None:
        data = data.subset(np.arange(min(args.trajectories, data.num_trajectories)))
    initial, previous = None, None
    if args.init is not None:
        start = load_checkpoint(args.init)
        if start.space.layout != data.space.layout:
            parser.error(
                f"--init {args.init}: a model on {start.space.description}, the data are on {data.space.description}"
            )
        config, initial = start.config, {name: np.array(value) for name, value in start.weights.items()}
        previous = dict(start.metadata.get("training", {}))
    else:
        try:
            space = space_for_variant(data.space, args.variant or data.space.variants[0])
        except ValueError as error:
            parser.error(str(error))
        config = _model_config(parser, args, space, data)
    space = space_of_config(config)
    preset = training_for(space)
    given = {
        field: getattr(args, option) for option, field in _SETTINGS_OPTIONS.items() if getattr(args, option) is not None
    }
    if given.get("poor_loss_ratio") == _NO_VERDICT:
        given["poor_loss_ratio"] = None
    probe, measure = _swing_measure(data, space)
    if probe is not None and "window" not in given:
        given["window"] = min(probe.physics.scales.training_window, int(data.u.shape[1]))
    try:
        settings = TrainSettings(**{**preset.settings, **given, "seed": args.seed, "compile": args.compile})
    except ValueError as error:
        parser.error(str(error))

    if preset.optimizers is not None and settings.optimizer not in preset.optimizers:
        parser.error(f"models on {space.description} train with {', '.join(preset.optimizers)} only")
    out = args.out or default_output_stem(data, args.data, config.variant)
    if args.out is None:
        refuse_to_overwrite(out, args.force)
    model, report = train_model(data, config, settings, progress=not args.quiet, initial_weights=initial,
                                measure=measure)
    if report["quality"]["verdict"] == "poor":
        print(f"train: warning: {quality_line(report['quality'])}", file=sys.stderr)
    if probe is not None:
        report["swing"] = swing_apex_error(torch_model_step(model), probe)
        report["window_chosen"] = "given" if args.window is not None else "scene scales: half a natural period"
    if previous is not None:
        report["continued_from"] = {"checkpoint": str(args.init), "iterations": previous.get("iterations"),
                                    "wall_clock_s": previous.get("wall_clock_s"), "cpu_s": previous.get("cpu_s"),
                                    "continued_from": previous.get("continued_from")}
    if "dissipation" in _field_names(config) and initial is None:
        report["dissipation_chosen"] = "given" if args.dissipation is not None else "scene joint damping"
    report["process_to_train_end_s"] = time.perf_counter() - _START
    report["process_cpu_to_train_end_s"] = time.process_time()  # CPU seconds since the process started
    weights = model.numpy_weights()
    evaluation: dict[str, Any] = {}
    if preset.report is not None:
        evaluation = preset.report(weights, config, data, None if args.test_data is None else load_data(args.test_data))
    stem = save_checkpoint(
        out, config, weights, scene=data.metadata.get("scene", "unknown"), body=data.metadata.get("body"),
        data={"path": str(args.data), "trajectories": data.num_trajectories, "transitions": data.num_transitions,
              **{key: data.metadata[key] for key in ("seed", "collector") if key in data.metadata},
              "control_period": data.control_period},
        training=report, **({"evaluation": evaluation} if evaluation else {}), versions=package_versions(),
    )
    summary = {
        "checkpoint": str(stem),
        "space": space.name,
        "variant": config.variant,
        "optimizer": report["optimizer"],
        "iterations": report["iterations"],
        "stopped": report["stopped"],
        "restarts": report["restarts"],
        "quality": report["quality"]["verdict"],
        "threads": report["threads"],
        "final_train_loss": report["final_train_loss"],
        "final_validation_loss": report["final_validation_loss"],
        "wall_clock_s": round(report["wall_clock_s"], 1),
        "cpu_s": report.get("cpu_s"),
        "process_s": round(time.perf_counter() - _START, 1),
    }
    if "dissipation" in _field_names(config):
        summary["dissipation"] = config.dissipation
    if probe is not None:
        summary.update({key: report["swing"][key] for key in ("swing_energy_error", "swing_apex_error_deg")})
        summary["selected"] = report.get("selected")
    print(json.dumps({**summary, **evaluation}, indent=2))
    sys.stdout.flush()
    return 0


def _swing_measure(data: Any, space: Any) -> tuple[Any, Any]:
    """``(probe, measure)`` of the data's scene for a model on S³ (``(None, None)`` otherwise, or when
    the scene cannot be swung: no scene recorded, unbounded actuators, nothing to swing up)."""
    scene = data.metadata.get("scene")
    if space is not S3 or not scene:
        return None, None
    try:
        probe = swing_probe(str(scene), data.metadata.get("body"), data.control_period)
    except (ValueError, FileNotFoundError, OSError) as error:
        print(f"train: no swing measure on {scene}: {error}", file=sys.stderr)
        return None, None
    return probe, lambda model: swing_apex_error(torch_model_step(model), probe)["swing_energy_error"]


def _field_names(config: Any) -> set[str]:
    return {field.name for field in fields(config)}


def _model_config(parser: argparse.ArgumentParser, args: argparse.Namespace, space: Any, data: Any) -> Any:
    """The model config of ``space`` from the data and the options (:func:`default_model_config` for what
    they leave open); an option the space's config has no field for is refused."""
    names = {field.name for field in fields(space.config_type)}
    given = {"variant": args.variant} if args.variant else {}
    for option in ("hidden_width", "hidden_layers", "newton_iters", "dissipation"):
        value = getattr(args, option)
        if value is None:
            continue
        if option not in names:
            parser.error(f"--{option.replace('_', '-')} does not apply to models on {space.description}")
        given[option] = value
    try:
        return default_model_config(data, space, **given)
    except ValueError as error:
        parser.error(str(error))


if __name__ == "__main__":
    raise SystemExit(run_command(main))
