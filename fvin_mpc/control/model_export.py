"""A trained S3FVIN as a symbolic CasADi function, and compiled code cached on disk.

:func:`step_function` builds ``F(x, u) -> x_next`` of a configuration space's step
(:class:`fvin_mpc.core.space.ConfigurationSpace`; S³: ``x = [q (w,x,y,z), ω]``, 7 entries) with ``K``
Newton iterations unrolled, by calling the same step and learned-terms code the torch model trains
with — only the leaf operations (:class:`fvin_mpc.core.backend.CasadiOps`) differ. Tests prove the
two agree to 1e-12 in value and 1e-8 in Jacobian, for every registered space.

:class:`ExportedModel` bundles the function with what a controller needs (step size,
control dimension, a NumPy evaluation of ``J``, ``U``, ``g`` for energies) and is made by
:func:`from_checkpoint` or :func:`from_rigid_body` (the closed-form ``--true-model``).

:func:`compile_functions` turns CasADi functions into one shared library with gcc and
loads it back with ``casadi.external``; the library is cached under :func:`cache_dir`,
named by the SHA-256 of the generated C source (which spells out the weights, ``K`` and
every option baked into the functions), so a second run with the same model and
settings does not compile again.

Every model carries its space: :func:`from_checkpoint` reads it from the checkpoint (S³, SO(3) or
R³ × S³ — a free body's ``x = [x, q (w,x,y,z), v (world), ω (body)]``, 13 entries) and
:func:`from_closed_form` takes it with a closed-form body; both go through :func:`from_terms`.

No torch here: the control runtime reads weights with safetensors/NumPy.
"""

from __future__ import annotations

import functools
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import casadi as ca
import numpy as np

from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.checkpoint import Checkpoint, load_checkpoint
from fvin_mpc.core.model_parameters import (
    GAIN_SCALE,
    LOW_RANK_PREFIX,
    ModelParameters,
    body_parameters,
    gain_scale_block,
    learned_parameters,
    low_rank_basis,
    parametrized_body,
)
from fvin_mpc.core.space import R3S3, S3, ConfigurationSpace, get_space, require

CA = get_ops("casadi")
NP = get_ops("numpy")


def step_function(terms: Any, step_size: float, newton_iters: int, name: str = "fvin_step",
                  space: ConfigurationSpace = S3, **options: Any) -> ca.Function:
    """``F(x[n], u[m]) -> (x_next[n], residual)`` of ``space``'s step as an SX function.

    ``residual`` is the final Newton residual in rad/s (:meth:`ConfigurationSpace.step`); it is
    large past the solvability limit ``h|ω| ≈ 1`` where ``x_next`` means nothing.

    Args:
        terms: the space's terms built on the CasADi backend.
        step_size: ``h`` (s).
        newton_iters: ``K`` Newton iterations, unrolled.
        space: the configuration space (default S³, ``x = (q, ω)``).
        options: the space's step options (R³ × S³: ``force_rule``).
    """
    x = ca.SX.sym("x", space.state_dim)
    u = ca.SX.sym("u", terms.control_dim)
    x_next, residual = space.step(x, u, terms, step_size, newton_iters, CA, **options)
    return ca.Function(name, [x, u], [x_next, residual], ["x", "u"], ["x_next", "residual"])


def energy_function(terms: Any, name: str = "fvin_energy", space: ConfigurationSpace = S3) -> ca.Function:
    """``E(x[n]) -> energy`` (``½ωᵀJ(q)ω + U(q)`` on S³) as an SX function, from the same terms as the step."""
    x = ca.SX.sym("x", space.state_dim)
    return ca.Function(name, [x], [space.energy(x, terms, CA)], ["x"], ["energy"])


