"""Train a learned model on trajectory data (the library behind ``python -m fvin_mpc.train``).

One loop (:func:`train`) for every model: by default the model of the config's configuration space
(:func:`fvin_mpc.learning.model.model_for`: S³, the SO3FVIN baseline, the free-body R³ × S³ model),
or any model a ``model_factory`` makes (the MLP baseline).

Loss: multi-step rollout over windows of ``window`` steps, the sign-invariant
orientation error ``4(1 − ⟨q̂, q⟩²)`` (≈ squared angle error in rad²) plus
``omega_weight``·‖ω̂ − ω‖², averaged over windows and steps. Trajectories are split
into train/validation sets before windowing; training stops early once the
validation loss stops improving and returns the best weights seen. A plateau far above the
data's floor (the validation loss over :func:`hold_loss`, above ``poor_loss_ratio``) is not
convergence: it starts a fresh run from a new initialization (``restarts``, within the same
iteration and time limits), and a model that ends there is reported poor (``report["quality"]``).

Optimizers (``docs/training.md`` has measurements):

- ``"lm"`` (default): Levenberg–Marquardt on the stacked residuals. The loss is a
  sum of squares ``Σ r²`` with ``r`` = the three components of ``2 Im(q̄ ⊗ q̂)``
  (their squares sum to ``4(1 − ⟨q̂, q⟩²)`` for unit ``q̂, q``) and
  ``√omega_weight·(ω̂ − ω)``, scaled by ``1/√(windows·steps)``. Each iteration
  solves ``(JᵀJ + λ(diag JᵀJ + ε)) δ = −Jᵀr`` with the full-batch gradient ``Jᵀr``
  and the Gauss–Newton matrix ``JᵀJ`` estimated from ``jacobian_windows`` random
  windows (per-window Jacobians by ``torch.func``: ``vmap(jacrev(·))``). A step is
  accepted when it lowers the full-batch loss; ``λ`` shrinks after a success and
  grows after a failure. Tens of iterations where Adam needs a thousand.
- ``"lbfgs"``: full-batch L-BFGS with a strong-Wolfe line search.
- ``"adam"``: full-batch Adam, cosine-decayed learning rate (the former default).
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Callable, Literal, Mapping

import numpy as np

from fvin_mpc.core import s3
from fvin_mpc.core.data import Trajectories
from fvin_mpc.core.errors import UsageError
from fvin_mpc.core.networks import ModelConfig
from fvin_mpc.envs import RigidBodyEnv
from fvin_mpc.learning.timing import torch_threads

DEFAULT_DATA = Path("data/pendulum.npz")

Optimizer = Literal["lm", "lbfgs", "adam"]
OPTIMIZERS: tuple[str, ...] = ("lm", "lbfgs", "adam")
#: Upper bound on the iterations of each optimizer when ``TrainSettings.iterations`` is ``None``
#: (early stopping on the validation loss normally ends the run well before).
DEFAULT_ITERATIONS: dict[str, int] = {"lm": 60, "lbfgs": 300, "adam": 1500}
#: Iterations between validation evaluations when ``TrainSettings.eval_every`` is ``None``.
DEFAULT_EVAL_EVERY: dict[str, int] = {"lm": 1, "lbfgs": 1, "adam": 25}


@dataclass(frozen=True)
class TrainSettings:
    """Optimization settings.

    Attributes:
        optimizer: ``"lm"`` (Levenberg–Marquardt, default), ``"lbfgs"`` or ``"adam"``.
        iterations: most iterations (LM steps, L-BFGS steps or Adam steps); ``None``:
            :data:`DEFAULT_ITERATIONS` of the optimizer. Early stopping usually ends sooner.
        learning_rate: initial Adam learning rate (cosine-decayed to 5 % of it); Adam only.
        window: rollout length in steps of every training window.
        omega_weight: weight of ‖ω̂ − ω‖² against the orientation error.
        validation_fraction: share of trajectories held out.
        seed: seeds the initialization, the split and LM's Jacobian samples.
        eval_every: iterations between validation evaluations; ``None``: :data:`DEFAULT_EVAL_EVERY`.
        patience: stop after this many validation evaluations in a row without a relative
            improvement of at least ``min_improvement`` over the best one; ``0`` never stops early.
        min_improvement: relative decrease of the validation loss that counts as progress.
        target_loss: stop as soon as the validation loss is at most this (``None``: no target).
        jacobian_windows: windows sampled (anew each time) for LM's Gauss–Newton matrix.
        curvature_reuse: LM iterations that share one Gauss–Newton matrix (the gradient is
            always fresh); a stale matrix that yields no descent step is recomputed.
        threads: torch intra-op threads; ``None``: :func:`safe_thread_count` (1 on a busy machine).
        compile: ``torch.compile`` the step (Adam and L-BFGS only). Costs ≈ 75–200 s of
            compilation once, then ≈ 3× faster iterations: worth it only for runs of many
            minutes (``docs/training.md``).
        time_limit_s: stop after this many seconds of training (``None``: no limit).
        selection: which evaluated iteration's weights :func:`train` returns when it is given a
            ``measure``: ``"measure"`` — the lowest measure among the iterations whose validation loss
            is within ``selection_tolerance`` (relative) of the best; ``"validation"`` — the lowest
            validation loss (the measure is only recorded). Without a measure, the lowest validation loss.
        selection_tolerance: how much above the best validation loss a selected iteration may be
            (``1.0``: up to twice it).
        poor_loss_ratio: the validation loss, as a share of the data's hold loss (:func:`hold_loss`: the
            loss of a model that predicts no motion at all), above which a model is poor: far from
            the floor the data's noise and the model class leave. A plateau there is not convergence:
            it starts a fresh run (``restarts``), and once none are left the last run goes on
            without patience until it comes within the ratio or reaches a limit. A model returned
            above the ratio is reported poor (``report["quality"]``; the command says so on stderr).
            ``None``: every plateau is convergence (the former rule) and no verdict is given.
        restarts: most fresh runs (new initialization and Jacobian samples, the same split) after a
            plateau above ``poor_loss_ratio``; every run shares ``iterations`` and ``time_limit_s``,
            and the returned weights are the best of all runs'.
    """

    optimizer: Optimizer = "lm"
    iterations: int | None = None
    learning_rate: float = 1e-2
    window: int = 8
    omega_weight: float = 0.1
    validation_fraction: float = 0.1
    seed: int = 0
    eval_every: int | None = None
    patience: int = 2
    min_improvement: float = 1e-2
    target_loss: float | None = None
    jacobian_windows: int = 128
    curvature_reuse: int = 1
    threads: int | None = None
    compile: bool = False
    time_limit_s: float | None = None
    selection: Literal["measure", "validation"] = "measure"
    selection_tolerance: float = 1.0
    poor_loss_ratio: float | None = 5e-3
    restarts: int = 2

    def __post_init__(self) -> None:
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"unknown optimizer {self.optimizer!r}; expected one of {OPTIMIZERS}")
        if self.iterations is not None and self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")
        if self.eval_every is not None and self.eval_every < 1:
            raise ValueError(f"eval_every must be >= 1, got {self.eval_every}")
        if self.patience < 0 or self.jacobian_windows < 1 or self.curvature_reuse < 1:
            raise ValueError("patience must be >= 0, jacobian_windows and curvature_reuse >= 1")
        if self.threads is not None and self.threads < 1:
            raise ValueError(f"threads must be >= 1, got {self.threads}")
        if self.restarts < 0 or (self.poor_loss_ratio is not None
                                 and not (self.poor_loss_ratio > 0.0 and math.isfinite(self.poor_loss_ratio))):
            raise ValueError(f"restarts must be >= 0 and poor_loss_ratio a finite number > 0 (or None), got "
                             f"{self.restarts}, {self.poor_loss_ratio!r}")
        if self.selection not in ("measure", "validation") or not self.selection_tolerance >= 0.0:
            raise ValueError(f"selection must be 'measure' or 'validation' and selection_tolerance >= 0, got "
                             f"{self.selection!r}, {self.selection_tolerance!r}")
        if self.compile and self.optimizer == "lm":
            raise ValueError(
                "compile applies to the adam and lbfgs optimizers only (LM differentiates with torch.func)"
            )

    @property
    def max_iterations(self) -> int:
        return self.iterations if self.iterations is not None else DEFAULT_ITERATIONS[self.optimizer]

    @property
    def evaluation_interval(self) -> int:
        return self.eval_every if self.eval_every is not None else DEFAULT_EVAL_EVERY[self.optimizer]


# ---------------------------------------------------------------------------- machine
def available_cores() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def safe_thread_count(cores: int | None = None, load: float | None = None) -> int:
    """Intra-op threads that cannot oversubscribe the machine: the cores not busy by the
    1-minute load average (a core counts as busy once the load claims half of it), at least 1.

    Two threads on a 2-core machine already running one job collapse (40–170× slower than
    idle, ``docs/training.md``); one thread never does. At this model's sizes (tensors of a few thousand
    elements) extra threads gain little anyway (``docs/training.md``)."""
    cores = available_cores() if cores is None else cores
    load = os.getloadavg()[0] if load is None else load
    return max(1, min(cores, int(math.floor(cores - load + 0.5))))


# ---------------------------------------------------------------------------- scene facts
def scene_stem(scene: str) -> str:
    """A checkpoint-name stem for a scene: the built-in name, or an MJCF path's file stem
    (``/a/b/arm.xml`` → ``arm``)."""
    name = Path(str(scene)).name
    return name[:-4] if name.lower().endswith(".xml") else name


def default_checkpoint_stem(data: Trajectories, variant: str, directory: Path = Path("checkpoints")) -> Path:
    """``checkpoints/<scene stem>_<variant>`` for data collected in ``data.metadata['scene']``."""
    return directory / f"{scene_stem(data.metadata.get('scene', 'unknown'))}_{variant}"


def default_output_stem(data: Trajectories, data_path: str | Path, variant: str,
                        directory: Path = Path("checkpoints")) -> Path:
    """Where ``train`` writes by default: the scene's default checkpoint
    (:func:`default_checkpoint_stem`) for data in a file named after their scene (``data/arm.npz``
    from ``arm.xml``), else ``checkpoints/<data file stem>_<variant>``: other data of a scene
    (``data/arm_big.npz``) must not take the name the scene's commands load by default."""
    scene_named = default_checkpoint_stem(data, variant, directory)
    stem = Path(data_path).stem
    if stem == scene_stem(data.metadata.get("scene", "unknown")):
        return scene_named
    return directory / f"{stem}_{variant}"


