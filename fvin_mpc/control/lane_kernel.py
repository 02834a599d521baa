"""A stage function mapped over the horizon, four stages at a time on the vector units: CasADi's C, in lanes.

The real-time iteration linearizes every stage of its plan with the same scalar function (the dynamics'
gap and ``[A B]``, :func:`~fvin_mpc.control.linearization.unrolled_stage_function`; the cost's Gauss–Newton model).
CasADi generates it as straight-line scalar C and maps it with a loop of calls: one double at a time, while
the CPU's vector units hold four. :func:`lane_map_kernel` translates that C line by line into the same code on
vectors of four doubles (``c_kernels/lanes_prelude.c``: GCC's and Clang's vector extension), each lane one
stage, and wraps it in a kernel that runs the horizon four stages at a time — the ``map`` of the function as
a :class:`~fvin_mpc.control.model_export.CKernel` the generated linearization calls, in both loops alike.

What stays the same: every operation is the scalar one in each lane (IEEE ``+ − × ÷ √`` and libm's functions
lane by lane), so a lane computes what the scalar function computes, but for ``tanh``: libm's scalar ``tanh``,
four calls per vector, takes more than half of a learned stage's time in lanes, and the prelude computes it on whole
vectors instead (within 4 units in the last place of libm's). Fused multiply–adds may be contracted differently in
the two codes, so the kernel agrees with the scalar function to rounding, not to the bit
(``tests/test_lane_kernel.py``: within 1e-12 of each output's size on the learned and closed-form ball joint's
and quadrotor's stages).

The timings, a stage alone and inside the loop (``python -m benchmarks.c_loop``): docs/c-controller.md, "Four
stages at a time".

Where it runs: ``RTIOptions.stage_lanes`` (:func:`uses_lanes`): compiled loops that renew every stage's
Jacobians each period (``relinearize_every = 1``, the default) and whose stage CasADi writes in the operations
translated here; kept Jacobians need the per-stage switch of the generated map.
"""

from __future__ import annotations

import re
import warnings
from importlib import resources

import casadi as ca

from fvin_mpc.control.model_export import CKernel

#: Stages per vector (four doubles: the 256-bit registers of AVX2; two 128-bit halves without it).
LANES = 4
#: The choices of ``RTIOptions.stage_lanes``.
STAGE_LANES = ("auto", "on", "off")

_VARIABLE = r"a\d+"
_NUMBER = r"-?(?:\d+\.?\d*(?:e[-+]?\d+)?)"
_OPERAND = rf"(?:{_VARIABLE}|{_NUMBER})"
_COMPARISONS = {"<": "lt", "<=": "le", "==": "eq", "!=": "ne", "&&": "and", "||": "or"}
#: The scalar functions of CasADi's C a lane kernel has vector versions of (``c_kernels/lanes_prelude.c``).
FUNCTIONS = frozenset({"sqrt", "exp", "log", "sin", "cos", "tan", "asin", "acos", "atan", "sinh", "cosh", "tanh",
                       "floor", "ceil", "erf", "log1p", "expm1", "casadi_log1p", "casadi_expm1", "casadi_sq",
                       "casadi_fabs", "casadi_sign", "casadi_fmax", "casadi_fmin", "atan2", "pow", "fmod"})
_RULES = (
    (re.compile(rf"({_VARIABLE})=arg\[(\d+)\]\? arg\[\d+\]\[(\d+)\] : 0;"),
     lambda m: f"{m[1]}={_load(int(m[2]), int(m[3]))};"),
    (re.compile(rf"if \(res\[(\d+)\]!=0\) res\[\d+\]\[(\d+)\]=({_VARIABLE});"),
     lambda m: " ".join(f"out[{int(m[1]) * LANES + lane}][{m[2]}]={m[3]}[{lane}];" for lane in range(LANES))),
    (re.compile(rf"({_VARIABLE})=({_NUMBER});"), lambda m: f"{m[1]}=fvl_splat({m[2]});"),
    (re.compile(rf"({_VARIABLE})=\(({_VARIABLE})\?({_VARIABLE}|0):({_VARIABLE}|0)\);"),
     lambda m: f"{m[1]}=fvl_select({m[2]},{_vector(m[3])},{_vector(m[4])});"),
    (re.compile(rf"({_VARIABLE})=\(!({_VARIABLE})\);"), lambda m: f"{m[1]}=fvl_not({m[2]});"),
    (re.compile(rf"({_VARIABLE})=\(({_VARIABLE})(<=|<|==|!=|&&|\|\|)({_VARIABLE})\);"),
     lambda m: f"{m[1]}=fvl_{_COMPARISONS[m[3]]}({m[2]},{m[4]});"),
    # arithmetic is the vector extension's own (a number beside a vector is taken in every lane)
    (re.compile(rf"({_VARIABLE})=\(({_OPERAND})([-+*/])({_OPERAND})\);"), lambda m: m[0]),
    (re.compile(rf"({_VARIABLE})=\(-({_VARIABLE})\);"), lambda m: m[0]),
    (re.compile(rf"({_VARIABLE})=({_VARIABLE});"), lambda m: m[0]),
    (re.compile(rf"({_VARIABLE})=([a-z_0-9]+)\(({_VARIABLE})(?:,({_VARIABLE}))?\);"),
     lambda m: f"{m[1]}=fvl_{m[2]}({m[3]}{',' + m[4] if m[4] else ''});" if m[2] in FUNCTIONS else None),
)


