"""Train a learned R³ × S³ model on free-body data: ``python -m fvin_mpc.learning.training_r3s3``.

Trains with :func:`fvin_mpc.learning.training.train` itself (its split, multi-step loss,
Levenberg–Marquardt, early stopping and thread choice), given the model and the windows: the
model's rollout speaks the training layout of :mod:`fvin_mpc.learning.model_r3s3` (orientation
apart, ``(s_x x, s_v v, ω)`` as the second block), so the loss is
``4(1 − ⟨q̂, q⟩²) + omega_weight·(s_x²|x̂ − x|² + s_v²|v̂ − v|² + |ω̂ − ω|²)``.
``python -m fvin_mpc.train`` on free-body data runs this module's command.

Also here: the targets of issue 13 that are measured on the model alone — the held-out open-loop
error over 1 s of the learned model against the closed-form model through the same integrator
(:func:`open_loop_errors`) and the recovered mass and inertia (:func:`recovered_parameters`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from fvin_mpc.core.free_body_data import FreeBodyData, load_free_body_data
from fvin_mpc.core.networks_r3s3 import LearnedCombinedTerms, R3S3Config, physical_scale
from fvin_mpc.learning.training import TrainSettings, package_versions, refuse_to_overwrite, train

#: Position and velocity scales of the loss (1/m, s/m): 1 mm of position error weighs as 0.03 rad/s.
POSITION_SCALE, VELOCITY_SCALE = 30.0, 10.0
DEFAULT_DATA = Path("data/quadrotor.npz")


def train_r3s3(data: FreeBodyData, config: R3S3Config, settings: TrainSettings = TrainSettings(),
               position_scale: float = POSITION_SCALE, velocity_scale: float = VELOCITY_SCALE,
               progress: bool = True, initial_weights: Mapping[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
    """Train an :class:`~fvin_mpc.learning.model_r3s3.R3S3FVIN` with Levenberg–Marquardt through
    :func:`fvin_mpc.learning.training.train`; returns ``(model, report)`` as it does, with the loss
    scales added. ``initial_weights`` continues from a trained model (default: the seeded
    initialization)."""
    from fvin_mpc.learning.model_r3s3 import R3S3FVIN

    if settings.optimizer != "lm":
        raise ValueError("the R³ × S³ model trains with Levenberg–Marquardt only (settings.optimizer='lm')")

    def model_factory(config: R3S3Config, seed: int) -> R3S3FVIN:
        return R3S3FVIN(config, initial_weights, seed=seed, position_scale=position_scale,
                        velocity_scale=velocity_scale)

    model, report = train(data, config, settings, progress, model_factory=model_factory,
                          window_tensors=free_body_windows)
    report.update(position_scale=position_scale, velocity_scale=velocity_scale)
    return model, report


def free_body_windows(model: Any, data: FreeBodyData, window: int) -> tuple[Any, ...]:
    """``data``'s windows of ``window`` steps in ``model``'s training layout: ``(q, r, u)`` tensors
    with ``r = (s_x x, s_v v, ω)`` (:meth:`~fvin_mpc.learning.model_r3s3.R3S3FVIN.pack`)."""
    import torch

    from fvin_mpc.learning.model import DTYPE

    states, u = data.windows(window)
    return (*model.pack(torch.as_tensor(states, dtype=DTYPE)), torch.as_tensor(u, dtype=DTYPE))


# ----------------------------------------------------------------------------- targets
def recovered_parameters(weights: Mapping[str, Any], config: R3S3Config, body: Any = None,
                         orientations: int = 200, seed: int = 0) -> dict[str, Any]:
    """The learned ``M`` and ``J`` in kg and kg·m², each divided by its own scale.

    The translational scale ``c`` is read off the thrust (:func:`fvin_mpc.core.networks_r3s3.physical_scale`:
    one newton shared evenly by the rotors is one newton; its spread over ``orientations`` random
    attitudes is reported). An untethered craft's rotation does not see its translation (no term
    couples them), so its terms carry a second, independent scale ``c_rot``: fixed by the rotors'
    known torque, ``c_rot = ‖ĝ‖ / ‖2B‖`` (Frobenius, ``B`` from ``body``'s rotor sites and κ), when a
    closed-form ``body`` (:class:`~fvin_mpc.core.quadrotor.Quadrotor`) is given; then relative errors
    against its mass and inertia too. ``J`` at the identity."""
    from fvin_mpc.core.backend import get_ops

    terms = LearnedCombinedTerms(weights, config, get_ops("numpy"))
    scale = physical_scale(terms)
    rng = np.random.default_rng(seed)
    spread = []
    for _ in range(orientations):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        gain = np.asarray(terms.force_gain(tuple(np.zeros(3)), tuple(q)), dtype=float)
        spread.append(np.linalg.norm(gain.mean(axis=1)))
    identity = tuple(np.float64(c) for c in (1.0, 0.0, 0.0, 0.0))
    mass = np.array(terms.mass_matrix(), dtype=float) / scale
    result: dict[str, Any] = {"scale": scale, "scale_over_orientations": {"min": float(np.min(spread)),
                                                                        "max": float(np.max(spread))},
                              "mass_matrix": mass.tolist()}
    inertia = np.array(terms.inertia(identity), dtype=float)
    if body is None:
        result["inertia_unscaled"] = inertia.tolist()
        return result
    gain = np.array(terms.control_gain(tuple(np.zeros(3)), identity), dtype=float)
    rotational_scale = float(np.linalg.norm(gain) / np.linalg.norm(2.0 * np.array(body.torque_map)))
    inertia = inertia / rotational_scale
    true_inertia = np.array(body.inertia)
    result.update(
        rotational_scale=rotational_scale, inertia=inertia.tolist(),
        mass_relative_error=float(np.abs(np.linalg.eigvalsh(mass) / body.mass - 1.0).max()),
        inertia_relative_error=float(np.abs(np.diag(inertia) / np.diag(true_inertia) - 1.0).max()),
        inertia_off_diagonal_relative=float(np.abs(inertia - np.diag(np.diag(inertia))).max() / np.trace(true_inertia) * 3),
    )
    return result


def open_loop_errors(step: Any, data: FreeBodyData, horizon_steps: int) -> dict[str, Any]:
    """Open-loop rollouts of ``step(state (B, 13), u (B, m)) -> state (B, 13)`` from the first state of
    every trajectory of ``data`` under its recorded controls, against the recorded states, over
    ``horizon_steps`` steps: position (m), orientation (rad, sign invariant), velocity (m/s) and
    angular velocity (rad/s) errors at the end (median, 90th percentile, max) and the largest
    ``||q| − 1|``."""
    horizon_steps = min(horizon_steps, data.u.shape[1])  # the recorded trajectories' length at most
    states = data.state[:, : horizon_steps + 1]
    predicted = [states[:, 0]]
    for k in range(horizon_steps):
        predicted.append(step(predicted[-1], data.u[:, k]))
    final, truth = predicted[-1], states[:, -1]
    alignment = np.clip(np.abs(np.sum(final[:, 3:7] * truth[:, 3:7], axis=1) / np.linalg.norm(final[:, 3:7], axis=1)), 0, 1)
    errors = {
        "position_m": np.linalg.norm(final[:, :3] - truth[:, :3], axis=1),
        "orientation_rad": 2.0 * np.arccos(alignment),
        "velocity_m_s": np.linalg.norm(final[:, 7:10] - truth[:, 7:10], axis=1),
        "angular_velocity_rad_s": np.linalg.norm(final[:, 10:] - truth[:, 10:], axis=1),
    }
    summary: dict[str, Any] = {name: {"median": float(np.median(e)), "p90": float(np.percentile(e, 90)),
                                      "max": float(np.max(e))} for name, e in errors.items()}
    summary["max_unit_norm_error"] = float(max(np.abs(np.linalg.norm(p[:, 3:7], axis=1) - 1.0).max() for p in predicted))
    summary["all_finite"] = bool(all(np.all(np.isfinite(p)) for p in predicted))
    summary["horizon_s"] = horizon_steps * data.control_period
    summary["trajectories"] = data.num_trajectories
    return summary


def hover_thrust(weights: Mapping[str, Any], config: R3S3Config, data: FreeBodyData) -> float:
    """The per-rotor thrust, shared evenly, at which the learned model holds still level at the
    data's hover point (the first recorded position's neighbourhood: ``(0, 0, 1)`` for the scene):
    ``(∇ₓU)_z / (G_x 1)_z`` at ``(x*, identity)``."""
    from fvin_mpc.core.backend import get_ops

    terms = LearnedCombinedTerms(weights, config, get_ops("numpy"))
    x = tuple(np.float64(c) for c in (0.0, 0.0, 1.0))
    q = tuple(np.float64(c) for c in (1.0, 0.0, 0.0, 0.0))
    gain = np.asarray(terms.force_gain(x, q), dtype=float)
    return float(np.asarray(terms.potential_gradient_x(x, q), dtype=float)[2] / gain[2].sum())


def scene_quadrotor(scene: str) -> Any:
    """The closed-form :class:`~fvin_mpc.core.quadrotor.Quadrotor` of a free-body scene's MJCF."""
    from fvin_mpc.core.quadrotor import from_mujoco
    from fvin_mpc.envs import QuadrotorEnv

    env = QuadrotorEnv(scene=scene)
    try:
        return from_mujoco(env.model, env.body_name)
    finally:
        env.close()