@dataclass(frozen=True)
class ExportedModel:
    """A discrete-time model ``x_{k+1} = F(x_k, u_k)`` ready for a controller.

    Attributes:
        step: ``F(x[n], u[m]) -> (x_next[n], residual)`` (see :func:`step_function`).
        step_size: ``h`` (s), the control period the model was trained at.
        newton_iters: ``K`` unrolled in ``step``.
        control_dim: ``m``.
        numpy_terms: the same terms evaluated with NumPy (energies, LQR).
        name: a short label (checkpoint stem or ``"true:<body>"``).
        energy_function: ``E(x[n]) -> energy`` symbolic (see :func:`energy_function`), for
            costs on the model's energy (the MPC's ``terminal_energy_weight``).
        space: the configuration space whose states ``step`` maps (:mod:`fvin_mpc.core.space`).
        casadi_terms: the terms ``step`` was built from, on the CasADi backend, for controllers that
            impose the step's equations themselves (:mod:`fvin_mpc.control.implicit_dynamics`);
            ``None`` for a model with no rigid-body terms (e.g. an unstructured baseline).
        parameters: the model's run-time parameters (:mod:`fvin_mpc.core.model_parameters`); ``None``:
            the gain scale only.
        parametrize: ``p`` (a CasADi column of ``parameters``' size) → the CasADi terms reading ``p`` where
            ``casadi_terms`` has constants — the same terms code; ``None``: ``casadi_terms`` (no physical
            parameters).
        step_options: the space's step options ``step`` was built with (R³ × S³'s ``force_rule``).
    """

    step: ca.Function
    step_size: float
    newton_iters: int
    control_dim: int
    numpy_terms: Any
    name: str
    energy_function: ca.Function
    space: ConfigurationSpace = S3
    casadi_terms: Any = None
    parameters: ModelParameters | None = None
    parametrize: Callable[[Any], Any] | None = None
    step_options: Mapping[str, Any] = field(default_factory=dict)

    @property
    def model_parameters(self) -> ModelParameters:
        """The run-time parameters (at least the gain scale)."""
        return self.parameters or ModelParameters((gain_scale_block(self.control_dim),))

    def terms_at(self, p: Any) -> Any:
        """The CasADi terms with the parameters ``p`` (a CasADi column) in place of their constants."""
        return self.parametrize(p) if self.parametrize is not None else self.casadi_terms

    @functools.cached_property
    def parametric_step(self) -> ca.Function:
        """``F(x[n], u[m], p) -> (x_next[n], residual)``: :attr:`step` with the parameters as an input
        (with :attr:`ModelParameters.defaults` it computes what :attr:`step` does)."""
        x, u = ca.SX.sym("x", self.state_dim), ca.SX.sym("u", self.control_dim)
        p = ca.SX.sym("p", self.model_parameters.size)
        if self.casadi_terms is None:  # no terms to read p: only the gain scale
            x_next, residual = self.step(x, self.model_parameters.actuated(u, p))
        else:
            x_next, residual = self.step_on_terms(x, u, p)
        return ca.Function("fvin_step_p", [x, u, p], [x_next, residual], ["x", "u", "p"], ["x_next", "residual"])

    def step_on_terms(self, x: Any, u: Any, p: Any = None, wrap: Callable[[Any], Any] | None = None) -> tuple[Any, Any]:
        """``(x_next, residual)`` of the space's step on this model's terms, as CasADi expressions of ``x``,
        ``u`` — the expression :attr:`step` computes, or with the parameters ``p`` :attr:`parametric_step`'s;
        ``wrap`` (terms → terms) changes how the terms are read, e.g. their first-order expansions
        (:mod:`fvin_mpc.control.term_expansion`). Needs :attr:`casadi_terms`."""
        if self.casadi_terms is None:
            raise ValueError(f"model {self.name!r} has no rigid-body terms to step on")
        terms = self.casadi_terms if p is None else self.terms_at(p)
        actuated = u if p is None else self.model_parameters.actuated(u, p)
        return self.space.step(x, actuated, terms if wrap is None else wrap(terms), self.step_size,
                               self.newton_iters, CA, **self.step_options)

    @functools.cached_property
    def parametric_energy(self) -> ca.Function:
        """``E(x[n], p) -> energy``: :attr:`energy_function` with the parameters as an input."""
        x, p = ca.SX.sym("x", self.state_dim), ca.SX.sym("p", self.model_parameters.size)
        energy = self.energy_function(x) if self.casadi_terms is None else self.space.energy(x, self.terms_at(p), CA)
        return ca.Function("fvin_energy_p", [x, p], [energy], ["x", "p"], ["energy"])

    @property
    def state_dim(self) -> int:
        """``n``, the space's state size (7 for ``(q, ω)``, 13 for ``(x, q, v, ω)``)."""
        return self.space.state_dim

    @property
    def configuration_space(self) -> str:
        """The space's name (the tag in checkpoints)."""
        return self.space.name

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
        """The model's energy of a state ``x (n,)`` (``½ωᵀJω + U(q)`` of ``(q, ω)``; free body:
        ``½vᵀMv + ½ωᵀJω + U(x, q)`` of ``(x, q, v, ω)``), in the model's own scale."""
        return float(self.space.energy(np.asarray(x, dtype=float), self.numpy_terms, NP))

    def require(self, *supported: ConfigurationSpace, by: str) -> None:
        """``ValueError`` unless this model's space is one of ``supported`` — how a controller that
        is written for some spaces refuses the others, instead of running them as something else."""
        require(self.space, supported, by, f"model {self.name!r}")


