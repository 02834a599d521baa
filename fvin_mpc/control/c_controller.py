"""The real-time controller's one loop: a self-contained C library, which Python drives and a robot links.

:func:`write_controller` writes a folder that builds with ``make`` (or ``cc -O2``): the CasADi
functions of a :class:`~fvin_mpc.control.rti.RealTimeMPC` — ``rti_linearize_blocks``, ``rti_predict``,
``rti_feedback``, ``rti_apply``, its :attr:`~fvin_mpc.control.rti.RealTimeMPC.loop_functions` — generated as C
(``fvc_model.c``) with the C functions they call (``fvc_kernels.c``: the lane kernels of the linearization and the
Riccati kernel where the controller uses them, :attr:`~fvin_mpc.control.rti.RealTimeMPC.loop_kernels`), a free
body's generated first guess (``fvc_goal.c``), the settings as constants (``fvc_config.h``) and the hand-written
driver (``fvin_controller.c``, package data under ``c_template/``): the cold multi-start, the warm iterations,
the preparation (shift + linearization), the fallback to the shifted plan, the restart, the disturbance
estimate, the reference and the model parameters as run-time inputs (``fvc_set_parameters``). A header
(``fvin_controller.h``), a ``Makefile`` and an example ``main.c`` come with it. Nothing of Python, NumPy,
CasADi or torch at run time.

Iteration counts and wall-clock budgets (``RTIOptions.cold_iter``, ``max_iter``, ``cold_budget_s``,
``budget_s``; the monotonic clock) bound a call.

:func:`cached_library` builds such a library once, cached by the SHA-256 of its sources and flags;
:class:`ControllerLibrary` loads it through ``ctypes`` — what :class:`~fvin_mpc.control.rti.RealTimeMPC` calls
every period, and its compiled functions through CasADi's ``external`` for studies and tests.

Refused, with the reason: a QP solver other than the generated Riccati one (:func:`check_exportable`).
"""

from __future__ import annotations

import ctypes
import hashlib
import math
import os
import shutil
import subprocess
import sys
from importlib import resources
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import casadi as ca
import numpy as np

from fvin_mpc.control.buffered import BufferedFunction
from fvin_mpc.control.model_export import (
    KERNEL_FLAGS,
    CompileCount,
    cache_dir,
    generated_code_flags,
    host_cpu,
    write_generated_source,
)
from fvin_mpc.core import s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.blocks import Hinge, single_attitude
from fvin_mpc.core.errors import FvinMpcError

#: What the library is built from: a :class:`fvin_mpc.control.rti.RealTimeMPC` (that module imports this one).
RealTimeMPC = Any
CA = get_ops("casadi")

#: The order a cold call tries ``cold_starts`` in (within ``rti.cold_budget_s``): from the ``"goal"``
#: guess the iteration reached IPOPT's optimum on the ball joint in ~10 iterations, from the
#: rollouts (ω clipped to the bound: large gaps) it diverged (docs/realtime.md).
RTI_COLD_ORDER = ("goal", "rollout+", "rollout-")
#: The cold guesses by the index the library reports (``fvc_cold_guess_name``).
COLD_GUESS_NAMES = {-1: None, **dict(enumerate(RTI_COLD_ORDER))}
#: The generated source of the loop's functions, ``fvc_model.c`` in the library's folder.
LOOP_SOURCE = "fvc_model"

#: The hand-written files copied next to the generated ones.
TEMPLATE_FILES = ("fvin_controller.c", "fvin_controller.h", "main.c", "Makefile")
#: The generated functions, in the order RealTimeMPC.loop_functions holds them.
LOOP_FUNCTION_NAMES = ("rti_linearize_blocks", "rti_predict", "rti_feedback", "rti_apply")
#: Flags of the shared library's objects, beside the host's target flags
#: (:func:`~fvin_mpc.control.model_export.generated_code_flags`), as for the package's other generated code.
LIBRARY_FLAGS = ("-O2", "-fPIC")
#: The hand-written driver is also compiled without fused multiply–adds: its sums (the goal control, the
#: disturbance estimate) round in source order, whatever the target — as when the reference episodes of
#: ``tests/data/loop_reference`` were recorded.
DRIVER_FLAGS = ("-ffp-contract=off",)
#: What ``fvc_feedback`` returns (fvin_controller.h).
STATUS_NAMES = {0: "rti", 1: "cold", 2: "previous-plan", -1: "bad-state", -2: "no-memory", -3: "bad-parameters",
                -4: "not-parametric", -5: "not-measured", -6: "bad-plan"}