def compare_open_loop(weights: Mapping[str, Any], config: R3S3Config, test: FreeBodyData, scene: str,
                      horizon_s: float = 1.0) -> dict[str, Any]:
    """:func:`open_loop_errors` over ``horizon_s`` of the learned model and of the closed-form craft read
    off the scene's MJCF (:func:`fvin_mpc.core.quadrotor.from_mujoco`), through the same step (``h``,
    ``K``, force rule), on the same held-out trajectories."""
    from fvin_mpc.core.backend import get_ops

    body = scene_quadrotor(scene)
    steps = int(round(horizon_s / config.step_size))
    ops = get_ops("numpy")
    return {
        "open_loop_learned": open_loop_errors(numpy_step(LearnedCombinedTerms(weights, config, ops), config,
                                                         config.newton_iters, config.force_rule), test, steps),
        "open_loop_closed_form": open_loop_errors(numpy_step(body.terms(ops), config, config.newton_iters,
                                                             config.force_rule), test, steps),
    }


def numpy_step(terms: Any, config_or_step: Any, newton_iters: int, force_rule: str = "trapezoid") -> Any:
    """``step(state (B, 13), u (B, m))`` of NumPy :class:`CombinedTerms` at step size ``config_or_step``
    (a float, or a config with ``step_size``)."""
    from fvin_mpc.core import fvin_r3s3
    from fvin_mpc.core.backend import get_ops

    h = float(getattr(config_or_step, "step_size", config_or_step))
    ops = get_ops("numpy")
    return lambda state, u: fvin_r3s3.step_state(state, u, terms, h, newton_iters, ops, force_rule)[0]


