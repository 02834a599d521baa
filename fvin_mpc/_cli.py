"""Command-line options the commands share: the scene, its model, the MPC's settings and the execution backend,
and the checks every command makes at its edge, before any work (docs/bad-inputs.md): each option's value
while parsing (a ``type=`` validator; a 0 is a value or an error, never "the default"), the scene's physics
(:func:`check_scene_env`) and the output paths (:func:`check_output_file`, :func:`check_output_folder`:
creatable, of a kind the writer knows, nothing replaced without ``--force``, nothing written into the
package's own ``docs/`` unless the user named it)."""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path
from typing import Any, Callable

from fvin_mpc.core.checkpoint import CheckpointError, checkpoint_exists, load_checkpoint
from fvin_mpc.core.errors import INSTALL_TRAIN, SceneError, UsageError, run_command  # noqa: F401 (every command's wrapper)
from fvin_mpc.core.networks import MAX_NEWTON_ITERS
from fvin_mpc.envs import QuadrotorEnv, RigidBodyEnv
from fvin_mpc.envs.scenes import FREE_BODY_SCENES, SCENES, built_in_scene, existing_scene, resolve_scene
from fvin_mpc.studies.pool import TasksFailed

#: The longest MPC horizon (steps) a command line may ask for: 16× the longest default
#: (:data:`~fvin_mpc.control.scene.MAX_DEFAULT_HORIZON`, 60), past which the terminal cost does the
#: look-ahead anyway; a plan of 100,000 stages builds for hours and prints nothing meanwhile.
MAX_HORIZON = 1000
#: The longest closed loop a command runs (s): an hour of simulated time (72,000 periods at 50 ms);
#: ``--duration 1e12`` would run, silently, forever.
MAX_DURATION_S = 3600.0


def _number(text: str, kind: type) -> Any:
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected {'a whole number' if kind is int else 'a number'}, got {text!r}") from None
    if kind is float and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def number_in(kind: type, low: float | None = None, high: float | None = None, low_open: bool = False,
              high_open: bool = False) -> Callable[[str], Any]:
    """An argparse ``type=``: a finite ``kind`` (``int`` or ``float``) within the bounds, refused while
    parsing (``low_open``/``high_open``: the bound itself is excluded)."""

    def parse(text: str) -> Any:
        value = _number(text, kind)
        if low is not None and (value <= low if low_open else value < low):
            raise argparse.ArgumentTypeError(f"must be {'>' if low_open else '>='} {low:g}, got {text!r}")
        if high is not None and (value >= high if high_open else value > high):
            raise argparse.ArgumentTypeError(f"must be {'<' if high_open else '<='} {high:g}, got {text!r}")
        return value

    parse.__name__ = kind.__name__
    return parse


#: A finite number >= 0 (a cost weight, an angular speed, a noise level).
nonnegative_float = number_in(float, 0.0)
#: A whole number >= 0 (a seed: NumPy's generators take no negative one).
nonnegative_int = number_in(int, 0)
#: A seed: a whole number >= 0.
seed_value = nonnegative_int
#: ``--newton-iters``: K in 1 … :data:`MAX_NEWTON_ITERS`.
newton_iters_type = number_in(int, 1, MAX_NEWTON_ITERS)
#: ``--horizon``: 1 … :data:`MAX_HORIZON` steps.
horizon_steps = number_in(int, 1, MAX_HORIZON)

