"""A trained S3FVIN as a symbolic CasADi function, and compiled code cached on disk.

:func:`step_function` builds ``F(x, u) -> x_next`` (``x = [q (w,x,y,z), ω]``, 7 entries)
with ``K`` Newton iterations unrolled, by calling the same :func:`fvin_mpc.core.fvin.fvin_step`
and :class:`fvin_mpc.core.networks.LearnedTerms` code the torch model trains with — only the
leaf operations (:class:`fvin_mpc.core.backend.CasadiOps`) differ. Tests prove the two agree
to 1e-12 in value and 1e-8 in Jacobian.

:class:`ExportedModel` bundles the function with what a controller needs (step size,
control dimension, a NumPy evaluation of ``J``, ``U``, ``g`` for energies) and is made by
:func:`from_checkpoint` or :func:`from_rigid_body` (the closed-form ``--true-model``).

:func:`compile_functions` turns CasADi functions into one shared library with gcc and
loads it back with ``casadi.external``; the library is cached under :func:`cache_dir`,
named by the SHA-256 of the generated C source (which spells out the weights, ``K`` and
every option baked into the functions), so a second run with the same model and
settings does not compile again.

Free bodies (R³ × S³, ``docs/r3s3.md``): :func:`free_body_step_function` builds
``F(x[13], u[m]) -> (x_next[13], residual)`` with ``x = [x, q (w,x,y,z), v (world), ω (body)]``
from :func:`fvin_mpc.core.fvin_r3s3.step_state`; :func:`from_quadrotor` (closed form, read off the
MJCF by :func:`fvin_mpc.core.quadrotor.from_mujoco`) and :func:`from_checkpoint` (a learned R³ × S³
checkpoint) give the same :class:`ExportedModel` with the same call signature.

No torch here: the control runtime reads weights with safetensors/NumPy.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import casadi as ca
import numpy as np

from fvin_mpc.core import fvin, fvin_r3s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.checkpoint import Checkpoint, load_checkpoint
from fvin_mpc.core.networks import LearnedTerms, ModelConfig
from fvin_mpc.core.networks_r3s3 import CONFIGURATION_SPACE as R3S3, LearnedCombinedTerms, R3S3Config
from fvin_mpc.core.state import STATE_DIM, split_state

CA = get_ops("casadi")
NP = get_ops("numpy")



def step_function(terms: Any, step_size: float, newton_iters: int, name: str = "fvin_step") -> ca.Function:
    """``F(x[7], u[m]) -> (x_next[7], residual)`` as an SX function.

    ``residual`` is the final Newton residual in rad/s (:attr:`fvin_mpc.core.fvin.StepResult.residual`);
    it is large past the solvability limit ``h|ω| ≈ 1`` where ``x_next`` means nothing.

    Args:
        terms: :class:`~fvin_mpc.core.fvin.RigidBodyTerms` built on the CasADi backend.
        step_size: ``h`` (s).
        newton_iters: ``K`` Newton iterations, unrolled.
    """
    x = ca.SX.sym("x", STATE_DIM)
    u = ca.SX.sym("u", terms.control_dim)
    result = fvin.fvin_step(
        tuple(x[i] for i in range(4)), tuple(x[4 + i] for i in range(3)),
        tuple(u[i] for i in range(terms.control_dim)), terms, step_size, newton_iters, CA, with_residual=True,
    )
    x_next = ca.vertcat(*result.q, *result.omega)
    return ca.Function(name, [x, u], [x_next, result.residual], ["x", "u"], ["x_next", "residual"])


def free_body_step_function(terms: Any, step_size: float, newton_iters: int, force_rule: str = "trapezoid",
                            name: str = "fvin_r3s3_step") -> ca.Function:
    """``F(x[13], u[m]) -> (x_next[13], residual)`` of a free body (R³ × S³) as an SX function:
    :func:`fvin_mpc.core.fvin_r3s3.step_state` on :class:`~fvin_mpc.core.fvin_r3s3.CombinedTerms`
    built on the CasADi backend; ``residual`` as in :func:`step_function`."""
    x = ca.SX.sym("x", fvin_r3s3.FREE_STATE_DIM)
    u = ca.SX.sym("u", terms.control_dim)
    x_next, residual = fvin_r3s3.step_state(x, u, terms, step_size, newton_iters, CA, force_rule)
    return ca.Function(name, [x, u], [x_next, residual], ["x", "u"], ["x_next", "residual"])


def free_body_energy_function(terms: Any, name: str = "fvin_r3s3_energy") -> ca.Function:
    """``E(x[13]) -> ½vᵀMv + ½ωᵀJω + U(x, q)`` as an SX function, from the same terms as the step."""
    x = ca.SX.sym("x", fvin_r3s3.FREE_STATE_DIM)
    energy = fvin_r3s3.total_energy(*fvin_r3s3.split_free_state(x, CA), terms)
    return ca.Function(name, [x], [energy], ["x"], ["energy"])


def energy_function(terms: Any, name: str = "fvin_energy") -> ca.Function:
    """``E(x[7]) -> ½ωᵀJ(q)ω + U(q)`` as an SX function, from the same terms as the step."""
    x = ca.SX.sym("x", STATE_DIM)
    energy = fvin.total_energy(tuple(x[i] for i in range(4)), tuple(x[4 + i] for i in range(3)), terms)
    return ca.Function(name, [x], [energy], ["x"], ["energy"])


@dataclass(frozen=True)
class ExportedModel:
    """A discrete-time model ``x_{k+1} = F(x_k, u_k)`` ready for a controller.

    Attributes:
        step: ``F(x[n], u[m]) -> (x_next[n], residual)`` (see :func:`step_function`, and
            :func:`free_body_step_function` for ``n = 13``).
        step_size: ``h`` (s), the control period the model was trained at.
        newton_iters: ``K`` unrolled in ``step``.
        control_dim: ``m``.
        numpy_terms: the same ``J``, ``U``, ``g`` evaluated with NumPy (energies, LQR).
        name: a short label (checkpoint stem or ``"true:<body>"``).
        energy_function: ``E(x[n]) -> energy`` symbolic (see :func:`energy_function`), for
            costs on the model's energy (the MPC's ``terminal_energy_weight``).
        configuration_space: ``"S3"`` (a pivoted body, ``x = (q, ω)``, n = 7) or ``"R3xS3"``
            (a free body, ``x = (x, q, v, ω)``, n = 13).
        casadi_terms: the terms ``step`` was built from, on the CasADi backend, for controllers that
            impose the step's equations themselves (:mod:`fvin_mpc.control.implicit_dynamics`);
            ``None`` for a model with no rigid-body terms (e.g. an unstructured baseline).
    """

    step: ca.Function
    step_size: float
    newton_iters: int
    control_dim: int
    numpy_terms: Any
    name: str
    energy_function: ca.Function
    configuration_space: str = "S3"
    casadi_terms: Any = None

    @property
    def state_dim(self) -> int:
        """``n``: 7 for ``"S3"``, 13 for ``"R3xS3"``."""
        return fvin_r3s3.FREE_STATE_DIM if self.configuration_space == R3S3 else STATE_DIM

    def __call__(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, float]:
        """One numeric step: ``(x_next (n,), residual)``."""
        x_next, residual = self.step(x, u)
        return np.asarray(x_next, dtype=float).ravel(), float(residual)

    def rollout(self, x0: np.ndarray, controls: np.ndarray) -> np.ndarray:
        """States ``(T+1, n)`` under ``controls (T, m)`` from ``x0 (n,)``."""
        controls = np.asarray(controls, dtype=float).reshape(-1, self.control_dim)
        states = [np.asarray(x0, dtype=float)]
        for u in controls:
            states.append(self(states[-1], u)[0])
        return np.array(states)

    def energy(self, x: np.ndarray) -> float:
        """``½ωᵀJω + U(q)`` of the state ``x = (q, ω)`` ``(7,)`` (free body: ``½vᵀMv + ½ωᵀJω + U(x, q)``
        of ``(x, q, v, ω)`` ``(13,)``), in the model's own scale."""
        if self.configuration_space == R3S3:
            return float(fvin_r3s3.total_energy(*fvin_r3s3.split_free_state(np.asarray(x, dtype=float), NP),
                                                self.numpy_terms))
        q, omega = split_state(np.asarray(x, dtype=float))
        return float(fvin.total_energy(tuple(q), tuple(omega), self.numpy_terms))