# ----------------------------------------------------------------------------- command
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.learning.training_r3s3", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="free-body data (default: %(default)s)")
    parser.add_argument("--test-data", type=Path, default=None, help="held-out data for the 1 s open-loop error")
    parser.add_argument("--variant", default="fixed-inertia", choices=("sign-invariant", "fixed-inertia", "plain"))
    parser.add_argument("--hidden-width", type=int, default=16)
    parser.add_argument("--newton-iters", type=int, default=2)
    parser.add_argument("--trajectories", type=int, default=None, help="train on the first N trajectories only")
    parser.add_argument("--window", type=int, default=8)
    parser.add_argument("--iterations", type=int, default=None)
    parser.add_argument("--jacobian-windows", type=int, default=TrainSettings.jacobian_windows)
    parser.add_argument("--patience", type=int, default=6, help="validation evaluations without progress before stopping")
    parser.add_argument("--time-limit", type=float, default=None, help="seconds")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None,
                        help="checkpoint stem (default: checkpoints/<scene>_<variant>, e.g. "
                             "checkpoints/quadrotor_fixed-inertia; never replacing an existing checkpoint, a shipped "
                             "one included, unless --force)")
    parser.add_argument("--force", action="store_true", help="let the default --out replace an existing checkpoint")
    parser.add_argument("--init", default=None, metavar="CHECKPOINT",
                        help="continue training from this checkpoint (its architecture; --variant and --hidden-width are ignored)")
    parser.add_argument("--evaluate", default=None, metavar="CHECKPOINT",
                        help="no training: evaluate this checkpoint on --test-data (open loop over 0.2, 0.5 and 1 s, "
                             "learned beside closed form; recovered mass, inertia and hover thrust)")
    parser.add_argument("--quiet", action="store_true")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)

    from fvin_mpc.core.checkpoint import load_checkpoint, save_checkpoint

    if args.evaluate is not None:
        if args.test_data is None:
            parser.error("--evaluate needs --test-data")
        checkpoint = load_checkpoint(args.evaluate)
        test = load_free_body_data(args.test_data)
        scene = str(test.metadata.get("scene", "quadrotor"))
        body = scene_quadrotor(scene)
        result: dict[str, Any] = {"checkpoint": str(checkpoint.path), "test_data": str(args.test_data),
                                  "recovered": recovered_parameters(checkpoint.weights, checkpoint.config, body),
                                  "hover_thrust": hover_thrust(checkpoint.weights, checkpoint.config, test),
                                  "true_hover_thrust": body.hover_thrust}
        for horizon in (0.2, 0.5, 1.0):
            result[f"horizon_{horizon:g}s"] = compare_open_loop(checkpoint.weights, checkpoint.config, test, scene, horizon)
        print(json.dumps(result, indent=2))
        return 0

    data = load_free_body_data(args.data)
    if args.trajectories is not None:
        data = data.subset(np.arange(min(args.trajectories, data.num_trajectories)))
    config = R3S3Config(variant=args.variant, control_dim=data.u.shape[2], hidden_width=args.hidden_width,
                        step_size=data.control_period, newton_iters=args.newton_iters)
    initial = None
    if args.init is not None:
        start = load_checkpoint(args.init)
        if not isinstance(start.config, R3S3Config):
            parser.error(f"--init {args.init}: not an R3xS3 checkpoint")
        config, initial = start.config, {name: np.array(value) for name, value in start.weights.items()}
        previous = dict(start.metadata.get("training", {}))
    stem = args.out or Path("checkpoints") / f"{data.metadata.get('scene', 'quadrotor')}_{config.variant}"
    if args.out is None:
        refuse_to_overwrite(stem, args.force)
    settings = TrainSettings(optimizer="lm", iterations=args.iterations, window=args.window, seed=args.seed,
                             jacobian_windows=args.jacobian_windows, threads=args.threads, patience=args.patience,
                             time_limit_s=args.time_limit)
    model, report = train_r3s3(data, config, settings, progress=not args.quiet, initial_weights=initial)
    if args.init is not None:
        report["continued_from"] = {"checkpoint": str(args.init), "iterations": previous.get("iterations"),
                                    "wall_clock_s": previous.get("wall_clock_s"), "cpu_s": previous.get("cpu_s"),
                                    "continued_from": previous.get("continued_from")}
    weights = model.numpy_weights()
    summary: dict[str, Any] = {"recovered": recovered_parameters(weights, config,
                                                                 scene_quadrotor(str(data.metadata.get("scene", "quadrotor"))))}
    if args.test_data is not None:
        test = load_free_body_data(args.test_data)
        summary.update(compare_open_loop(weights, config, test, str(test.metadata.get("scene", "quadrotor"))))
    history = report.pop("history")
    save_checkpoint(stem, config, weights, scene=data.metadata.get("scene"), body=data.metadata.get("body"),
                    data={"path": str(args.data), "trajectories": data.num_trajectories,
                          "transitions": data.num_transitions, **{k: data.metadata.get(k) for k in ("seed", "collector")}},
                    training={**report, "history_tail": history[-5:]}, evaluation=summary, versions=package_versions())
    print(json.dumps({"checkpoint": str(stem), "iterations": report["iterations"], "stopped": report["stopped"],
                      "final_validation_loss": report["final_validation_loss"], "wall_clock_s": report["wall_clock_s"],
                      "cpu_s": report["cpu_s"], **summary}, indent=2))
    return 0


if __name__ == "__main__":
    from fvin_mpc.core.errors import run_command

    raise SystemExit(run_command(main))