#: ``--option`` → :class:`~fvin_mpc.control.mpc.MPCSettings` field (``ipopt.…`` / ``rti.…``: a field of that
#: solver's options), its parser and help, for the settings a user may need to change on a new scene (every
#: one defaults to the scene's value).
MPC_OPTIONS: dict[str, tuple[str, Callable[[str], Any], str]] = {
    "--horizon": ("horizon", horizon_steps, f"MPC steps (1 … {MAX_HORIZON})"),
    "--energy-weight": ("terminal_energy_weight", nonnegative_float, "terminal energy-deficit weight W_E"),
    "--orientation-weight": ("orientation_weight", nonnegative_float, "stage weight on sin²(angle/2)"),
    "--omega-weight": ("omega_weight", nonnegative_float, "stage weight on |ω|²"),
    "--control-weight": ("control_weight", nonnegative_float, "stage weight on |u|²"),
    "--terminal-orientation-weight": ("terminal_orientation_weight", nonnegative_float,
                                      "terminal weight on sin²(angle/2)"),
    "--terminal-omega-weight": ("terminal_omega_weight", nonnegative_float, "terminal weight on |ω|²"),
    "--max-iter": ("ipopt.max_iter", number_in(int, 1),
                   "solver iterations per warm-started solve (ipopt, sqpmethod, fatrop)"),
    "--cold-max-iter": ("ipopt.cold_max_iter", number_in(int, 1),
                        "solver iterations per cold solve (ipopt, sqpmethod, fatrop)"),
    "--torque-reserve": ("torque_reserve", number_in(float, 0.0, 1.0, high_open=True),
                         "fraction of the torque range the plan keeps in reserve after its first control, in [0, 1) "
                         "(every solver)"),
}


def positive_float(text: str) -> float:
    """An option that must be a finite number above zero (``--duration``): refused while parsing, before any work."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}") from None
    if not 0.0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    return value


def duration_s(text: str) -> float:
    """``--duration``: seconds in (0, :data:`MAX_DURATION_S`], refused while parsing."""
    value = positive_float(text)
    if value > MAX_DURATION_S:
        raise argparse.ArgumentTypeError(f"must be <= {MAX_DURATION_S:g} s (an hour of closed loop), got {text!r}")
    return value


def positive_int(text: str) -> int:
    """An option that must be a whole number above zero (``--rti-cold-iter``): refused while parsing."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number > 0, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text!r}")
    return value


def add_scene_arguments(parser: argparse.ArgumentParser, newton_iters: bool = True) -> None:
    """``--scene``, ``--checkpoint``, ``--control-period`` and (unless ``newton_iters=False``) ``--newton-iters``."""
    parser.add_argument("--scene", default="pendulum", help="built-in scene name or MJCF path")
    parser.add_argument("--checkpoint", default=None,
                        help="shipped name or path (default: the scene's, <scene>_sign-invariant)")
    parser.add_argument("--control-period", type=positive_float, default=None,
                        help="seconds per control step (default: the checkpoint's step, else the scene's)")
    if newton_iters:
        parser.add_argument("--newton-iters", type=newton_iters_type, default=None,
                            help=f"K, 1 … {MAX_NEWTON_ITERS} (default: the model's)")


def add_mpc_arguments(parser: argparse.ArgumentParser) -> None:
    """The MPC settings of :data:`MPC_OPTIONS`, plus ``--hessian`` and ``--single-start``."""
    group = parser.add_argument_group("MPC settings (default: derived from the scene's scales and declaration)")
    for option, (_, kind, text) in MPC_OPTIONS.items():
        group.add_argument(option, type=kind, default=None, help=text)
    group.add_argument("--hessian", choices=["gauss-newton", "exact", "limited-memory"], default=None,
                       help="Lagrangian Hessian")
    group.add_argument("--single-start", action="store_true",
                       help="cold solves from one first guess instead of every guess (multi-start)")
    group.add_argument("--solver", choices=["ipopt", "sqpmethod", "fatrop", "rti"], default=None,
                       help="ipopt: solved to convergence every period (the reference); rti: one Gauss–Newton "
                            "SQP iteration per period (real-time iteration, bounded compute)")
    group.add_argument("--rti-dynamics", choices=["unrolled", "implicit"], default=None,
                       help="rti only: the dynamics constraint — unrolled: the exported step x⁺ = F(x, u) "
                            "linearized per stage; implicit: the step's equations between plan nodes, the "
                            "learned terms once per node (default: the scene's)")
    group.add_argument("--rti-feedback", choices=["qp", "prepared"], default=None,
                       help="rti only: what a period's call computes — qp: the QP at the measured state (default); "
                            "prepared: the preparation solves it at the predicted state and the call applies its "
                            "Riccati gains (a forward pass; one iteration per period)")
    group.add_argument("--rti-cold-iter", type=positive_int, default=None,
                       help="rti only: Gauss–Newton iterations per first guess of a cold call (a count: the C loop "
                            "runs it in full, the Python loop within its wall-clock cold budget; default: the "
                            "scene's)")
    group.add_argument("--rti-qp-iterations", type=positive_int, default=None,
                       help="rti only: interior-point iterations of the Riccati QP per Gauss–Newton iteration (a "
                            "count, the same in both loops; default: the scene's)")
    group.add_argument("--rti-qp-method", choices=["path", "mehrotra"], default=None,
                       help="rti only: the Riccati QP's interior-point method — path: path-following, one solve per "
                            "iteration (default); mehrotra: predictor-corrector, two solves of one factorization")
    group.add_argument("--rti-riccati-stage", choices=["auto", "generated", "kernel"], default=None,
                       help="rti only: the QP's Riccati stage — generated code, or the hand-written C kernel (auto, "
                            "the default: the kernel for a free body, where it is faster)")
    group.add_argument("--rti-stage-lanes", choices=["auto", "on", "off"], default=None,
                       help="rti only: linearize four stages at a time on the vector units (on), a stage at a time "
                            "(off), or on wherever it can run (auto, the default: compiled, every Jacobian renewed)")
    add_relinearize_argument(group)


