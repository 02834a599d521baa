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

from fvin_mpc.core import fvin
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.checkpoint import Checkpoint, load_checkpoint
from fvin_mpc.core.networks import LearnedTerms, ModelConfig
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


def energy_function(terms: Any, name: str = "fvin_energy") -> ca.Function:
    """``E(x[7]) -> ½ωᵀJ(q)ω + U(q)`` as an SX function, from the same terms as the step."""
    x = ca.SX.sym("x", STATE_DIM)
    energy = fvin.total_energy(tuple(x[i] for i in range(4)), tuple(x[4 + i] for i in range(3)), terms)
    return ca.Function(name, [x], [energy], ["x"], ["energy"])


@dataclass(frozen=True)
class ExportedModel:
    """A discrete-time model ``x_{k+1} = F(x_k, u_k)`` ready for a controller.

    Attributes:
        step: ``F(x[7], u[m]) -> (x_next[7], residual)`` (see :func:`step_function`).
        step_size: ``h`` (s), the control period the model was trained at.
        newton_iters: ``K`` unrolled in ``step``.
        control_dim: ``m``.
        numpy_terms: the same ``J``, ``U``, ``g`` evaluated with NumPy (energies, LQR).
        name: a short label (checkpoint stem or ``"true:<body>"``).
        energy_function: ``E(x[7]) -> energy`` symbolic (see :func:`energy_function`), for
            costs on the model's energy (the MPC's ``terminal_energy_weight``).
    """

    step: ca.Function
    step_size: float
    newton_iters: int
    control_dim: int
    numpy_terms: Any
    name: str
    energy_function: ca.Function

    def __call__(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, float]:
        """One numeric step: ``(x_next (7,), residual)``."""
        x_next, residual = self.step(x, u)
        return np.asarray(x_next, dtype=float).ravel(), float(residual)

    def rollout(self, x0: np.ndarray, controls: np.ndarray) -> np.ndarray:
        """States ``(T+1, 7)`` under ``controls (T, m)`` from ``x0 (7,)``."""
        controls = np.asarray(controls, dtype=float).reshape(-1, self.control_dim)
        states = [np.asarray(x0, dtype=float)]
        for u in controls:
            states.append(self(states[-1], u)[0])
        return np.array(states)

    def energy(self, x: np.ndarray) -> float:
        """``½ωᵀJω + U(q)`` of the state ``x = (q, ω)`` ``(7,)``, in the model's own scale."""
        q, omega = split_state(np.asarray(x, dtype=float))
        return float(fvin.total_energy(tuple(q), tuple(omega), self.numpy_terms))


def from_checkpoint(checkpoint: Checkpoint | str | Path, newton_iters: int | None = None) -> ExportedModel:
    """Export a checkpoint (object, shipped name or path) with ``K = newton_iters`` (default: the checkpoint's)."""
    if not isinstance(checkpoint, Checkpoint):
        checkpoint = load_checkpoint(checkpoint)
    config: ModelConfig = checkpoint.config
    k = newton_iters or config.newton_iters
    terms = LearnedTerms(checkpoint.weights, config, CA)
    label = checkpoint.path.name if checkpoint.path is not None else "checkpoint"
    return ExportedModel(
        step=step_function(terms, config.step_size, k), step_size=config.step_size, newton_iters=k,
        control_dim=config.control_dim, numpy_terms=LearnedTerms(checkpoint.weights, config, NP), name=label,
        energy_function=energy_function(terms),
    )


def from_rigid_body(body: Any, step_size: float, newton_iters: int = 2, name: str = "true") -> ExportedModel:
    """Export a closed-form :class:`~fvin_mpc.core.rigid_body.PivotedRigidBody` through the same step."""
    terms = body.terms(CA)
    return ExportedModel(
        step=step_function(terms, step_size, newton_iters), step_size=step_size, newton_iters=newton_iters,
        control_dim=body.control_dim, numpy_terms=body.terms(NP), name=name, energy_function=energy_function(terms),
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