def refuse_to_overwrite(stem: Path, force: bool) -> None:
    """``UsageError`` if a checkpoint (either of its files) is at ``stem`` and not ``force``: a default
    output name must not silently replace a shipped or earlier model."""

    existing = [path for path in (stem.parent / f"{stem.name}.json", stem.parent / f"{stem.name}.safetensors")
                if path.exists()]
    if existing and not force:
        raise UsageError(f"checkpoint {stem} exists ({existing[0]}); the default --out would replace it: "
                         "pass --out for a new name, or --force to replace it")


def _from_scene_env(metadata: Mapping[str, Any], read: Callable[[Any], Any]) -> Any:
    """``read(env)`` on the env of the data's scene (its metadata's ``scene`` and ``body``); ``None`` when
    there is no scene or its MJCF cannot be opened."""
    scene = metadata.get("scene")
    if not scene:
        return None
    try:
        env = RigidBodyEnv(scene=scene, body=metadata.get("body"))
    except (ValueError, FileNotFoundError, OSError):
        return None
    try:
        return read(env.unwrapped)
    finally:
        env.close()


def scene_has_joint_damping(metadata: Mapping[str, Any]) -> bool | None:
    """Whether the data's scene declares joint damping: the collection metadata's
    ``physics.joint_damping`` when recorded, else the scene's env (``physics.joint_damping``);
    ``None`` when neither can tell (no scene, or its MJCF is gone)."""
    physics = metadata.get("physics")
    if isinstance(physics, Mapping) and "joint_damping" in physics:
        return bool(physics["joint_damping"])
    return _from_scene_env(metadata, lambda env: bool(env.physics.joint_damping))