def add_relinearize_argument(parser: Any) -> None:
    """``--rti-relinearize-every K``: :attr:`~fvin_mpc.control.mpc.RTIOptions.relinearize_every` (kept Jacobians)."""
    parser.add_argument("--rti-relinearize-every", type=positive_int, default=None,
                        help="rti only: a warm linearization renews the dynamics' Jacobians of the first stages, every "
                             "K-th, the last and those whose node moved, and keeps the previous ones, shifted with the "
                             "plan, for the rest (none older than K-1 periods; default 1: all renewed every time)")


def parse_latency(text: str) -> Any:
    """``--latency``: ``none``, ``measured`` or a fixed delay in seconds."""
    if text in ("none", "measured"):
        return text
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected none, measured or seconds, got {text!r}") from None
    if not 0.0 <= value < math.inf:
        raise argparse.ArgumentTypeError(f"a fixed latency must be finite seconds >= 0, got {text!r}")
    return value


def add_latency_argument(parser: argparse.ArgumentParser, default: str = "none") -> None:
    """``--latency none|measured|SECONDS`` (:func:`fvin_mpc.control.closed_loop.run_episode`)."""
    parser.add_argument("--latency", type=parse_latency, default=default,
                        help="none: the simulator waits for the controller (model-quality studies); measured: "
                             "each torque acts from the first MuJoCo sub-step after the controller's measured "
                             "compute time (real-time claims); SECONDS: a fixed delay (deterministic)")


def add_closed_loop_arguments(parser: argparse.ArgumentParser) -> None:
    """What a closed-loop command needs beyond the scene: ``--latency`` and the MPC settings."""
    add_latency_argument(parser)
    add_mpc_arguments(parser)


