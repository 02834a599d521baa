"""The Riccati stage as hand-written C (``c_kernels/riccati_stage.c``): the generated QP's hot loop on the vector units.

The real-time iteration's QP (:func:`fvin_mpc.control.riccati_qp.riccati_feedback_function`) runs one backward Riccati
stage per stage and interior-point iteration — 180 a period on the quadrotor (``N = 30``, six iterations),
most of its QP's time. CasADi generates each stage as straight-line scalar code
(:func:`~fvin_mpc.control.riccati_qp.riccati_stage_function`, the reference). The kernel computes the same stage
with the two products that dominate it, ``P [A B]`` and ``[A B]ᵀ P [A B]``, as loops over columns of four
doubles, compiled with ``-O3`` where GCC and Clang turn them into vector instructions. The generated
feedback calls the whole backward sweep over the stages (:func:`riccati_stage_kernel` with a horizon) through
CasADi's external-function convention, in place of a ``mapaccum`` of the generated stage: one
source for both loops, which compile it alike (the Python loop's library, :func:`compile_functions`; the
C loop's, :mod:`fvin_mpc.control.c_controller`).

Where it pays: a stage alone, the kernel is faster than the generated code at a free body's size
(``n_δ = 12``) and slower at a pivoted body's (``n_δ = 6``); ``RTIOptions.riccati_stage="auto"`` therefore takes the
kernel for free bodies (:data:`KERNEL_MIN_TANGENT_DIM`) and the generated stage for pivoted ones. The timings, a
stage alone (``python -m benchmarks.riccati_stage``) and inside the quadrotor's QP: docs/c-controller.md, "Fewer
operations, again".
"""

from __future__ import annotations

from importlib import resources

from fvin_mpc.control.model_export import CKernel

#: ``riccati_stage="auto"`` takes the kernel from this tangent dimension on (free bodies; module docstring).
KERNEL_MIN_TANGENT_DIM = 12
#: The choices of ``RTIOptions.riccati_stage``.
RICCATI_STAGES = ("auto", "generated", "kernel")


def riccati_stage_kernel(nd: int, m: int, horizon: int | None = None) -> CKernel:
    """The kernel of a Riccati stage with ``n_δ = nd`` and ``m`` controls (``fvin_riccati_stage_{nd}_{m}``, the
    signature of :func:`~fvin_mpc.control.riccati_qp.riccati_stage_function`) or, with a ``horizon`` ``N``, of the whole
    backward sweep over ``N`` such stages (``fvin_riccati_sweep_{nd}_{m}_{N}``: ``(P_N, p_N, H, g, [A B], c, d,
    r) → (K, k)``, every block in the stages' own order): the template's source after a prelude that fixes its
    sizes and its name. The sweep is what the feedback calls: it runs the stages in place, where a ``mapaccum``
    of the stage copied the cost-to-go from call to call and the stages' data into reverse order."""
    if nd < 1 or m < 1 or (horizon is not None and horizon < 1):
        raise ValueError(f"a Riccati stage needs n_delta >= 1, m >= 1 and a horizon >= 1, got {nd}, {m}, {horizon}")
    name = f"fvin_riccati_stage_{nd}_{m}" if horizon is None else f"fvin_riccati_sweep_{nd}_{m}_{horizon}"
    template = (resources.files("fvin_mpc.control") / "c_kernels" / "riccati_stage.c").read_text()
    macros = {"FVK_NAME": name, "FVK_ND": nd, "FVK_M": m, **({} if horizon is None else {"FVK_N": horizon})}
    prelude = "".join(f"#define {macro} {value}\n" for macro, value in macros.items())
    # its sizes and name undefined again at its end: the macros are this kernel's only
    return CKernel(name, prelude + template + "".join(f"#undef {macro}\n" for macro in macros))


def uses_kernel(choice: str, nd: int, compiled: bool, method: str) -> bool:
    """Whether a controller's feedback runs the kernel: ``choice`` (``RTIOptions.riccati_stage``) for a tangent
    dimension ``nd``, compiled functions or not, the QP method. ``ValueError`` where ``"kernel"`` cannot run."""
    if choice not in RICCATI_STAGES:
        raise ValueError(f"unknown riccati_stage {choice!r}; one of {RICCATI_STAGES}")
    if choice == "kernel":
        if not compiled:
            raise ValueError("riccati_stage='kernel' is C: it needs compile='cached' (a C compiler)")
        if method != "path":
            raise ValueError("riccati_stage='kernel' is the fused stage of qp_method='path'; the predictor-corrector "
                             "splits the stage in two halves, which are generated (riccati_stage='generated')")
        return True
    return choice == "auto" and compiled and method == "path" and nd >= KERNEL_MIN_TANGENT_DIM