def scene_hinge_axis(metadata: Mapping[str, Any]) -> tuple[float, float, float] | None:
    """The hinge axis (body frame, unit) of the data's scene: the collection metadata's ``hinge_axis``
    when recorded (``None`` there: a ball joint), else the scene's env's; ``None`` when the joint is not
    a hinge or neither can tell (no scene, or its MJCF is gone)."""
    axis = metadata["hinge_axis"] if "hinge_axis" in metadata else _from_scene_env(metadata, lambda env: env.joint_axis)
    return None if axis is None else tuple(float(v) for v in axis)  # type: ignore[return-value]


def scene_vertical(metadata: Mapping[str, Any]) -> tuple[float, float, float] | None:
    """World "up" (unit, against gravity) when the data's scene moves the same however the world is
    turned about it (:attr:`~fvin_mpc.core.networks.ModelConfig.vertical`): a ball joint under
    gravity with no joint spring and no wind. ``None`` otherwise, or when the scene cannot be opened."""

    def read(env: Any) -> tuple[float, float, float] | None:
        model = env.model
        joint = int(model.body_jntadr[model.body(env.body_name).id])
        gravity = np.asarray(model.opt.gravity, dtype=float)
        if (env.joint_type != "ball" or not np.linalg.norm(gravity) > 0.0 or model.jnt_stiffness[joint] != 0.0
                or np.any(np.asarray(model.opt.wind) != 0.0)):
            return None
        return tuple(float(c) for c in -gravity / np.linalg.norm(gravity))  # type: ignore[return-value]

    return _from_scene_env(metadata, read)


# ---------------------------------------------------------------------------- loss
def rollout_loss(model: Any, q: Any, omega: Any, u: Any, omega_weight: float, step: Any = None) -> Any:
    """Mean multi-step loss of ``model`` on windows ``q (W, T+1, 4)``, ``ω (W, T+1, 3)``, ``u (W, T, m)``.

    ``step`` replaces ``model.step`` (e.g. by a compiled version of it)."""
    q_hat, omega_hat = model.rollout(q[:, 0], omega[:, 0], u, step=step)
    alignment = (q_hat[:, 1:] * q[:, 1:]).sum(-1)
    orientation = 4.0 * (1.0 - alignment**2)
    velocity = ((omega_hat[:, 1:] - omega[:, 1:]) ** 2).sum(-1)
    return orientation.mean() + omega_weight * velocity.mean()