def mpc_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The :func:`~fvin_mpc.control.scene.scene_mpc_settings` overrides the options ask for."""
    given = {field: getattr(args, option[2:].replace("-", "_")) for option, (field, _, _) in MPC_OPTIONS.items()}
    given.update({"ipopt.hessian": args.hessian, "solver": args.solver, "rti.dynamics": args.rti_dynamics,
                  "rti.feedback": args.rti_feedback, "rti.cold_iter": args.rti_cold_iter,
                  "rti.qp_iterations": args.rti_qp_iterations, "rti.qp_method": args.rti_qp_method,
                  "rti.riccati_stage": args.rti_riccati_stage, "rti.stage_lanes": args.rti_stage_lanes,
                  "rti.relinearize_every": args.rti_relinearize_every})
    if args.single_start:
        given["cold_starts"] = ("rollout+",)
    if args.rti_feedback == "prepared":  # it applies one prepared solve: a preset's further iterations go
        given["rti.max_iter"] = 1
    overrides: dict[str, Any] = {}
    for path, value in given.items():
        if value is None:  # the scene's value stands
            continue
        solver, _, name = path.rpartition(".")
        if solver:
            overrides.setdefault(solver, {})[name] = value
        else:
            overrides[name] = value
    return overrides


def add_backend_arguments(parser: argparse.ArgumentParser,
                          workers_help: str = "parallel processes, or Ray actors with --backend ray") -> None:
    """``--workers``, ``--backend process|ray`` and ``--ray-address`` (:func:`fvin_mpc.studies.pool.run_tasks`)."""
    group = parser.add_argument_group("execution backend")
    group.add_argument("--workers", type=int, default=1, help=f"{workers_help} (default: %(default)s)")
    group.add_argument("--backend", choices=["process", "ray"], default="process",
                       help="process: this machine (serial, or --workers spawned processes; default); ray: --workers "
                            "Ray actors of one CPU each, on the cluster at --ray-address / $RAY_ADDRESS, else on a "
                            'local one (needs pip install -e ".[ray]")')
    group.add_argument("--ray-address", default=None,
                       help="Ray cluster to run on, e.g. auto or ray://head:10001 (default: $RAY_ADDRESS if set, "
                            "else a local cluster started for this run)")


def backend_options(args: argparse.Namespace) -> dict[str, Any]:
    """``backend`` and ``address`` for :func:`~fvin_mpc.studies.pool.run_tasks`; ``UsageError`` for
    ``--workers`` below 1, ``--ray-address`` without ``--backend ray``, or Ray missing."""
    if args.workers < 1:
        raise UsageError(f"--workers must be >= 1, got {args.workers}")
    if args.ray_address is not None and args.backend != "ray":
        raise UsageError("--ray-address needs --backend ray")
    if args.backend == "ray":
        import importlib.util

        if importlib.util.find_spec("ray") is None:
            raise UsageError('--backend ray needs Ray: pip install -e ".[ray]"')
    return {"backend": args.backend, "address": args.ray_address}


def exit_status(error: Exception) -> int:
    """Print a command's error on stderr; its exit status: 1 for tasks that failed while running
    (:class:`~fvin_mpc.studies.pool.TasksFailed`, their inputs listed), 2 for input the command refused."""
    import sys

    print("error: " + " ".join(str(error).split()), file=sys.stderr)
    return 1 if isinstance(error, TasksFailed) else 2


def _scene_identity(spec: Any) -> tuple[str, str]:
    """``("built-in", name)`` or ``("file", stem)``: a user's ``pendulum.xml`` is not the built-in ``pendulum``.
    Files are told apart by their stem only, as a checkpoint records the path it was trained from
    as written then (often relative to another working directory)."""

    built_in = any(spec is known for known in (*SCENES.values(), *FREE_BODY_SCENES.values()))
    return ("built-in" if built_in else "file", spec.name)


def _recorded_scene(scene: str) -> tuple[str, str]:
    """The identity of the scene a checkpoint's sidecar names (its MJCF may be gone: only the name is read)."""

    try:
        return _scene_identity(resolve_scene(scene))
    except SceneError:
        return ("file", scene)