class UntranslatableCode(ValueError):
    """CasADi wrote a stage in code a lane kernel does not translate (an operation without a vector version,
    work vectors, a call): the message names the line."""


def _load(index: int, element: int) -> str:
    return "(fvl_vec){" + ", ".join(f"in[{index * LANES + lane}][{element}]" for lane in range(LANES)) + "}"


def _vector(operand: str) -> str:
    return "fvl_splat(0.)" if operand == "0" else operand


def scalar_body(function: ca.Function) -> list[str]:
    """The lines of CasADi's C for ``function`` (an SX function: one straight-line body), between its
    declaration of scalars and its ``return``; ``UntranslatableCode`` where it is anything else."""
    if not function.is_a("SXFunction"):
        raise UntranslatableCode(f"{function.name()} is not a scalar (SX) function")
    generator = ca.CodeGenerator("lanes.c")
    generator.add(function)
    text = generator.dump()
    bodies = re.findall(r"static int casadi_f\d+\(const casadi_real\*\* arg, casadi_real\*\* res, casadi_int\* iw, "
                        r"casadi_real\* w, int mem\) \{\n(.*?)\n\}\n", text, re.S)
    if len(bodies) != 1:
        raise UntranslatableCode(f"CasADi wrote {function.name()} as {len(bodies)} functions, not one body")
    lines = [line.strip() for line in bodies[0].splitlines()]
    if not lines or lines[-1] != "return 0;":
        raise UntranslatableCode(f"{function.name()}'s body does not end in its return")
    return [line for line in lines[:-1] if not line.startswith("casadi_real ")]  # the declarations: made anew


def translate_line(line: str) -> str:
    """One line of CasADi's scalar C as the same on vectors of :data:`LANES` stages (``in``/``out``: each input's
    and output's pointer per lane); ``UntranslatableCode`` naming it where no rule applies."""
    for pattern, rewrite in _RULES:
        match = pattern.fullmatch(line)
        if match:
            translated = rewrite(match)
            if translated is not None:
                return translated
    raise UntranslatableCode(f"no vector translation of the generated line {line!r}")