def from_checkpoint(checkpoint: Checkpoint | str | Path, newton_iters: int | None = None) -> ExportedModel:
    """Export a checkpoint (object, shipped name or path) with ``K = newton_iters`` (default: the checkpoint's)."""
    if not isinstance(checkpoint, Checkpoint):
        checkpoint = load_checkpoint(checkpoint)
    label = checkpoint.path.name if checkpoint.path is not None else "checkpoint"
    if isinstance(checkpoint.config, R3S3Config):
        free: R3S3Config = checkpoint.config
        k = newton_iters or free.newton_iters
        return _free_body_model(LearnedCombinedTerms(checkpoint.weights, free, CA),
                                LearnedCombinedTerms(checkpoint.weights, free, NP), free.step_size, k, free.force_rule, label)
    config: ModelConfig = checkpoint.config
    k = newton_iters or config.newton_iters
    terms = LearnedTerms(checkpoint.weights, config, CA)
    return ExportedModel(
        step=step_function(terms, config.step_size, k), step_size=config.step_size, newton_iters=k,
        control_dim=config.control_dim, numpy_terms=LearnedTerms(checkpoint.weights, config, NP), name=label,
        energy_function=energy_function(terms), casadi_terms=terms,
    )


def from_rigid_body(body: Any, step_size: float, newton_iters: int = 2, name: str = "true") -> ExportedModel:
    """Export a closed-form :class:`~fvin_mpc.core.rigid_body.PivotedRigidBody` through the same step."""
    terms = body.terms(CA)
    return ExportedModel(
        step=step_function(terms, step_size, newton_iters), step_size=step_size, newton_iters=newton_iters,
        control_dim=body.control_dim, numpy_terms=body.terms(NP), name=name, energy_function=energy_function(terms),
        casadi_terms=terms,
    )