class ControllerNotExportable(FvinMpcError, ValueError):
    """The controller's settings ask for something the library does not have (the message says what)."""


def check_compiler() -> None:
    """``ControllerNotExportable`` with the reason unless a C compiler is on PATH (``$CC``, default ``cc``): the
    real-time iteration runs as its generated C library."""
    compiler = os.environ.get("CC", "cc")
    if shutil.which(compiler) is None:
        raise ControllerNotExportable(f"the real-time iteration runs as generated C and needs a C compiler: no "
                                      f"{compiler!r} on PATH (install cc, gcc or clang, or set CC)")


def solver_settings(controller: RealTimeMPC) -> dict[str, Any]:
    """The real-time iteration's own settings the library reads, by their names here — the one place
    that knows where :class:`~fvin_mpc.control.mpc.MPCSettings` keeps them."""
    s = controller.settings.rti
    return {"cold_solver": s.cold_solver, "qp_solver": s.qp_solver, "dynamics": s.dynamics,
            "max_iter": s.max_iter, "cold_iter": s.cold_iter, "tol": s.tol,
            "qp_iterations": s.qp_iterations, "model_parameters": s.model_parameters,
            "feedback": s.feedback, "restart_speed": s.restart_speed, "cold_budget_s": s.cold_budget_s,
            "budget_s": s.budget_s}


def check_exportable(controller: RealTimeMPC, standalone: bool = True) -> None:
    """``ControllerNotExportable`` unless the library can run ``controller``'s settings; ``standalone``: a folder
    that runs without Python, which cannot hold an IPOPT cold start."""
    s = SimpleNamespace(**solver_settings(controller))
    if standalone and s.cold_solver != "rti":
        raise ControllerNotExportable(
            f"RTIOptions.cold_solver={s.cold_solver!r}: a cold start with IPOPT cannot be generated as C; "
            "use cold_solver='rti' (the real-time iteration's own multi-start cold start)")
    if s.qp_solver != "riccati":
        raise ControllerNotExportable(f"RTIOptions.qp_solver={s.qp_solver!r}: only the generated Riccati "
                                      "interior-point QP ('riccati') is generated as C")
    if "goal" in controller.settings.cold_starts and controller.goal_set.attitude_at_rest \
            and single_attitude(controller.layout) is None:
        raise ControllerNotExportable(f"the C driver's upright goal guess turns one attitude; the state "
                                      f"{controller.layout.name} has {len(controller.layout.quaternions)}: leave "
                                      "'goal' out of cold_starts")
    names = tuple(function.name() for function in controller.loop_functions)
    if names != LOOP_FUNCTION_NAMES:
        raise ControllerNotExportable(f"the controller's loop functions are {names}, the C driver calls "
                                      f"{LOOP_FUNCTION_NAMES}")