def rollout_residuals(q_hat: Any, omega_hat: Any, q: Any, omega: Any, omega_weight: float) -> Any:
    """Residuals ``(W, T, 6)`` whose squares sum to ``W·T·rollout_loss`` (unit quaternions).

    Orientation: ``2 Im(q̄ ⊗ q̂)`` — twice the vector part of the rotation from the data's ``q``
    to the prediction ``q̂``, whose square is ``4(1 − ⟨q̂, q⟩²)`` (the real part is ``⟨q̂, q⟩``)
    — three residuals, the fewest with that sum of squares (the six of Lagrange's identity
    ``2(q̂ᵢqⱼ − q̂ⱼqᵢ)`` give the same ``JᵀJ`` and ``Jᵀr``; changing the sign of ``q`` or ``q̂``
    changes the residuals' sign, not their squares, ``JᵀJ`` or ``Jᵀr``); velocity:
    ``√omega_weight·(ω̂ − ω)``."""
    import torch

    a, b = q_hat[:, 1:].unbind(-1), q[:, 1:].unbind(-1)
    orientation = torch.stack(s3.imaginary(s3.multiply(s3.conjugate(b), a)), dim=-1)
    velocity = math.sqrt(omega_weight) * (omega_hat[:, 1:] - omega[:, 1:])
    return torch.cat([2.0 * orientation, velocity], dim=-1)


def split_data(data: Any, validation_fraction: float, seed: int) -> tuple[Any, Any]:
    """``(train, validation)`` subsets of whole trajectories of ``data`` (any data set with
    ``subset`` and ``num_trajectories``), the validation share drawn with ``seed``."""
    order = np.random.default_rng(seed).permutation(data.num_trajectories)
    n_val = max(1, int(round(validation_fraction * data.num_trajectories)))
    return data.subset(np.sort(order[n_val:])), data.subset(np.sort(order[:n_val]))


# ---------------------------------------------------------------------------- training
class _EarlyStopping:
    """Keeps a run's best validation loss and weights; says when to stop the run.

    ``poor_above``: the validation loss above which the run is far from the floor (``None``: never).
    A plateau there still stops the run (``plateau`` set: the caller may start a fresh one) unless
    ``persist``, when patience waits until the best loss comes below it."""

    def __init__(self, settings: TrainSettings, poor_above: float | None = None, persist: bool = False) -> None:
        self.settings = settings
        self.poor_above = poor_above
        self.persist = persist
        self.best = math.inf
        self.best_weights: dict[str, Any] | None = None
        self.stale = 0
        self.plateau = False
        self.reason = "iteration limit"

    @property
    def far(self) -> bool:
        """Whether the best loss so far is poor (:func:`is_poor`)."""
        return is_poor(self.best, self.poor_above)

    def update(self, validation: float, model: Any) -> bool:
        """Record a validation loss; ``True`` when training should stop."""
        if validation < self.best * (1.0 - self.settings.min_improvement):
            self.stale = 0
        else:
            self.stale += 1
        if validation < self.best:
            self.best = validation
            self.best_weights = {name: p.detach().clone() for name, p in model.weights.items()}
        target = self.settings.target_loss
        if target is not None and validation <= target:
            self.reason = f"validation loss reached the target {target:.3g}"
            return True
        if self.settings.patience and self.stale >= self.settings.patience and not (self.persist and self.far):
            self.plateau = True
            self.reason = (
                f"validation loss did not improve by {self.settings.min_improvement:.1%} in {self.stale} evaluations"
            )
            return True
        return False