def from_terms(space: ConfigurationSpace, casadi_terms: Any, numpy_terms: Any, step_size: float, newton_iters: int,
               name: str, parameters: ModelParameters | None = None, parametrize: Callable[[Any], Any] | None = None,
               **options: Any) -> ExportedModel:
    """An :class:`ExportedModel` of ``space``'s step on given terms (learned or closed form): the one
    place every model a controller gets is made. ``parameters``, ``parametrize``: its run-time parameters
    and the terms built on them (:class:`ExportedModel`; default: the gain scale only)."""
    return ExportedModel(
        step=step_function(casadi_terms, step_size, newton_iters, space=space, **options), step_size=step_size,
        newton_iters=newton_iters, control_dim=casadi_terms.control_dim, numpy_terms=numpy_terms, name=name,
        energy_function=energy_function(casadi_terms, space=space), space=space, casadi_terms=casadi_terms,
        parameters=parameters, parametrize=parametrize, step_options=dict(options),
    )


def parametrized_weights(weights: Mapping[str, Any], parameters: ModelParameters, p: Any) -> dict[str, Any]:
    """``weights`` with every parameter block replaced by the entries of the CasADi column ``p``, in the
    weight's shape (a matrix as a CasADi matrix, row-major): the learned terms built on it read ``p``."""
    replaced = dict(weights)
    for block in parameters.blocks:
        if block.name == GAIN_SCALE:
            continue
        entries = ca.vertcat(*parameters.block(p, block.name))
        if block.default.ndim == 2:
            rows, cols = block.default.shape
            entries = ca.reshape(entries, cols, rows).T  # CasADi reshapes column-major; p is row-major
        if block.name.startswith(LOW_RANK_PREFIX):  # W + C Σ_r V_rᵀ (model_parameters.low_rank_blocks)
            layer = block.name[len(LOW_RANK_PREFIX):]
            basis = low_rank_basis(weights[layer], block.default.shape[1])
            replaced[layer] = ca.DM(np.asarray(weights[layer], dtype=float)) + ca.mtimes(entries, ca.DM(basis))
            continue
        replaced[block.name] = entries
    return replaced


def from_checkpoint(checkpoint: Checkpoint | str | Path, newton_iters: int | None = None,
                    low_rank: int = 0) -> ExportedModel:
    """Export a checkpoint (object, shipped name or path) of any registered configuration space
    with ``K = newton_iters`` (default: the checkpoint's); ``low_rank`` ``r > 0`` adds rank-``r``
    corrections of the networks' output layers to the run-time parameters
    (:func:`~fvin_mpc.core.model_parameters.low_rank_blocks`)."""
    if not isinstance(checkpoint, Checkpoint):
        checkpoint = load_checkpoint(checkpoint)
    label = checkpoint.path.name if checkpoint.path is not None else "checkpoint"
    space, config, weights = checkpoint.space, checkpoint.config, checkpoint.weights
    parameters = learned_parameters(weights, config, low_rank)

    def parametrize(p: Any) -> Any:
        return space.learned_terms(parametrized_weights(weights, parameters, p), config, CA)

    return from_terms(space, space.learned_terms(weights, config, CA), space.learned_terms(weights, config, NP),
                      config.step_size, newton_iters or config.newton_iters, label, parameters=parameters,
                      parametrize=parametrize, **space.step_options(config))