def from_quadrotor(body: Any, step_size: float, newton_iters: int = 2, force_rule: str = "trapezoid",
                   name: str = "true:quadrotor") -> ExportedModel:
    """Export a closed-form :class:`~fvin_mpc.core.quadrotor.Quadrotor` through the same R³ × S³ step
    (same signature as a learned R³ × S³ checkpoint's :func:`from_checkpoint`)."""
    return _free_body_model(body.terms(CA), body.terms(NP), step_size, newton_iters, force_rule, name)


def _free_body_model(terms: Any, numpy_terms: Any, step_size: float, newton_iters: int, force_rule: str,
                     name: str) -> ExportedModel:
    return ExportedModel(
        step=free_body_step_function(terms, step_size, newton_iters, force_rule), step_size=step_size,
        newton_iters=newton_iters, control_dim=terms.control_dim, numpy_terms=numpy_terms, name=name,
        energy_function=free_body_energy_function(terms), configuration_space=R3S3, casadi_terms=terms,
    )


def save_function(function: ca.Function, path: str | Path) -> Path:
    """Write ``function`` as a CasADi serialized file (``.casadi``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    function.save(str(path))
    return path


def load_function(path: str | Path) -> ca.Function:
    """Read a function written by :func:`save_function`; ``FileNotFoundError``/``ValueError`` if unusable."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"CasADi function file not found: {path}")
    try:
        return ca.Function.load(str(path))
    except RuntimeError as error:
        raise ValueError(f"{path}: not a readable CasADi function file ({str(error).splitlines()[-1]})") from None


# ----------------------------------------------------------------------------- compiled code
def cache_dir() -> Path:
    """Where compiled libraries live: ``$FVIN_MPC_CACHE``, else ``~/.cache/fvin_mpc``."""
    return Path(os.environ.get("FVIN_MPC_CACHE", Path.home() / ".cache" / "fvin_mpc"))


@dataclass(frozen=True)
class CompileReport:
    """How :func:`compile_functions` obtained its library.

    Attributes:
        library: path of the shared library.
        cached: ``True`` if it was already on disk (no compiler run).
        codegen_s: seconds spent generating C.
        compile_s: seconds spent in the C compiler (0 when cached).
    """

    library: Path
    cached: bool
    codegen_s: float
    compile_s: float


COMPILER_FLAGS: tuple[str, ...] = ("-O2", "-fPIC", "-shared")


def compile_functions(functions: Sequence[ca.Function], prefix: str, flags: Sequence[str] = COMPILER_FLAGS,
                      external_options: dict[str, Any] | None = None) -> tuple[dict[str, ca.Function], CompileReport]:
    """Generate C for ``functions``, compile it once into a cached shared library, load it.

    Returns ``({name: external function}, report)``; ``external_options`` are passed to
    ``casadi.external`` for every function. The cache key is the SHA-256 of the
    generated source plus the compiler flags and CasADi version, so anything that changes
    the math (weights, ``K``, horizon, cost weights) changes the key.

    Raises:
        RuntimeError: no C compiler, or compilation failed (with the compiler's message).
    """
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="fvin_mpc_codegen_") as workdir:
        generator = ca.CodeGenerator(f"{prefix}.c", {"with_header": False})
        for function in functions:
            generator.add(function)
        source_path = Path(generator.generate(workdir + os.sep))
        source = source_path.read_bytes()
        codegen_s = time.perf_counter() - start
        digest = hashlib.sha256(source + " ".join(flags).encode() + ca.__version__.encode()).hexdigest()[:20]
        library = cache_dir() / f"{prefix}_{digest}.so"
        cached = library.is_file()
        compile_s = 0.0
        if not cached:
            compiler = os.environ.get("CC", "gcc")
            if shutil.which(compiler) is None:
                raise RuntimeError(f"no C compiler {compiler!r} on PATH; install gcc or use compile='none'")
            library.parent.mkdir(parents=True, exist_ok=True)
            partial = library.with_suffix(f".{os.getpid()}.tmp")
            start = time.perf_counter()
            process = subprocess.run([compiler, *flags, str(source_path), "-o", str(partial), "-lm"],
                                     capture_output=True, text=True)
            compile_s = time.perf_counter() - start
            if process.returncode != 0:
                partial.unlink(missing_ok=True)
                raise RuntimeError(f"compiling {source_path.name} failed: {process.stderr.strip()[-2000:]}")
            os.replace(partial, library)  # atomic: concurrent runs never load a half-written file
    loaded = {function.name(): ca.external(function.name(), str(library), external_options or {})
              for function in functions}
    return loaded, CompileReport(library=library, cached=cached, codegen_s=codegen_s, compile_s=compile_s)