class _LevenbergMarquardt:
    """LM on the flattened parameters; see the module docstring."""

    def __init__(self, model: Any, windows: tuple[Any, ...], settings: TrainSettings) -> None:
        import torch

        self.model, self.windows, self.settings = model, windows, settings
        self.parameters = list(model.weights.values())
        self.names = [f"model.weights.{name}" for name in model.weights]
        self.shapes = [p.shape for p in self.parameters]
        self.sizes = [p.numel() for p in self.parameters]
        count, steps = windows[2].shape[:2]
        self.scale = 1.0 / math.sqrt(count * steps)
        self.sample = min(settings.jacobian_windows, count)
        self.rng = np.random.default_rng(settings.seed)
        self.damping = 10.0
        self.gauss_newton: Any = None
        self.age = 0
        # The accepted trial's loss with its graph: the next iteration's forward pass.
        self._accepted_loss: Any = None
        self.rollout = _rollout_module(model)
        self._jacobian = torch.func.vmap(torch.func.jacrev(self._window_residuals), in_dims=(None, 0, 0, 0))

    def _window_residuals(self, theta: Any, q: Any, omega: Any, u: Any) -> Any:
        """Scaled residuals of one window (``q (T+1, 4)``…) as a flat vector, for ``torch.func``."""
        import torch

        params = {name: c.reshape(s) for name, c, s in zip(self.names, torch.split(theta, self.sizes), self.shapes)}
        q, omega, u = q[None], omega[None], u[None]
        q_hat, omega_hat = torch.func.functional_call(self.rollout, params, (q[:, 0], omega[:, 0], u))
        return self.scale * rollout_residuals(q_hat, omega_hat, q, omega, self.settings.omega_weight).reshape(-1)

    def _theta(self) -> Any:
        import torch

        return torch.cat([p.detach().reshape(-1) for p in self.parameters])

    def _assign(self, theta: Any) -> None:
        import torch

        with torch.no_grad():
            for p, c in zip(self.parameters, torch.split(theta, self.sizes)):
                p.copy_(c.reshape(p.shape))

    def _gauss_newton(self, theta: Any) -> Any:
        """``JᵀJ`` of the full training set, estimated from ``jacobian_windows`` random windows."""
        import torch

        count = self.windows[0].shape[0]
        index = torch.as_tensor(np.sort(self.rng.choice(count, self.sample, replace=False)))
        jacobian = self._jacobian(theta, *(w[index] for w in self.windows)).reshape(-1, theta.numel())
        return (count / self.sample) * (jacobian.T @ jacobian)

    def step(self) -> float:
        """One LM iteration; returns the full-batch training loss before it (``nan`` once no step helps)."""
        import torch

        model, settings = self.model, self.settings
        for p in self.parameters:
            p.grad = None
        loss = self._accepted_loss if self._accepted_loss is not None else rollout_loss(model, *self.windows,
                                                                                        settings.omega_weight)
        self._accepted_loss = None
        if not torch.isfinite(loss):
            raise FloatingPointError(f"training loss became {loss.item()}")
        loss.backward()
        half_gradient = 0.5 * torch.cat([p.grad.reshape(-1) for p in self.parameters])
        theta = self._theta()
        fresh = self.gauss_newton is None or self.age >= self.settings.curvature_reuse
        if fresh:
            self.gauss_newton, self.age = self._gauss_newton(theta), 0
        self.age += 1
        current = loss.item()
        while True:
            if self._try_steps(theta, half_gradient, current):
                return current
            if fresh:
                return math.nan
            # A stale Gauss–Newton matrix may be what fails: retry with a fresh one.
            self.gauss_newton, self.age, fresh = self._gauss_newton(theta), 1, True

    def _try_steps(self, theta: Any, half_gradient: Any, current: float) -> bool:
        """Damped steps until one lowers the full-batch loss (kept) or 12 tries fail (restored)."""
        import torch

        diagonal = self.gauss_newton.diagonal()
        floor = 1e-6 * float(diagonal.max()) + 1e-12
        for _ in range(12):
            system = self.gauss_newton + torch.diag(self.damping * (diagonal + floor))
            try:
                delta = -torch.linalg.solve(system, half_gradient)
            except RuntimeError:  # singular: more damping
                self.damping *= 4.0
                continue
            self._assign(theta + delta)
            # With its graph: an accepted trial's forward pass is the next iteration's, which
            # then needs only the backward (the parameters do not change in between).
            trial_loss = rollout_loss(self.model, *self.windows, self.settings.omega_weight)
            trial = trial_loss.item()
            if trial < current:
                self.damping = max(self.damping / 3.0, 1e-9)
                self._accepted_loss = trial_loss
                return True
            self.damping *= 4.0
        self._assign(theta)
        return False