def from_closed_form(space: ConfigurationSpace | str, body: Any, step_size: float, newton_iters: int = 2,
                     name: str = "true", **options: Any) -> ExportedModel:
    """Export a closed-form body of ``space`` (what :meth:`ConfigurationSpace.closed_form` reads off
    an MJCF: it has ``terms(ops)``) through the same step as a learned model."""
    space = get_space(space)
    parameters = body_parameters(body)
    return from_terms(space, body.terms(CA), body.terms(NP), step_size, newton_iters, name, parameters=parameters,
                      parametrize=lambda p: parametrized_body(body, parameters, p).terms(CA), **options)


def from_rigid_body(body: Any, step_size: float, newton_iters: int = 2, name: str = "true") -> ExportedModel:
    """Export a closed-form :class:`~fvin_mpc.core.rigid_body.PivotedRigidBody` through the S³ step."""
    return from_closed_form(S3, body, step_size, newton_iters, name)


def from_quadrotor(body: Any, step_size: float, newton_iters: int = 2, force_rule: str = "trapezoid",
                   name: str = "true:quadrotor") -> ExportedModel:
    """Export a closed-form :class:`~fvin_mpc.core.quadrotor.Quadrotor` through the R³ × S³ step
    (same signature as a learned R³ × S³ checkpoint's :func:`from_checkpoint`)."""
    return from_closed_form(R3S3, body, step_size, newton_iters, name, force_rule=force_rule)


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
        source_sha256: the SHA-256 of the generated source (hex): what another build of the same source
            (the C loop's ``fvc_model.c``) can be compared with.
    """

    library: Path
    cached: bool
    codegen_s: float
    compile_s: float
    source_sha256: str = ""


#: How a library of generated code is compiled, beside the target flags (:func:`generated_code_flags`).
COMPILER_FLAGS: tuple[str, ...] = ("-O2", "-fPIC", "-shared")
#: Set to ``1`` to compile generated code for the architecture's baseline instructions instead of this CPU's.
PORTABLE_ENV = "FVIN_MPC_PORTABLE"


@functools.cache
def generated_code_flags(compiler: str = "gcc") -> tuple[str, ...]:
    """The target flags of every library of generated code on this host: ``-march=native`` where
    ``compiler`` accepts it, else none; none with ``$FVIN_MPC_PORTABLE=1``.

    The generated functions are long straight-line scalar code; the host's instruction set (AVX, fused
    multiply–adds) takes 20–35 % off the learned linearization and the QP (docs/c-controller.md, "Compiled
    for this CPU"). Fused multiply–adds round differently from a multiplication and an addition, so the
    results move in the last bits against a baseline build; both loops (this module's libraries and
    :func:`fvin_mpc.control.c_controller.build_library`) use these flags, so they stay the same to the bit.
    A library built so runs only on CPUs like this one: :func:`compile_functions` puts :func:`host_cpu`
    in its cache key. Found once per process and compiler (the environment variable too)."""
    if os.environ.get(PORTABLE_ENV, "") not in ("", "0"):
        return ()
    if shutil.which(compiler) is None:
        return ()  # compiling fails later with the reason
    probe = subprocess.run([compiler, "-march=native", "-x", "c", "-E", "-o", os.devnull, os.devnull],
                           capture_output=True, text=True)
    if probe.returncode != 0:
        warnings.warn(f"{compiler} does not take -march=native ({probe.stderr.strip()[-200:]}); generated code is "
                      "compiled for the baseline instruction set (slower, the same results to rounding)",
                      RuntimeWarning, stacklevel=2)
        return ()
    return ("-march=native",)


@functools.cache
def host_cpu() -> str:
    """What identifies this CPU's instruction set for a cache key: the machine, and on Linux the first
    processor's model name and feature flags (``/proc/cpuinfo``)."""
    described = [platform.machine(), platform.processor()]
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        lines = []
    for key in ("model name", "flags", "Features"):  # x86 names its features "flags", Arm "Features"
        described += [line for line in lines if line.split(":")[0].strip() == key][:1]
    return "\n".join(described)


#: Options of every scalar (SX) function the real-time loop generates as C. Common subexpression
#: elimination: a stage built from several calls of the model repeats their shared terms (the step's
#: learned terms in its value and again in its derivatives), each computed once in the generated code. It
#: only merges identical operations on identical operands, so the results are the same to the bit
#: (``tests/test_rti.py``); ``python -m benchmarks.c_loop`` prints the instruction counts.
GENERATED_SX_OPTIONS: dict[str, Any] = {"cse": True}


class CompileCount:
    """How many times this process generated C and loaded it (:func:`compile_functions`, cached or not),
    and how many of those ran the compiler: what a change that must not recompile (the model
    parameters) is checked against."""

    calls = 0
    compiler_runs = 0


#: Flags of a hand-written kernel's object (its own translation unit; the host's target flags follow, as for
#: generated code): its loops over short vectors are unrolled at -O3 (:mod:`fvin_mpc.control.riccati_kernel`).
KERNEL_FLAGS: tuple[str, ...] = ("-O3", "-fPIC")


@dataclass(frozen=True)
class CKernel:
    """A hand-written or translated C function with CasADi's calling convention that generated code calls
    (declared there as an external function): its symbol and its whole source; for one translated from generated
    code (:mod:`fvin_mpc.control.lane_kernel`), the CasADi instructions of the scalar code it computes."""

    name: str
    source: str
    scalar_instructions: int | None = None


def compile_kernel(kernel: CKernel, compiler: str, flags: Sequence[str], directory: Path) -> Path:
    """``kernel``'s object file in ``directory``, compiled with ``flags``; ``RuntimeError`` with the compiler's
    message when it fails."""
    source = directory / f"{kernel.name}.c"
    source.write_text(kernel.source)
    target = directory / f"{kernel.name}.o"
    process = subprocess.run([compiler, *flags, "-c", str(source), "-o", str(target)], capture_output=True,
                             text=True)
    if process.returncode != 0:
        raise RuntimeError(f"compiling the kernel {kernel.name} failed: {process.stderr.strip()[-2000:]}")
    return target


def cached_kernel_object(kernel: CKernel, compiler: str, flags: Sequence[str]) -> Path:
    """``kernel``'s object compiled with ``flags``, kept under :func:`cache_dir` by its source, flags, compiler,
    CasADi version and :func:`host_cpu`: a kernel is compiled once for every library that links it (a lane
    kernel's standalone library, :func:`kernel_function`, and the loop's)."""
    key = "\n".join([kernel.source, " ".join(flags), compiler, ca.__version__, host_cpu()]).encode()
    target = cache_dir() / "kernels" / f"{kernel.name}_{hashlib.sha256(key).hexdigest()[:20]}.o"
    if not target.is_file():
        target.parent.mkdir(parents=True, exist_ok=True)
        CompileCount.compiler_runs += 1
        # compiled beside its place, then moved there whole: concurrent runs never link a half-written object
        with tempfile.TemporaryDirectory(prefix="partial_", dir=target.parent) as workdir:
            os.replace(compile_kernel(kernel, compiler, flags, Path(workdir)), target)
    return target


def kernel_function(kernel: CKernel) -> ca.Function:
    """``kernel`` as a CasADi function: the symbolic graphs call it (and the generated code calls its symbol);
    evaluated outside compiled code, from a library of its own, compiled and cached as the generated code's
    (:func:`compile_functions` with no generated function)."""
    _, report = compile_functions([], prefix=kernel.name, kernels=[kernel])
    return ca.external(kernel.name, str(report.library))


def write_generated_source(functions: Sequence[ca.Function], name: str, directory: str | Path) -> Path:
    """Write the C CasADi generates for ``functions`` as ``{name}.c`` and ``{name}.h`` into ``directory``; returns
    the ``.c``. One function for every library and folder of generated code: the same functions under the same
    name give the same text."""
    generator = ca.CodeGenerator(f"{name}.c", {"with_header": True})
    for function in functions:
        generator.add(function)
    return Path(generator.generate(str(directory) + os.sep))


def compile_functions(functions: Sequence[ca.Function], prefix: str, flags: Sequence[str] = COMPILER_FLAGS,
                      external_options: dict[str, Any] | None = None,
                      kernels: Sequence[CKernel] = (), source_name: str | None = None
                      ) -> tuple[dict[str, ca.Function], CompileReport]:
    """Generate C for ``functions``, compile it once into a cached shared library, load it.

    Returns ``({name: external function}, report)``; ``external_options`` are passed to
    ``casadi.external`` for every function. ``flags`` are followed by the host's target flags
    (:func:`generated_code_flags`). The cache key is the SHA-256 of the generated source plus the
    compiler flags, the CasADi version and, for a library built for this CPU, :func:`host_cpu`, so
    anything that changes the math (weights, ``K``, horizon, cost weights) changes the key, and a cache
    shared by machines of different CPUs never hands one of them another's instructions.

    ``kernels``: the hand-written C functions (:class:`CKernel`) the generated code calls, each compiled as its own
    object with :data:`KERNEL_FLAGS` and linked in; their sources are part of the key. ``source_name``: the
    generated source's name (default ``prefix``), which names its static functions: the text, and so the machine
    code, is that of any other source generated from the same functions under that name
    (:func:`write_generated_source`).

    Raises:
        RuntimeError: no C compiler, or compilation failed (with the compiler's message).
    """
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="fvin_mpc_codegen_") as workdir:
        source_path = write_generated_source(functions, source_name or prefix, workdir)
        source = source_path.read_bytes()
        codegen_s = time.perf_counter() - start
        compiler = os.environ.get("CC", "gcc")
        target = generated_code_flags(compiler)
        flags = (*flags, *target)
        key = source + " ".join(flags).encode() + ca.__version__.encode() + (host_cpu().encode() if target else b"")
        key += b"".join(kernel.source.encode() for kernel in kernels)
        digest = hashlib.sha256(key).hexdigest()[:20]
        library = cache_dir() / f"{prefix}_{digest}.so"
        cached = library.is_file()
        compile_s = 0.0
        CompileCount.calls += 1
        if not cached:
            CompileCount.compiler_runs += 1
            if shutil.which(compiler) is None:
                raise RuntimeError(f"no C compiler {compiler!r} on PATH; install gcc or use compile='none'")
            library.parent.mkdir(parents=True, exist_ok=True)
            partial = library.with_suffix(f".{os.getpid()}.tmp")
            start = time.perf_counter()
            objects = [str(cached_kernel_object(kernel, compiler, (*KERNEL_FLAGS, *target))) for kernel in kernels]
            process = subprocess.run([compiler, *flags, str(source_path), *objects, "-o", str(partial), "-lm"],
                                     capture_output=True, text=True)
            compile_s = time.perf_counter() - start
            if process.returncode != 0:
                partial.unlink(missing_ok=True)
                raise RuntimeError(f"compiling {source_path.name} failed: {process.stderr.strip()[-2000:]}")
            os.replace(partial, library)  # atomic: concurrent runs never load a half-written file
    loaded = {function.name(): ca.external(function.name(), str(library), external_options or {})
              for function in functions}
    return loaded, CompileReport(library=library, cached=cached, codegen_s=codegen_s, compile_s=compile_s,
                                 source_sha256=hashlib.sha256(source).hexdigest())