def goal_guess_function(controller: RealTimeMPC) -> ca.Function:
    """``rti_goal_guess(x0, R (n_x, N+1), u_s (m, N)) → (X, U)``: a free body's ``"goal"`` first guess
    (:meth:`~fvin_mpc.control.mpc.MPC._first_guess`) from :mod:`fvin_mpc.core.s3` on CasADi — the
    reference states, the attitude turned from the measured one to the reference's along the geodesic
    over the first third of the horizon, at rest in ``ω``; the controls the reference's targets."""
    layout, n, m = controller.layout, controller.horizon, controller.model.control_dim
    attitude = layout.attitude(by="the goal first guess")
    x0, references = ca.SX.sym("x0", layout.state_dim), ca.SX.sym("R", layout.state_dim, n + 1)
    targets = ca.SX.sym("u_s", m, n)
    q0 = tuple(ca.vertsplit(x0[attitude.quaternion]))
    columns = [x0]
    for k in range(1, n + 1):
        q_ref = tuple(ca.vertsplit(references[attitude.quaternion, k]))
        q_ref = s3.scale(ca.if_else(s3.dot(q_ref, q0) >= 0, 1.0, -1.0), q_ref)  # on q0's side of S³
        turn = s3.log(s3.multiply(s3.conjugate(q0), q_ref), CA)
        weight = min(max(k / max(1, n // 3), 0.0), 1.0)
        column = list(ca.vertsplit(references[:, k]))
        column[attitude.quaternion] = s3.multiply(q0, s3.exp(tuple(weight * t for t in turn), CA))
        column[attitude.omega] = [ca.SX(0)] * 3
        columns.append(ca.vertcat(*column))
    return ca.Function("rti_goal_guess", [x0, references, targets], [ca.horzcat(*columns), targets],
                       ["x0", "R", "u_s"], ["X", "U"])


def generated_functions(controller: RealTimeMPC) -> list[ca.Function]:
    """What ``fvc_model.c`` holds: the loop's functions (every output dense
    already: the driver passes plain arrays between them)."""
    for function in controller.loop_functions:
        sparse = [function.name_out(i) for i in range(function.n_out()) if not function.sparsity_out(i).is_dense()]
        if sparse:
            raise ValueError(f"{function.name()}: outputs {sparse} are sparse; the loop's functions are built dense")
    return list(controller.loop_functions)


def free_goal_guess(controller: RealTimeMPC) -> bool:
    return "goal" in controller.settings.cold_starts and not controller.goal_set.attitude_at_rest


def dense_outputs(function: ca.Function) -> ca.Function:
    """``function`` with every output dense (the driver passes plain arrays between the functions)."""
    if all(function.sparsity_out(i).is_dense() for i in range(function.n_out())):
        return function
    inputs = function.mx_in()
    return ca.Function(function.name(), inputs, [ca.densify(out) for out in function.call(inputs)],
                       function.name_in(), function.name_out())


def _c_string(text: str) -> str:
    if not all(c.isalnum() or c in "_[],." for c in text):
        raise ValueError(f"parameter name {text!r} is not a plain name")
    return f'"{text}"'


def _literal(values: Any) -> str:
    return ", ".join(repr(float(v)) for v in np.ravel(values))


def _seconds(value: float) -> str:
    return repr(float(value)) if math.isfinite(value) else "INFINITY"


def _int_array(name: str, values: list[int]) -> str:
    """A C array of ints (ISO C has no empty arrays: an unused ``-1`` where there are none)."""
    return f"static const int {name}[{max(1, len(values))}] = {{{', '.join(map(str, values or [-1]))}}};"


def block_table(layout: Any) -> list[str]:
    """The state's blocks as the C driver reads them (``fvin_controller.c``): where the rates start, every
    unit quaternion's first entry, the angular rates, the hinge angles, and the one body attitude (``-1`` where
    the state has none or several)."""
    quaternions = [quaternion.start for quaternion in layout.quaternions]
    angular = list(np.arange(layout.state_dim)[layout.angular_rates])
    hinges = [slot.position.start for slot in layout.slots if isinstance(slot.block, Hinge)]
    attitude = single_attitude(layout)
    return [
        f"#define FVC_NPOS {layout.positions.stop}",
        f"#define FVC_NQUAT {len(quaternions)}", _int_array("fvc_quaternions", quaternions),
        f"#define FVC_NANGULAR {len(angular)}", _int_array("fvc_angular", [int(i) for i in angular]),
        f"#define FVC_NHINGE {len(hinges)}", _int_array("fvc_hinges", hinges),
        f"#define FVC_ATTITUDE {-1 if attitude is None else attitude.quaternion.start}",
        f"#define FVC_ATTITUDE_OMEGA {-1 if attitude is None else attitude.omega.start}",
    ]


def config_header(controller: RealTimeMPC, example_state: np.ndarray) -> str:
    """``fvc_config.h``: the dimensions and the settings the driver reads, as C constants."""
    s, layout, m = controller.settings, controller.layout, controller.model.control_dim
    rti = SimpleNamespace(**solver_settings(controller))
    order = [RTI_COLD_ORDER.index(name) for name in sorted(s.cold_starts, key=RTI_COLD_ORDER.index)]
    names = controller.parameter_names
    items, item_size, point_size, renewed, renewed_further = controller.kept_jacobians
    lines = [
        "/* Generated by fvin_mpc.control.c_controller for model " + repr(controller.model.name) + ". */",
        "#ifndef FVC_CONFIG_H", "#define FVC_CONFIG_H",
        f"#define FVC_N {controller.horizon}", f"#define FVC_NS {layout.state_dim}",
        f"#define FVC_ND {layout.tangent_dim}", f"#define FVC_M {m}", *block_table(layout),
        f"#define FVC_IMPLICIT {int(rti.dynamics == 'implicit')}",
        f"#define FVC_FREE_GOAL_GUESS {int(free_goal_guess(controller))}",
        f"#define FVC_MAX_ITER {rti.max_iter}", f"#define FVC_COLD_ITER {rti.cold_iter}",
        f"#define FVC_N_COLD {len(order)}",
        f"#define FVC_TOL {rti.tol!r}", f"#define FVC_STEP_SIZE {controller.model.step_size!r}",
        f"#define FVC_COLD_BUDGET_S {_seconds(rti.cold_budget_s)}", f"#define FVC_BUDGET_S {_seconds(rti.budget_s)}",
        f"#define FVC_OMEGA_BOUND {controller.omega_bound!r}",
        f"#define FVC_INITIAL_TORQUE_FRACTION {s.initial_torque_fraction!r}",
        f"#define FVC_DISTURBANCE_GAIN {s.disturbance_gain!r}",
        f"#define FVC_DISTURBANCE_REGION_RAD {s.disturbance_region_rad!r}",
        f"#define FVC_DISTURBANCE_REGION_SPEED {s.disturbance_region_speed!r}",
        f"#define FVC_FREE_AXIS {int(s.free_axis is not None)}",
        f"#define FVC_RESTART_SPEED {rti.restart_speed!r}" if math.isfinite(rti.restart_speed)
        else "#define FVC_RESTART_SPEED INFINITY",
        f"static const double fvc_free_axis[3] = {{{_literal(s.free_axis or (0.0, 0.0, 0.0))}}};",
        f"#define FVC_NP {len(names)}", f"#define FVC_PARAMETRIC {int(rti.model_parameters)}",
        f"#define FVC_PREPARED_FEEDBACK {int(rti.feedback == 'prepared')}",
        f"#define FVC_KEPT_ITEMS {items}", f"#define FVC_KEPT_ITEM {item_size}", f"#define FVC_KEPT_POINT {point_size}",
        f"#define FVC_RELINEARIZE_EVERY {s.rti.relinearize_every}",
        f"static const double fvc_no_points[{items * point_size}] = {{{_literal(controller.nothing_kept[1].T)}}};",
        f"static const double fvc_relinearized[{items}] = {{{_literal(renewed)}}};",
        f"static const double fvc_all_renewed[{items}] = {{{_literal(np.ones(items))}}};",
        f"static const double fvc_renewed_further[{items}] = {{{_literal(renewed_further)}}};",
        f"static const double fvc_parameter_defaults[{len(names)}] = {{{_literal(controller.parameters)}}};",
        f"static const char *const fvc_parameter_names[{len(names)}] = {{{', '.join(map(_c_string, names))}}};",
        f"static const int fvc_cold_order[{len(order)}] = {{{', '.join(map(str, order))}}};",
        f"static const double fvc_torque_low[{m}] = {{{_literal(controller.torque_low)}}};",
        f"static const double fvc_torque_high[{m}] = {{{_literal(controller.torque_high)}}};",
        f"static const double fvc_goal_state[{layout.state_dim}] = {{{_literal(controller.goal_state)}}};",
        f"static const double fvc_example_state[{layout.state_dim}] = {{{_literal(example_state)}}};",
        "#endif", "",
    ]
    return "\n".join(lines)


def write_controller(controller: RealTimeMPC, directory: str | Path, example_state: Any = None,
                     standalone: bool = True) -> Path:
    """Write the C library of ``controller`` (module docstring) into ``directory``; returns it.

    ``example_state``: where ``main.c`` starts (default: the rest orientation at rest, or the goal
    state for a free body). ``standalone``: refuse what only the Python driver can add (an IPOPT cold start)."""
    check_exportable(controller, standalone)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    # the loop's functions under one source name: the same text wherever they are generated
    write_generated_source(generated_functions(controller), LOOP_SOURCE, directory)
    if free_goal_guess(controller):
        write_generated_source([dense_outputs(goal_guess_function(controller))], "fvc_goal", directory)
    else:
        (directory / "fvc_goal.c").write_text("/* No generated first guess: the driver's own (a pivoted body). */\n"
                                              "typedef int fvc_no_goal_guess;\n")
    (directory / "fvc_kernels.c").write_text(kernels_source(controller))
    if example_state is None:
        example_state = controller.goal_state.copy()
        if controller.rest_state is not None and controller.goal_set.attitude_at_rest:
            example_state = controller.rest_state.copy()
    (directory / "fvc_config.h").write_text(config_header(controller, np.asarray(example_state, dtype=float)))
    template = resources.files("fvin_mpc.control") / "c_template"
    for name in TEMPLATE_FILES:
        (directory / name).write_bytes((template / name).read_bytes())
    return directory


def kernels_source(controller: RealTimeMPC) -> str:
    """``fvc_kernels.c``: the sources of the controller's kernels in one translation unit (the lane kernels share
    their prelude, included once; the Riccati kernel undefines its macros at its end), or only a comment where it
    has none."""
    parts = ["/* The C functions fvc_model.c calls (fvin_mpc.control.lane_kernel, fvin_mpc.control.riccati_kernel); "
             "compiled with -O3. */\n", *(kernel.source for kernel in controller.loop_kernels)]
    if not controller.loop_kernels:
        parts.append("typedef int fvc_no_kernels;\n")  # ISO C wants a translation unit to declare something
    return "".join(parts)


def library_flags(compiler: str) -> tuple[str, ...]:
    """The flags :func:`build_library` compiles with on this host: :data:`LIBRARY_FLAGS` and the target flags
    of generated code (``-march=native`` where ``compiler`` takes it)."""
    return (*LIBRARY_FLAGS, *generated_code_flags(compiler))


def build_library(directory: str | Path, flags: tuple[str, ...] | None = None) -> Path:
    """Compile ``directory``'s controller into ``libfvin_controller.so`` with ``$CC`` (default ``cc``):
    the generated code with ``flags`` (default :func:`library_flags`), the driver with those and
    :data:`DRIVER_FLAGS`, the kernels with those and :data:`~fvin_mpc.control.model_export.KERNEL_FLAGS`, as
    the folder's ``Makefile`` does.

    Raises:
        RuntimeError: no C compiler, or compilation failed (with the compiler's message).
    """
    directory = Path(directory)
    compiler = os.environ.get("CC", "cc")
    CompileCount.compiler_runs += 1
    if shutil.which(compiler) is None:
        raise RuntimeError(f"no C compiler {compiler!r} on PATH; install one (cc, gcc, clang) or set CC")
    flags = library_flags(compiler) if flags is None else flags
    library = directory / "libfvin_controller.so"
    tag = f"{os.getpid()}.tmp"
    partial, driver, model, goal, kernels = (directory / f"{name}.{tag}"
                                             for name in ("libfvin_controller", "driver", "model", "goal", "kernels"))
    commands = ([compiler, *flags, *DRIVER_FLAGS, "-c", "fvin_controller.c", "-o", driver.name],
                [compiler, *flags, "-c", f"{LOOP_SOURCE}.c", "-o", model.name],
                [compiler, *flags, "-c", "fvc_goal.c", "-o", goal.name],
                [compiler, *flags, *KERNEL_FLAGS, "-c", "fvc_kernels.c", "-o", kernels.name],
                [compiler, *flags, "-shared", driver.name, model.name, goal.name, kernels.name, "-o", partial.name,
                 "-lm"])
    try:
        for command in commands:
            process = subprocess.run(command, cwd=directory, capture_output=True, text=True)
            if process.returncode != 0:
                partial.unlink(missing_ok=True)
                raise RuntimeError(f"compiling the controller in {directory} failed: {process.stderr.strip()[-2000:]}")
    finally:
        for obj in (driver, model, goal, kernels):
            obj.unlink(missing_ok=True)
    os.replace(partial, library)
    return library


def cached_library(controller: RealTimeMPC) -> tuple[Path, bool]:
    """The built library of ``controller`` and whether it was on disk already: under
    :func:`~fvin_mpc.control.model_export.cache_dir` ``/c_controller``, named by the SHA-256 of its sources,
    written and compiled only once."""
    check_compiler()
    CompileCount.calls += 1
    staging = cache_dir() / "c_controller" / f"staging_{os.getpid()}"
    shutil.rmtree(staging, ignore_errors=True)
    write_controller(controller, staging, standalone=False)
    digest = hashlib.sha256()
    for path in sorted(staging.iterdir()):
        digest.update(path.name.encode() + path.read_bytes())
    target = generated_code_flags(os.environ.get("CC", "cc"))
    flags = " ".join((*LIBRARY_FLAGS, *DRIVER_FLAGS, *KERNEL_FLAGS, *target))
    digest.update(flags.encode() + (host_cpu().encode() if target else b""))
    final = cache_dir() / "c_controller" / f"{controller.model.name.replace(':', '_')}_{digest.hexdigest()[:20]}"
    cached = (final / "libfvin_controller.so").is_file()
    if not cached:
        print(f"compiling the real-time controller of {controller.model.name} (once; cached in {final.parent})",
              file=sys.stderr, flush=True)
        build_library(staging)
        shutil.rmtree(final, ignore_errors=True)
        os.replace(staging, final)
    else:
        shutil.rmtree(staging, ignore_errors=True)
    return final / "libfvin_controller.so", cached


class _Status(ctypes.Structure):
    _fields_ = [("status", ctypes.c_int), ("iterations", ctypes.c_int), ("cold_guess", ctypes.c_int),
                ("last_step", ctypes.c_double), ("qp_mu", ctypes.c_double), ("step_residual", ctypes.c_double),
                ("budget", ctypes.c_int), ("restarted", ctypes.c_int),
                ("calls", ctypes.c_long), ("cold_calls", ctypes.c_long), ("fallbacks", ctypes.c_long),
                ("prepares", ctypes.c_long), ("bad_states", ctypes.c_long)]


def load_library(path: str | Path) -> ctypes.CDLL:
    """``path``'s controller library with its functions' argument types declared."""
    lib = ctypes.CDLL(str(path))
    pointer, double_p = ctypes.c_void_p, ctypes.POINTER(ctypes.c_double)
    lib.fvc_create.restype = pointer
    lib.fvc_free.argtypes = lib.fvc_reset.argtypes = lib.fvc_prepare.argtypes = lib.fvc_complete.argtypes = [pointer]
    lib.fvc_feedback.argtypes = [pointer, double_p, double_p]
    lib.fvc_measure.argtypes = [pointer, double_p]
    lib.fvc_solve.argtypes = [pointer, double_p]
    lib.fvc_solve_from.argtypes = [pointer, double_p, double_p, double_p]
    lib.fvc_feedback.restype = lib.fvc_measure.restype = lib.fvc_solve.restype = lib.fvc_solve_from.restype = \
        ctypes.c_int
    lib.fvc_set_reference.argtypes = [pointer, double_p, double_p, ctypes.c_int]
    lib.fvc_set_time.argtypes = [pointer, ctypes.c_double, ctypes.c_int]
    lib.fvc_time.argtypes = [pointer]
    lib.fvc_time.restype = ctypes.c_double
    lib.fvc_get_status.argtypes = [pointer, ctypes.POINTER(_Status)]
    lib.fvc_get_plan.argtypes = [pointer, double_p, double_p]
    lib.fvc_get_disturbance.argtypes = lib.fvc_get_goal_control.argtypes = [pointer, double_p]
    lib.fvc_set_disturbance.argtypes = [pointer, double_p]
    lib.fvc_get_cold_costs.argtypes = [pointer, double_p]
    lib.fvc_dims.argtypes = [ctypes.POINTER(ctypes.c_int)] * 4
    lib.fvc_cold_guess_name.restype = ctypes.c_char_p
    lib.fvc_cold_guess_name.argtypes = [ctypes.c_int]
    lib.fvc_parameter_count.restype = ctypes.c_int
    lib.fvc_parameter_name.restype = ctypes.c_char_p
    lib.fvc_parameter_name.argtypes = [ctypes.c_int]
    lib.fvc_default_parameters.argtypes = [double_p]
    lib.fvc_get_parameters.argtypes = [pointer, double_p]
    lib.fvc_set_parameters.argtypes = [pointer, double_p]
    lib.fvc_set_parameters.restype = ctypes.c_int
    return lib


def _pointer(array: np.ndarray) -> Any:
    return array.ctypes.data_as(ctypes.POINTER(ctypes.c_double))


class ControllerLibrary:
    """One controller of a built library (:func:`cached_library`), through ``ctypes``: every call of the loop
    (``feedback``, ``measure``/``solve``/``solve_from``, ``prepare``, ``reset``, the clock, the reference, the
    model parameters) and what it reports (``status``, ``plan``, ``disturbance``, ``cold_costs``). Arrays go
    through preallocated buffers: a ctypes pointer costs microseconds to make, and the feedback is timed.

    ``controller``: the :class:`~fvin_mpc.control.rti.RealTimeMPC` it was built from, whose dimensions and
    model parameters' names the library must have.
    """

    def __init__(self, path: str | Path, controller: RealTimeMPC) -> None:
        self.path = Path(path)
        self._lib = load_library(self.path)
        dims = [ctypes.c_int() for _ in range(4)]
        self._lib.fvc_dims(*[ctypes.byref(d) for d in dims])
        ns, _, m, n = (d.value for d in dims)
        layout, horizon = controller.layout, controller.horizon
        if (ns, m, n) != (layout.state_dim, controller.model.control_dim, horizon):
            raise ValueError(f"{self.path}: a controller of {ns} states, {m} controls, horizon {n}, not "
                             f"{layout.state_dim}, {controller.model.control_dim}, {horizon}")
        count = self._lib.fvc_parameter_count()
        names = tuple(self._lib.fvc_parameter_name(i).decode() for i in range(count))
        if names != controller.parameter_names:
            raise ValueError(f"{self.path}: model parameters {names}, the controller has {controller.parameter_names}")
        self._handle = ctypes.c_void_p(self._lib.fvc_create())
        if not self._handle.value:
            raise MemoryError("fvc_create: out of memory")
        self._x, self._u = np.zeros(ns), np.zeros(m)
        self._x_pointer, self._u_pointer = _pointer(self._x), _pointer(self._u)
        self._states, self._controls = np.zeros((n + 1, ns)), np.zeros((n, m))
        self._d, self._p, self._costs = np.zeros(m), np.zeros(count), np.zeros(len(RTI_COLD_ORDER))
        self._status = _Status()
        self._functions: dict[str, BufferedFunction] = {}

    def __del__(self) -> None:
        handle = getattr(self, "_handle", None)
        if handle is not None and handle.value:
            self._lib.fvc_free(handle)
            handle.value = None

    def function(self, name: str) -> BufferedFunction:
        """The library's compiled CasADi function ``name``, callable through buffers."""
        if name not in self._functions:
            self._functions[name] = BufferedFunction(ca.external(name, str(self.path)))
        return self._functions[name]

    # ------------------------------------------------------------------ a call
    def _checked(self, status: int) -> np.ndarray:
        if status < 0:
            raise ValueError(f"the controller refused the state {self._x} ({STATUS_NAMES[status]})")
        return self._u.copy()

    def feedback(self, x: Any) -> np.ndarray:
        """The control for the measured state ``x``: one C call."""
        self._x[:] = x
        return self._checked(self._lib.fvc_feedback(self._handle, self._x_pointer, self._u_pointer))

    def measure(self, x: Any) -> str:
        """The call's first half (``fvc_measure``): ``"cold"`` or ``"warm"``."""
        self._x[:] = x
        status = self._lib.fvc_measure(self._handle, self._x_pointer)
        self._checked(status)
        return "cold" if status == 1 else "warm"

    def solve(self) -> np.ndarray:
        """The call's second half: the library's own cold start or warm iterations."""
        return self._checked(self._lib.fvc_solve(self._handle, self._u_pointer))

    def solve_from(self, states: Any, controls: Any) -> np.ndarray:
        """A cold call's second half from a given plan (improved by one iteration)."""
        states = np.ascontiguousarray(states, dtype=float).reshape(self._states.shape)
        controls = np.ascontiguousarray(controls, dtype=float).reshape(self._controls.shape)
        status = self._lib.fvc_solve_from(self._handle, _pointer(states), _pointer(controls), self._u_pointer)
        if status == -6:
            raise ValueError("the cold plan handed to the controller is not finite")
        return self._checked(status)

    def prepare(self) -> None:
        self._lib.fvc_prepare(self._handle)

    def complete(self) -> None:
        self._lib.fvc_complete(self._handle)

    def reset(self) -> None:
        self._lib.fvc_reset(self._handle)

    # ------------------------------------------------------------------ the clock and the reference
    def time(self) -> float:
        return float(self._lib.fvc_time(self._handle))

    def set_time(self, t: float, time_varying_reference: bool) -> None:
        self._lib.fvc_set_time(self._handle, float(t), int(time_varying_reference))

    def set_reference(self, states: Any, scales: Any, new_reference: bool) -> None:
        states = np.ascontiguousarray(states, dtype=float).reshape(self._states.shape)
        scales = np.ascontiguousarray(scales, dtype=float).reshape(-1)[:self._controls.shape[0]]
        self._lib.fvc_set_reference(self._handle, _pointer(states), _pointer(scales), int(new_reference))

    # ------------------------------------------------------------------ what it reports
    def status(self) -> _Status:
        self._lib.fvc_get_status(self._handle, ctypes.byref(self._status))
        return self._status

    def plan(self) -> tuple[np.ndarray, np.ndarray]:
        self._lib.fvc_get_plan(self._handle, _pointer(self._states), _pointer(self._controls))
        return self._states.copy(), self._controls.copy()

    def disturbance(self) -> np.ndarray:
        self._lib.fvc_get_disturbance(self._handle, _pointer(self._d))
        return self._d.copy()

    def set_disturbance(self, d: Any) -> None:
        self._d[:] = d
        self._lib.fvc_set_disturbance(self._handle, _pointer(self._d))

    def goal_control(self) -> np.ndarray:
        self._lib.fvc_get_goal_control(self._handle, _pointer(self._d))
        return self._d.copy()

    def cold_costs(self) -> dict[str, float]:
        """Each first guess's score on the last cold call (the guesses tried)."""
        self._lib.fvc_get_cold_costs(self._handle, _pointer(self._costs))
        return {name: float(cost) for name, cost in zip(RTI_COLD_ORDER, self._costs) if not math.isnan(cost)}

    def counters(self) -> dict[str, int]:
        status = self.status()
        return {name: int(getattr(status, name)) for name in ("calls", "cold_calls", "fallbacks", "prepares",
                                                              "bad_states")}

    # ------------------------------------------------------------------ model parameters
    def parameters(self) -> np.ndarray:
        self._lib.fvc_get_parameters(self._handle, _pointer(self._p))
        return self._p.copy()

    def set_parameters(self, vector: Any) -> None:
        vector = np.ascontiguousarray(vector, dtype=float)
        status = self._lib.fvc_set_parameters(self._handle, _pointer(vector))
        if status == -4:
            raise ValueError("this controller has its model parameters baked in (rti.model_parameters=False); "
                             "build it with rti.model_parameters=True to change them at run time")
        if status != 0:
            raise ValueError(f"the controller refused the model parameters {vector} ({STATUS_NAMES[status]})")