def checked_scene_and_checkpoint(scene: Any, checkpoint: Any = None, true_model: bool = False,
                                 command: str | None = None, controls: int | None = None) -> tuple[Any, Any]:
    """The scene's declaration and, unless ``true_model``, the checkpoint that will plan on it, both
    checked before any work: the scene must exist, a checkpoint must be there, be a model of the
    scene's configuration space, and — when not named by the user — of this very scene.

    A checkpoint the user names (``--checkpoint``) may come from another scene of the same space (a
    model of one pendulum tried on another); one picked by default may not, since the user never
    chose it. With ``command`` (its name), the scene must be a body on a pivot, as the swing-up
    commands need; with ``controls``, the model must have that many. Returns ``(SceneSpec, Checkpoint | None)``.

    Raises:
        SceneError: the scene is neither built in nor an existing MJCF file.
        CheckpointError: no such checkpoint, an unreadable one, or one for another space or scene.
    """

    spec = existing_scene(scene)
    if command is not None and not spec.goal_set.attitude_at_rest:
        raise SceneError(f"scene {spec.name!r} is a free body and {command} needs a body on a pivot; "
                         "fly it with python -m fvin_mpc.fly")
    if true_model:
        return spec, None
    name = checkpoint if checkpoint is not None else spec.default_checkpoint
    if checkpoint is None and not checkpoint_exists(name):
        raise CheckpointError(
            f"scene {spec.name!r} has no trained model (no checkpoint {name!r}): collect data and train one "
            f"(python -m fvin_mpc.collect --scene {scene}, then python -m fvin_mpc.train --data data/{spec.name}.npz), "
            "pass --checkpoint, or plan with the closed form (--true-model)")
    loaded = load_checkpoint(name)
    # A model plans on the scene's states: a pivoted scene takes S³ or the SO(3) baseline (both on
    # (q, ω)), a free body R³ × S³.
    if loaded.space.layout != spec.space.layout:
        raise CheckpointError(
            f"checkpoint {name!r} is a model on {loaded.space.name} ({loaded.space.layout.name} states); scene "
            f"{spec.name!r} is on {spec.space.name} ({spec.space.layout.name} states), {spec.space.description}")
    if controls is not None and loaded.config.control_dim != controls:
        raise CheckpointError(f"checkpoint {name!r} has {loaded.config.control_dim} controls and scene {spec.name!r} "
                              f"has {controls}")
    if loaded.scene is not None and _recorded_scene(str(loaded.scene)) != _scene_identity(spec):
        if checkpoint is None:
            raise CheckpointError(
                f"the default checkpoint {name!r} models scene {loaded.scene!r}, not {str(scene)!r}: train one for "
                "this scene, or pass --checkpoint to plan with it anyway")
        print(f"note: checkpoint {name!r} was trained on scene {loaded.scene!r}, not {str(scene)!r}", file=sys.stderr)
    return spec, loaded


# ---------------------------------------------------------------------- output paths, checked before any work
#: What a ``--plot`` path may end in: the formats matplotlib writes (without a suffix it would append
#: ``.png`` and write beside the path the user gave).
PLOT_SUFFIXES = (".png", ".pdf", ".svg", ".jpg", ".jpeg", ".eps", ".tif", ".tiff", ".webp")
#: What a ``--video`` path may end in: the containers imageio's ffmpeg writes.
VIDEO_SUFFIXES = (".mp4", ".mov", ".mkv", ".avi", ".webm")


def _creatable(path: Path, option: str) -> None:
    """The nearest existing folder above ``path`` is a folder this process may write into (the folders
    between are created when the output is written)."""
    ancestor = Path(os.path.abspath(path)).parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise UsageError(f"{option} {path}: {ancestor} is a file, not a folder")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise UsageError(f"{option} {path}: cannot write into {ancestor} (permission denied)")


def given_path(path: Any) -> Path | None:
    """``None`` for an output the user switched off (``--plot ''``), else the path."""
    return None if path is None or str(path) in ("", ".") else Path(path)


def check_output_file(path: Any, option: str, suffixes: tuple[str, ...] | None = None,
                      force: bool | None = None) -> Path | None:
    """An output file a command will write, checked before any work: not a folder, ending in one of
    ``suffixes`` (when given), its folder creatable, and — with ``force`` given — not an existing file
    unless ``force`` (``None``: the command's own view of one run, a plot or a summary, is replaced).
    Returns the path, or ``None`` for an output switched off (:func:`given_path`).

    Raises:
        UsageError: naming the option and what to change.
    """
    path = given_path(path)
    if path is None:
        return None
    if path.is_dir():
        raise UsageError(f"{option} {path} is a folder; give a file path"
                         + (f" ending in {suffixes[0]}" if suffixes else ""))
    if suffixes and path.suffix.lower() not in suffixes:
        raise UsageError(f"{option} {path}: expected a file ending in {', '.join(suffixes)}")
    if force is False and path.exists():
        raise UsageError(f"{option} {path} exists; pass --force to replace it, or give another path")
    if path.exists() and not os.access(path, os.W_OK):
        raise UsageError(f"{option} {path}: the file is not writable (permission denied)")
    _creatable(path, option)
    return path