def _rollout_module(model: Any) -> Any:
    """An ``nn.Module`` whose call is ``model.rollout`` (a ``functional_call`` target; parameters
    named ``model.weights.<name>``)."""
    from torch import nn

    class Rollout(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(self, q0: Any, omega0: Any, u: Any) -> Any:
            return self.model.rollout(q0, omega0, u)

    return Rollout()


def train(data: Any, config: Any, settings: TrainSettings, progress: bool = True,
          model_factory: Callable[..., Any] | None = None,
          window_tensors: Callable[[Any, Any, int], tuple[Any, ...]] | None = None,
          measure: Callable[[Any], float] | None = None) -> tuple[Any, dict[str, Any]]:
    """Train a model; returns ``(model, report)`` with losses, timings, threads and machine load.

    One loop for every model: ``data`` is anything with ``subset``, ``windows``, ``u``,
    ``control_period`` and ``num_trajectories`` (:class:`~fvin_mpc.core.data.Trajectories` of any
    space), the model anything with ``weights``
    (a ``ParameterDict``), ``parameters()`` and ``rollout(q0, rest0, controls, step=None) → (q, rest)``
    scored by :func:`rollout_loss`.

    Args:
        data, config, settings, progress: what to train on, the architecture, the optimization,
            whether to show a progress bar.
        model_factory: called as ``model_factory(config, seed=settings.seed)`` for the model to
            train (a model class will do); default :func:`~fvin_mpc.learning.model.model_for`.
        window_tensors: ``(model, subset, window) → tensors`` for :func:`rollout_loss` (``q``, the
            rest of the state, ``u``) from a split of ``data``; default :func:`trajectory_windows`.
        measure: ``model → float``, lower is better, evaluated with the validation loss (e.g. the
            swing measure, :func:`fvin_mpc.learning.swing_measure.swing_apex_error`'s
            ``swing_energy_error``): recorded in the history and, with ``settings.selection ==
            "measure"``, what picks the returned iteration (``report["selected"]``).
    """
    threads = settings.threads if settings.threads is not None else safe_thread_count()
    load_before = os.getloadavg()
    with torch_threads(threads):
        model, report = _train(data, config, settings, progress, model_factory, window_tensors or trajectory_windows,
                               measure)
    report["threads"] = threads
    report["threads_chosen"] = "given" if settings.threads is not None else "safe_thread_count"
    report["cpu_cores"] = available_cores()
    report["load_average_start"] = list(load_before)
    report["load_average_end"] = list(os.getloadavg())
    return model, report


def trajectory_windows(model: Any, data: Trajectories, window: int) -> tuple[Any, ...]:
    """``data``'s windows of ``window`` steps as float64 tensors in ``model``'s training layout:
    ``(q, rest, u)``, ``rest`` scaled by the model's ``rest_scale`` where it has one (a pivoted body's
    ``rest`` is ``ω``)."""
    import torch

    from fvin_mpc.learning.model import DTYPE

    q, rest, u = (torch.as_tensor(a, dtype=DTYPE) for a in data.windows(window))
    scale = getattr(model, "rest_scale", None)
    return q, rest if scale is None else rest * scale, u


def hold_loss(q: Any, rest: Any, omega_weight: float) -> float:
    """The loss :func:`rollout_loss` gives a model that predicts no motion (every step equal to the
    window's first state) on windows ``q (W, T+1, 4)``, ``rest (W, T+1, n)``: the size of what the data
    ask a model to predict, in the loss's own units. A model's loss over it is the share of the
    data's motion it leaves unexplained (a scale-free yardstick for any scene and space)."""
    alignment = (q[:, 1:] * q[:, :1]).sum(-1)
    velocity = ((rest[:, 1:] - rest[:, :1]) ** 2).sum(-1)
    return float((4.0 * (1.0 - alignment**2)).mean() + omega_weight * velocity.mean())


def restart_seed(seed: int, run: int) -> int:
    """The seed of fresh run ``run`` (0: ``seed`` itself) of a training seeded ``seed``."""
    if run == 0:
        return seed
    return int(np.random.SeedSequence([seed, run]).generate_state(1)[0] % (2**31 - 1))


def _train(data: Any, config: Any, settings: TrainSettings, progress: bool, model_factory: Callable[..., Any] | None,
           window_tensors: Callable[[Any, Any, int], tuple[Any, ...]],
           measure: Callable[[Any], float] | None = None) -> tuple[Any, dict[str, Any]]:
    import torch
    from tqdm.auto import tqdm

    from fvin_mpc.learning.model import model_for

    if abs(data.control_period - config.step_size) > 1e-12:
        raise ValueError(f"model step {config.step_size} differs from the data's control period {data.control_period}")
    if data.u.shape[2] != config.control_dim:
        raise ValueError(f"data has {data.u.shape[2]} controls, the model config {config.control_dim}")
    factory = model_factory or model_for
    torch.manual_seed(settings.seed)
    model = factory(config, seed=settings.seed)
    first_weights = {name: p.detach().clone() for name, p in model.weights.items()}
    # One split for every run: their validation losses are then comparable.
    train_set, validation_set = split_data(data, settings.validation_fraction, settings.seed)
    train_windows = window_tensors(model, train_set, settings.window)
    validation_windows = window_tensors(model, validation_set, settings.window)
    hold = (hold_loss(validation_windows[0], validation_windows[1], settings.omega_weight)
            if validation_windows[0].shape[-1] == 4 else None)
    poor_above = None if settings.poor_loss_ratio is None or hold is None else settings.poor_loss_ratio * hold

    iterations, eval_every = settings.max_iterations, settings.evaluation_interval
    history: list[dict[str, float]] = []
    candidates: list[tuple[dict[str, float], dict[str, Any]]] = []
    runs: list[dict[str, Any]] = []
    best: tuple[float, dict[str, Any] | None] = (math.inf, None)
    start, cpu_start = time.perf_counter(), time.process_time()
    completed = 0
    reason = "iteration limit"
    bar = tqdm(total=iterations, desc=f"train {config.variant} ({settings.optimizer})", disable=not progress)
    for run in range(settings.restarts + 1):
        seed = restart_seed(settings.seed, run)
        if run > 0:
            torch.manual_seed(seed)
            model = factory(config, seed=seed)
            if all(torch.equal(p, first_weights[name]) for name, p in model.weights.items()):
                break  # the factory starts every run alike (continued training): nothing fresh to try
        run_settings = replace(settings, seed=seed)
        last_run = run == settings.restarts
        stopping = _EarlyStopping(run_settings, poor_above, persist=last_run)
        advance, damping = _optimizer(model, run_settings, train_windows, iterations)
        first_iteration = completed
        while completed < iterations:
            loss = advance()
            completed += 1
            bar.update(1)
            if math.isnan(loss):  # LM: no damping made a step that lowers the loss
                stopping.reason = "no Levenberg–Marquardt step lowers the training loss (converged)"
                stopping.plateau = True
                break
            if not math.isfinite(loss):
                raise FloatingPointError(f"training loss became {loss} at iteration {completed}")
            if (completed - first_iteration) % eval_every == 0 or completed == iterations:
                with torch.no_grad():
                    validation_loss = rollout_loss(model, *validation_windows, settings.omega_weight).item()
                entry = {"iteration": completed, "train": loss, "validation": validation_loss,
                         "elapsed_s": time.perf_counter() - start, "cpu_s": time.process_time() - cpu_start,
                         "run": run}
                if damping is not None:
                    entry["damping"] = damping()
                if measure is not None:
                    entry["measure"] = float(measure(model))
                    candidates.append((entry, {name: p.detach().clone() for name, p in model.weights.items()}))
                history.append(entry)
                bar.set_postfix(train=f"{loss:.2e}", val=f"{validation_loss:.2e}", run=run)
                if stopping.update(validation_loss, model):
                    break
            if settings.time_limit_s is not None and time.perf_counter() - start > settings.time_limit_s:
                stopping.reason = f"time limit of {settings.time_limit_s:g} s"
                break
        runs.append({"run": run, "seed": seed, "iterations": completed - first_iteration,
                     "best_validation": stopping.best, "stopped": stopping.reason})
        reason = stopping.reason
        if stopping.best < best[0]:
            best = (stopping.best, stopping.best_weights)
        out_of_budget = completed >= iterations or stopping.reason.startswith("time limit")
        if not (stopping.plateau and stopping.far) or out_of_budget:
            break
    bar.close()
    if best[1] is not None:
        _assign_weights(model, best[1])
    selected = _select(candidates, best[0], settings, model, poor_above) if candidates else None
    seconds, cpu_seconds = time.perf_counter() - start, time.process_time() - cpu_start
    with torch.no_grad():
        final_train = rollout_loss(model, *train_windows, settings.omega_weight).item()
        final_validation = rollout_loss(model, *validation_windows, settings.omega_weight).item()
    restarts = len(runs) - 1
    if restarts:
        reason = f"{reason} (run {len(runs)}, after {restarts} restart{'s' * (restarts > 1)})"
    quality = _quality(final_validation, hold, poor_above, settings, selected, runs)
    report = {
        "optimizer": settings.optimizer,
        "iterations": completed,
        "stopped": reason,
        "settings": asdict(settings),
        "train_windows": int(train_windows[0].shape[0]),
        "validation_windows": int(validation_windows[0].shape[0]),
        "final_train_loss": final_train,
        "final_validation_loss": final_validation,
        "wall_clock_s": seconds,
        "cpu_s": cpu_seconds,
        "seconds_per_iteration": seconds / max(completed, 1),
        "history": history,
        "restarts": restarts,
        "runs": runs,
        "quality": quality,
    }
    if selected is not None:
        report["selected"] = selected
    return model, report


def _optimizer(model: Any, settings: TrainSettings, train_windows: tuple[Any, ...],
               iterations: int) -> tuple[Callable[[], float], Callable[[], float] | None]:
    """``(advance, damping)`` of ``settings.optimizer`` on ``model``: one iteration, returning the
    training loss before it, and LM's current ``λ`` (``None`` for the others)."""
    import torch

    # One step is compiled (not the whole rollout): compile time grows steeply with graph size.
    step = torch.compile(model.step, dynamic=False) if settings.compile else None

    def train_loss() -> Any:
        return rollout_loss(model, *train_windows, settings.omega_weight, step)

    if settings.optimizer == "lm":
        lm = _LevenbergMarquardt(model, train_windows, settings)
        return lm.step, lambda: lm.damping
    if settings.optimizer == "lbfgs":
        lbfgs = torch.optim.LBFGS(
            model.parameters(), lr=1.0, max_iter=4, history_size=50, line_search_fn="strong_wolfe"
        )

        def closure() -> Any:
            lbfgs.zero_grad()
            loss = train_loss()
            loss.backward()
            return loss

        return lambda: lbfgs.step(closure).detach().item(), None
    adam = torch.optim.Adam(model.parameters(), lr=settings.learning_rate)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(adam, iterations, eta_min=0.05 * settings.learning_rate)

    def advance() -> float:
        adam.zero_grad()
        loss = train_loss()
        loss.backward()
        adam.step()
        schedule.step()
        return loss.item()

    return advance, None


def _assign_weights(model: Any, weights: Mapping[str, Any]) -> None:
    import torch

    with torch.no_grad():
        for name, p in model.weights.items():
            p.copy_(weights[name])


def is_poor(validation: float, poor_above: float | None) -> bool:
    """Whether a validation loss is poor: above ``poor_above`` (``poor_loss_ratio`` × the hold loss; ``None``:
    nothing is). The one test the stop rule, the selection and the verdict share, so that a run the stop rule
    calls converged returns a model the verdict calls good."""
    return poor_above is not None and validation > poor_above


def _quality(validation: float, hold: float | None, poor_above: float | None, settings: TrainSettings,
             selected: dict[str, Any] | None, runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The verdict on the returned model (the selected iterate, whose validation loss is ``validation``):
    ``"poor"`` when :func:`is_poor`, ``"good"`` otherwise, ``"unknown"`` without a yardstick."""
    ratio = None if hold is None or not hold > 0.0 else validation / hold
    limit = settings.poor_loss_ratio
    verdict = "unknown" if ratio is None or limit is None else ("poor" if is_poor(validation, poor_above) else "good")
    quality: dict[str, Any] = {"verdict": verdict, "validation_loss": validation, "hold_loss": hold,
                               "loss_ratio": ratio, "poor_loss_ratio": limit, "runs": len(runs)}
    if selected is not None:
        quality.update(measure=selected.get("measure"), iteration=selected["iteration"], run=selected["run"])
    return quality


def quality_line(quality: Mapping[str, Any]) -> str:
    """One line saying why a model is poor (``report["quality"]`` of :func:`train`)."""
    measure = quality.get("measure")
    runs = quality.get("runs", 1)
    return (f"the trained model is poor: its validation loss {quality['validation_loss']:.3g} is "
            f"{quality['loss_ratio']:.1%} of the data's hold loss {quality['hold_loss']:.3g} (poor above "
            f"{quality['poor_loss_ratio']:.1%})"
            + (f", swing measure {measure:.3g} energy spans" if measure is not None else "")
            + f", best of {runs} run{'s' * (runs > 1)}; it is unlikely to control — try more --iterations, "
              "another --seed or more data")


def checkpoint_quality(metadata: Mapping[str, Any]) -> dict[str, Any] | None:
    """The training's verdict recorded in a checkpoint's metadata (``training.quality``); ``None`` for
    a checkpoint trained before verdicts were recorded, or not by :func:`train`."""
    training = metadata.get("training")
    quality = training.get("quality") if isinstance(training, Mapping) else None
    return dict(quality) if isinstance(quality, Mapping) else None


def _select(candidates: list[tuple[dict[str, float], dict[str, Any]]], best_validation: float,
            settings: TrainSettings, model: Any, poor_above: float | None = None) -> dict[str, Any]:
    """Load the weights ``settings.selection`` picks among the evaluated ``candidates`` into ``model``
    (already holding the best validation loss's); what was picked and why.

    When the best validation loss is not poor (:func:`is_poor`), neither is the pick: the measure chooses only
    among iterations below ``poor_above`` too. Otherwise the stop rule, which judged the best loss good and so
    made no fresh run, would return a model the verdict calls poor."""
    import torch

    by_validation = min(candidates, key=lambda c: c[0]["validation"])[0]
    summary = {"by": settings.selection, "best_validation_iteration": by_validation["iteration"],
               "best_validation_measure": by_validation["measure"]}
    if settings.selection == "validation":
        return {**summary, "iteration": by_validation["iteration"], "validation": by_validation["validation"],
                "measure": by_validation["measure"], "run": by_validation.get("run", 0)}
    limit = best_validation * (1.0 + settings.selection_tolerance)
    if not is_poor(best_validation, poor_above) and poor_above is not None:
        limit = min(limit, poor_above)
    entry, weights = min((c for c in candidates if c[0]["validation"] <= limit), key=lambda c: c[0]["measure"])
    with torch.no_grad():
        for name, p in model.weights.items():
            p.copy_(weights[name])
    return {**summary, "iteration": entry["iteration"], "validation": entry["validation"], "measure": entry["measure"],
            "validation_limit": limit, "run": entry.get("run", 0)}


def split_losses(weights: Mapping[str, Any], config: ModelConfig, data: Trajectories,
                 settings: TrainSettings = TrainSettings()) -> tuple[float, float]:
    """``(train, validation)`` rollout losses of a model with ``weights`` on ``data``, split and
    windowed as :func:`train` does with ``settings`` (e.g. a shipped checkpoint on new data)."""
    import torch

    from fvin_mpc.learning.model import DTYPE, S3FVIN

    model = S3FVIN(config, weights)
    losses = []
    for subset in split_data(data, settings.validation_fraction, settings.seed):
        windows = tuple(torch.as_tensor(a, dtype=DTYPE) for a in subset.windows(settings.window))
        with torch.no_grad():
            losses.append(rollout_loss(model, *windows, settings.omega_weight).item())
    return losses[0], losses[1]


def reference_iteration(variant: str, windows: int, steps: int, compile: bool, seed: int = 0) -> tuple[Any, float]:
    """The reference workload of ``bench train-speed``: one full-batch Adam iteration (rollout,
    loss, backward, step) on ``windows`` random windows of ``steps`` steps, hidden width 10.

    Returns ``(iteration, compile_s)``: a no-argument callable running one iteration, and the
    seconds the first (compiling) iteration took when ``compile`` (else 0)."""
    import torch

    from fvin_mpc.learning.model import DTYPE, S3FVIN

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(windows, steps + 1, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    batch = tuple(torch.as_tensor(a, dtype=DTYPE) for a in (q, rng.normal(size=(windows, steps + 1, 3)),
                                                          rng.uniform(-2, 2, size=(windows, steps, 1))))
    model = S3FVIN(ModelConfig(variant=variant, hidden_width=10), seed=seed)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    step = torch.compile(model.step, dynamic=False) if compile else None

    def iteration() -> None:
        optimizer.zero_grad()
        rollout_loss(model, *batch, 0.1, step).backward()
        optimizer.step()

    compile_s = 0.0
    if compile:
        start = time.perf_counter()
        iteration()  # compiles forward and backward
        compile_s = time.perf_counter() - start
    return iteration, compile_s


def package_versions() -> dict[str, str]:
    import importlib.metadata as md

    versions = {}
    for name in ("fvin_mpc", "torch", "numpy", "casadi", "mujoco", "gymnasium"):
        try:
            versions[name] = md.version(name)
        except md.PackageNotFoundError:
            versions[name] = "not installed"
    return versions
