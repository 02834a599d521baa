"""Train an S3FVIN on trajectory data: ``python -m fvin_mpc.train``.

Loss: multi-step rollout over windows of ``--window`` steps, the sign-invariant
orientation error ``4(1 − ⟨q̂, q⟩²)`` (≈ squared angle error in rad²) plus
``--omega-weight``·‖ω̂ − ω‖², averaged over windows and steps. Full-batch Adam;
trajectories are split into train/validation sets before windowing.
"""

from __future__ import annotations
import argparse
import json
from pathlib import Path
from fvin_mpc.core.data import load_data
from fvin_mpc.core.networks import VARIANTS, ModelConfig
from fvin_mpc.learning.training import DEFAULT_DATA, TrainSettings, package_versions, train


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.train", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="data file from fvin_mpc.collect (default: %(default)s)")
    parser.add_argument("--out", type=Path, default=None, help="checkpoint stem (default: checkpoints/<scene>_<variant>)")
    parser.add_argument("--variant", choices=VARIANTS, default="sign-invariant")
    parser.add_argument("--hidden-width", type=int, default=ModelConfig.hidden_width)
    parser.add_argument("--hidden-layers", type=int, default=ModelConfig.hidden_layers)
    parser.add_argument("--newton-iters", type=int, default=ModelConfig.newton_iters)
    parser.add_argument("--dissipation", action="store_true", help="learn a damping term −Dω (for dissipative scenes)")
    parser.add_argument("--iterations", type=int, default=TrainSettings.iterations)
    parser.add_argument("--lr", type=float, default=TrainSettings.learning_rate)
    parser.add_argument("--window", type=int, default=TrainSettings.window)
    parser.add_argument("--omega-weight", type=float, default=TrainSettings.omega_weight)
    parser.add_argument("--no-compile", dest="compile", action="store_false",
                        help="run torch eagerly (skips ≈75 s of torch.compile; iterations ≈3× slower)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)

    from fvin_mpc.core.checkpoint import save_checkpoint

    data = load_data(args.data)
    config = ModelConfig(
        variant=args.variant, control_dim=int(data.u.shape[2]), hidden_width=args.hidden_width,
        hidden_layers=args.hidden_layers, step_size=data.control_period, newton_iters=args.newton_iters,
        dissipation=args.dissipation,
    )
    settings = TrainSettings(iterations=args.iterations, learning_rate=args.lr, window=args.window,
                             omega_weight=args.omega_weight, seed=args.seed, compile=args.compile)
    model, report = train(data, config, settings, progress=not args.quiet)
    scene = data.metadata.get("scene", "unknown")
    out = args.out or Path("checkpoints") / f"{scene}_{args.variant}"
    stem = save_checkpoint(
        out, config, model.numpy_weights(), scene=scene, body=data.metadata.get("body"),
        data={"path": str(args.data), "trajectories": data.num_trajectories, "transitions": data.num_transitions,
              "seed": data.metadata.get("seed"), "control_period": data.control_period},
        training=report, versions=package_versions(),
    )
    print(json.dumps({"checkpoint": str(stem), "final_train_loss": report["final_train_loss"],
                      "final_validation_loss": report["final_validation_loss"],
                      "wall_clock_s": round(report["wall_clock_s"], 1)}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