def check_output_folder(path: Any, option: str, force: bool, products: tuple[str, ...] = ()) -> Path:
    """A folder a command writes its files into, checked before any work: not a file, creatable, and —
    unless ``force`` — holding none of the files it would replace (``products``: names or glob patterns;
    none given: any file at all)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UsageError(f"{option} {path} is a file, not a folder")
    if path.is_dir() and not force:
        present = sorted({found.name for pattern in (products or ("*",)) for found in path.glob(pattern)})
        if present:
            raise UsageError(f"{option} {path} already holds {', '.join(present[:3])}"
                             f"{' …' if len(present) > 3 else ''}; pass --force to replace them, or "
                             f"give another folder")
    _creatable(path / "_", option)
    return path


def check_video_writer(path: Path | None, option: str = "--video") -> None:
    """A ``--video`` needs imageio's ffmpeg (the ``imageio[ffmpeg]`` package): checked before the episode."""
    import importlib.util

    if path is not None and (importlib.util.find_spec("imageio") is None
                             or importlib.util.find_spec("imageio_ffmpeg") is None):
        raise UsageError(f"{option} needs imageio with ffmpeg: pip install 'imageio[ffmpeg]'")


def check_craft_period(spec: Any, checkpoint: Any) -> None:
    """A free body flies at its scene's control period (its env's, :class:`~fvin_mpc.envs.QuadrotorEnv`), so a
    checkpoint that plans with it must step at that period: ``CheckpointError`` otherwise, before any build
    (a pivoted scene's env takes the checkpoint's step instead: :func:`~fvin_mpc.control.scene.scene_env`)."""
    if checkpoint is None or spec.goal_set.attitude_at_rest:
        return
    period = QuadrotorEnv(spec).dt
    step = float(checkpoint.config.step_size)
    if abs(step - period) > 1e-9:
        name = repr(str(checkpoint.path)) if checkpoint.path is not None else "the checkpoint"
        scene = spec.name if built_in_scene(spec) else spec.xml_path
        raise CheckpointError(f"checkpoint {name} steps at {step:g} s and scene {spec.name!r} is flown at "
                              f"{period:g} s: train a model on data collected from this scene (python -m "
                              f"fvin_mpc.collect --scene {scene}), or pass a checkpoint of that period")


def require_torch(command: str) -> None:
    """``UsageError`` naming the train extra when torch is missing: ``command`` trains models (the runtime
    needs no torch, so a plain install has none), checked before any work."""
    import importlib.util

    try:
        found = importlib.util.find_spec("torch") is not None
    except ValueError:  # sys.modules["torch"] is None: imports of it are blocked
        found = False
    if not found:
        raise UsageError(f"{command} trains models and needs torch, which is not installed: {INSTALL_TRAIN}")


def check_scene_env(spec: Any, body: str | None = None) -> None:
    """Build (and close) the scene's env once: every check of the physics it reads — the MJCF's
    (:func:`~fvin_mpc.envs.scenes.check_physics`) and its scales' (the envs') — before a command starts
    work that would otherwise meet them later."""
    env = RigidBodyEnv(spec, body=body) if spec.goal_set.attitude_at_rest else QuadrotorEnv(spec)
    env.close()



def check_rendering(env: Any, option: str = "--video") -> None:
    """Render one frame of ``env`` (made with ``render_mode="rgb_array"``) before the episode, so that a
    machine without an OpenGL context refuses ``--video`` at once instead of failing after the work."""
    import warnings

    try:
        with warnings.catch_warnings():  # GLFW warns before MuJoCo fails: the one line below says it all
            warnings.simplefilter("ignore")
            env.render()
    except Exception as error:  # MuJoCo's FatalError and the GL platforms' own errors: the reason, in one line
        reason = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise UsageError(f"{option}: MuJoCo cannot render here ({reason[:160]}); headless, set MUJOCO_GL=egl "
                         "(or osmesa)") from None