def lane_map_kernel(function: ca.Function, count: int, name: str | None = None) -> CKernel:
    """``function.map(count)`` as a lane kernel (module docstring): inputs and outputs are ``function``'s, each
    stage's block beside the last (a ``(rows, columns · count)`` matrix), all dense. ``name`` (default
    ``fvin_lanes_{function}_{count}``) is its symbol. ``UntranslatableCode`` where ``function``'s C has an
    operation this module has no vector version of, or a sparse input or output."""
    if count < 1:
        raise ValueError(f"a lane kernel maps over count >= 1 stages, got {count}")
    for kind, n, sparsity in (("input", function.n_in(), function.sparsity_in),
                              ("output", function.n_out(), function.sparsity_out)):
        for i in range(n):
            if not sparsity(i).is_dense():
                raise UntranslatableCode(f"{function.name()}'s {kind} {i} is sparse; a lane kernel maps dense blocks")
    name = name or f"fvin_lanes_{function.name()}_{count}"
    body = [translate_line(line) for line in scalar_body(function)]
    variables = sorted({v for line in body for v in re.findall(rf"\b{_VARIABLE}\b", line)}, key=lambda v: (len(v), v))
    n_in, n_out = function.n_in(), function.n_out()
    sizes_in = [function.nnz_in(i) for i in range(n_in)]
    sizes_out = [function.nnz_out(i) for i in range(n_out)]

    def shape(sparsity: ca.Sparsity) -> str:
        return f"{{{sparsity.size1()}, {sparsity.size2() * count}, 1}}"  # CasADi's compressed form of dense

    shapes = [shape(function.sparsity_in(i)) for i in range(n_in)] + [shape(function.sparsity_out(i))
                                                                        for i in range(n_out)]
    declarations = f"  fvl_vec {', '.join(variables)};\n" if variables else ""
    statements = "\n  ".join(body)
    prelude = (resources.files("fvin_mpc.control") / "c_kernels" / "lanes_prelude.c").read_text()
    return CKernel(name, scalar_instructions=function.n_instructions() * count, source=f"""{prelude}
/* {name}: {function.name()} of CasADi's C, {count} stages, {LANES} at a time (fvin_mpc.control.lane_kernel). */
static void {name}_lanes(const casadi_real* const* in, casadi_real* const* out) {{
{declarations}  {statements}
}}

static const casadi_int {name}_in_size[] = {{{', '.join(map(str, sizes_in)) or '0'}}};
static const casadi_int {name}_out_size[] = {{{', '.join(map(str, sizes_out)) or '0'}}};

int {name}(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w, int mem) {{
  /* a stage past the horizon's end reads the last stage and writes to scratch; so does a missing output */
  static const casadi_real zeros[{max(sizes_in, default=0) + 1}] = {{0}};
  casadi_real scratch[{max(sizes_out, default=0) + 1}];
  const casadi_real* in[{max(n_in, 1) * LANES}];
  casadi_real* out[{max(n_out, 1) * LANES}];
  casadi_int first, lane, i;
  (void)iw, (void)w, (void)mem;
  for (first = 0; first < {count}; first += {LANES}) {{
    for (lane = 0; lane < {LANES}; ++lane) {{
      casadi_int stage = first + lane < {count} ? first + lane : {count - 1};
      for (i = 0; i < {n_in}; ++i) in[i * {LANES} + lane] = arg[i] ? arg[i] + stage * {name}_in_size[i] : zeros;
      for (i = 0; i < {n_out}; ++i)
        out[i * {LANES} + lane] = res[i] && first + lane < {count} ? res[i] + stage * {name}_out_size[i] : scratch;
    }}
    {name}_lanes(in, out);
  }}
  return 0;
}}

/* What casadi.external reads to call the kernel from a shared library: dense inputs and outputs. */
static const casadi_int {name}_sp[][3] = {{{', '.join(shapes)}}};
casadi_int {name}_n_in(void) {{ return {n_in}; }}
casadi_int {name}_n_out(void) {{ return {n_out}; }}
const casadi_int* {name}_sparsity_in(casadi_int i) {{ return i >= 0 && i < {n_in} ? {name}_sp[i] : 0; }}
const casadi_int* {name}_sparsity_out(casadi_int i) {{ return i >= 0 && i < {n_out} ? {name}_sp[{n_in} + i] : 0; }}
""")


def uses_lanes(choice: str, compiled: bool, relinearize_every: int, unrolled: bool) -> bool:
    """Whether a controller's linearization maps its stages with lane kernels: ``choice``
    (``RTIOptions.stage_lanes``) for a compiled loop or not, its ``relinearize_every``, unrolled dynamics or the
    implicit ones. ``ValueError`` where ``"on"`` cannot run."""
    if choice not in STAGE_LANES:
        raise ValueError(f"unknown stage_lanes {choice!r}; one of {STAGE_LANES}")
    possible = compiled and relinearize_every == 1 and unrolled
    if choice == "on" and not possible:
        raise ValueError("stage_lanes='on' maps the unrolled dynamics' stages in C: it needs compile='cached' (a C "
                         f"compiler), rti.dynamics='unrolled' and relinearize_every=1 (kept Jacobians switch stage by "
                         f"stage); got compiled={compiled}, unrolled={unrolled}, relinearize_every={relinearize_every}")
    return choice != "off" and possible


def lane_map_or_none(choice: str, function: ca.Function, count: int) -> CKernel | None:
    """:func:`lane_map_kernel` of ``function``, or ``None`` where ``choice`` is ``"auto"`` and it is written in
    code this module does not translate (said in a warning: the generated map runs instead)."""
    try:
        return lane_map_kernel(function, count)
    except UntranslatableCode as reason:
        if choice == "on":
            raise
        warnings.warn(f"{function.name()} runs as generated scalar code, not in lanes: {reason}", RuntimeWarning,
                      stacklevel=3)
        return None
