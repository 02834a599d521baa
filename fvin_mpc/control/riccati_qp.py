"""The real-time iteration's QP solver: a primal–dual interior-point method on the input boxes, each iteration a
Riccati recursion, generated as one CasADi function with the trust region and the update of the plan
(:func:`riccati_feedback_function`; :mod:`fvin_mpc.control.rti` calls it once per iteration).

**The problem.** ``min Σ ½[δ;Δu]ᵀH_k[δ;Δu] + g_kᵀ[δ;Δu] + ½δ_NᵀH_Nδ_N + g_Nᵀδ_N`` subject to
``δ_{k+1} = A_kδ_k + B_kΔu_k + c_k``, ``δ_0`` fixed by the measurement, ``low_k ≤ ū_k + Δu_k ≤ high_k``: a
stage-wise LQ problem with boxes on the inputs only (state bounds enter the cost as penalties).

**The method.** A fixed number of iterations (no convergence test: the count bounds the time), each solving the
barrier-modified LQ problem (``R + diag(λ/s)``) by one backward Riccati recursion (``O(N)``; the stage's gram
matrix ``R + diag(d) + BᵀPB`` factored ``UᵀDU`` without square roots or pivoting,
:func:`riccati_stage_function`) and a forward pass, then the fraction-to-boundary step. ``method="path"``
reduces ``μ`` to a fixed fraction of the mean complementarity; ``"mehrotra"`` factors once and solves twice
(Mehrotra's predictor–corrector). ``μ`` never drops below :data:`QP_MU_MIN`.

**Where it breaks.**

* The gram matrix must stay positive definite: the Gauss–Newton Hessian is positive semidefinite, and a positive
  control weight makes ``R`` definite; with a zero control weight on an input the recursion can divide by a pivot
  near zero.
* A fixed iteration count returns an approximate QP solution: on some ball-joint QPs the first control stays more
  than 1 % of the torque range off even at 40 iterations (the iteration stalls; ``python -m benchmarks.qp_accuracy``,
  docs/realtime.md). Each iteration is still a descent of the barrier problem, and the trust region bounds the step.
* Without the floor on ``μ`` the barrier curvature ``λ/s`` swamps the recursion after ~20 iterations and ``μ``
  turns NaN (:data:`QP_MU_MIN`).
* Boxes on the inputs only: a hard state bound would make the linearized QP infeasible from a far first guess.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from fvin_mpc.control.linearization import clip_rows
from fvin_mpc.control.model_export import GENERATED_SX_OPTIONS
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.space import StateLayout

CA = get_ops("casadi")

#: The interior-point methods of the Riccati QP (:func:`riccati_feedback_function`): a path-following
#: iteration with a fixed centering, or Mehrotra's predictor–corrector.
QP_METHODS = ("path", "mehrotra")
#: Smallest barrier parameter of the Riccati QP's interior-point iterations. Without a floor μ falls
#: tenfold per iteration; past ~20 iterations the barrier curvature λ/s (~λ²/μ) swamps the Riccati
#: recursion, the dual update cancels catastrophically and μ turned NaN (20 iterations: 11 of 20
#: swing-ups lost, docs/bench/rti.md). At 1e-10 the iterations after the floor re-solve the same
#: barrier problem.
QP_MU_MIN = 1e-10


def _total(terms: list[Any]) -> Any:
    return sum(terms[1:], terms[0])


def _gram_factors(gram: dict[tuple[int, int], Any], m: int) -> tuple[list[Any], dict[tuple[int, int], Any]]:
    """``gram = Uᵀ D U`` (``U`` unit upper triangular, no square roots): the pivots ``D`` and ``U``'s entries
    above the diagonal, from the upper triangle of the symmetric positive definite ``gram``."""
    pivot: list[Any] = []
    upper: dict[tuple[int, int], Any] = {}
    for a in range(m):
        pivot.append(gram[a, a] - sum((upper[e, a] * upper[e, a] * pivot[e] for e in range(a)), 0.0))
        for b in range(a + 1, m):
            upper[a, b] = (gram[a, b] - sum((upper[e, a] * upper[e, b] * pivot[e] for e in range(a)), 0.0)) / pivot[a]
    return pivot, upper


def _lower_solve(upper: dict[tuple[int, int], Any], column: list[Any]) -> list[Any]:
    """``y`` of ``Uᵀ y = column``."""
    y: list[Any] = []
    for a in range(len(column)):
        y.append(column[a] - sum((upper[e, a] * y[e] for e in range(a)), 0.0))
    return y


def _upper_solve(upper: dict[tuple[int, int], Any], column: list[Any]) -> list[Any]:
    """``x`` of ``U x = column``."""
    m = len(column)
    x: list[Any] = [0.0] * m
    for a in reversed(range(m)):
        x[a] = column[a] - sum((upper[a, e] * x[e] for e in range(a + 1, m)), 0.0)
    return x


def _riccati_matrices(P: Any, H: Any, AB: Any, d: Any, nd: int, m: int) -> dict[str, Any]:
    """The matrix half of a Riccati stage, entry by entry (:func:`riccati_stage_function`): ``P`` read from its
    upper triangle, ``PA``, ``PB``, the gram matrix ``R + diag(d) + BᵀPB`` and its factors, ``cross = S + BᵀPA``,
    ``Y = U⁻ᵀ cross``, ``Z = D⁻¹ Y``."""
    def p_entry(i: int, j: int) -> Any:
        return P[min(i, j), max(i, j)]

    A = [[AB[i, j] for j in range(nd)] for i in range(nd)]
    B = [[AB[i, nd + a] for a in range(m)] for i in range(nd)]
    PA = [[_total([p_entry(i, k) * A[k][j] for k in range(nd)]) for j in range(nd)] for i in range(nd)]
    PB = [[_total([p_entry(i, k) * B[k][a] for k in range(nd)]) for a in range(m)] for i in range(nd)]
    gram = {(a, b): H[nd + a, nd + b] + _total([B[k][a] * PB[k][b] for k in range(nd)]) + (d[a] if a == b else 0.0)
            for a in range(m) for b in range(a, m)}
    cross = [[H[nd + a, j] + _total([PB[k][a] * A[k][j] for k in range(nd)]) for j in range(nd)] for a in range(m)]
    pivot, upper = _gram_factors(gram, m)
    Y = [_lower_solve(upper, [cross[a][j] for a in range(m)]) for j in range(nd)]  # Y[j] = U⁻ᵀ cross[:, j]
    Z = [[Y[j][a] / pivot[a] for a in range(m)] for j in range(nd)]               # D⁻¹ Y
    gains = [_upper_solve(upper, [-Z[j][a] for a in range(m)]) for j in range(nd)]
    P_prev = ca.SX(nd, nd)
    for i in range(nd):
        for j in range(i, nd):
            P_prev[i, j] = P_prev[j, i] = (H[i, j] + _total([A[k][i] * PA[k][j] for k in range(nd)])
                                           - _total([Z[i][a] * Y[j][a] for a in range(m)]))
    K = ca.SX(m, nd)
    for j in range(nd):
        for a in range(m):
            K[a, j] = gains[j][a]
    return {"A": A, "B": B, "p_entry": p_entry, "pivot": pivot, "upper": upper, "Z": Z, "P_prev": P_prev, "K": K}


def _riccati_vectors(matrices: dict[str, Any], p: Any, g: Any, c: Any, r: Any, nd: int, m: int
                     ) -> tuple[list[Any], list[Any]]:
    """The vector half of a Riccati stage given its matrix half (:func:`_riccati_matrices`): ``r̃ = r + Bᵀ(Pc +
    p)``, the feedforward ``k = −gram⁻¹ r̃`` and ``p⁻ = g_δ + Aᵀ(Pc + p) − Zᵀ U⁻ᵀ r̃``."""
    A, B, p_entry, upper, pivot, Z = (matrices[key] for key in ("A", "B", "p_entry", "upper", "pivot", "Z"))
    pc = [_total([p_entry(i, k) * c[k] for k in range(nd)]) + p[i] for i in range(nd)]
    r_tilde = [r[a] + _total([B[k][a] * pc[k] for k in range(nd)]) for a in range(m)]
    w = _lower_solve(upper, r_tilde)
    z = [w[a] / pivot[a] for a in range(m)]
    feedforward = _upper_solve(upper, [-z[a] for a in range(m)])
    p_prev = [g[i] + _total([A[k][i] * pc[k] for k in range(nd)]) - _total([Z[i][a] * w[a] for a in range(m)])
              for i in range(nd)]
    return p_prev, feedforward


def riccati_stage_function(nd: int, m: int) -> ca.Function:
    """One backward stage of the Riccati recursion, ``rti_riccati_stage(P, p, H, g, [A B], c, d, r) →
    (P⁻, p⁻, K, k)``: the cost-to-go ``½δᵀPδ + pᵀδ`` at stage ``k+1`` to stage ``k``'s, with the stage's
    gain ``K`` and feedforward ``k`` (``Δu = Kδ + k``), for ``gram = R + diag(d) + BᵀPB``,
    ``cross = S + BᵀPA``, ``r̃ = r + Bᵀ(Pc + p)``::

        K = −gram⁻¹ cross,   k = −gram⁻¹ r̃,
        P⁻ = Q + AᵀPA − crossᵀ gram⁻¹ cross,   p⁻ = g_δ + Aᵀ(Pc + p) − crossᵀ gram⁻¹ r̃.

    Written entry by entry, because the QP runs this ``N × qp_iterations`` times a period and the
    matrix form generated about 40 % more operations (14,397 against 10,173 instructions for
    ``n_δ = 12, m = 4``): ``P`` is read from its upper triangle and ``P⁻``, ``AᵀPA`` computed once per
    pair ``i ≤ j``; ``PA`` and ``PB`` are formed once and shared by ``BᵀPB``, ``BᵀPA``, ``AᵀPA``; ``gram``
    (symmetric positive definite: ``R`` holds the control weight and the regularization, ``d ≥ 0`` the
    barrier's curvature) is factored once as ``UᵀDU`` (no square roots) and serves both solves and
    ``crossᵀgram⁻¹cross = YᵀD⁻¹Y`` with ``Y = U⁻ᵀ cross``, where ``ca.solve`` on SX expanded a
    general solve twice. ``tests/test_rti.py`` checks it against the matrix formulas in NumPy. Its matrix and
    vector halves are also separate functions (:func:`riccati_factor_function`, :func:`riccati_solve_function`)
    for an iteration that solves twice with one factorization."""
    size = nd + m
    P, p = ca.SX.sym("P", nd, nd), ca.SX.sym("p", nd)
    H, g = ca.SX.sym("H", size, size), ca.SX.sym("g", size)
    AB, c = ca.SX.sym("AB", nd, size), ca.SX.sym("c", nd)
    d, r = ca.SX.sym("d", m), ca.SX.sym("r", m)
    matrices = _riccati_matrices(P, H, AB, d, nd, m)
    p_prev, feedforward = _riccati_vectors(matrices, p, g, c, r, nd, m)
    return ca.Function("rti_riccati_stage", [P, p, H, g, AB, c, d, r],
                       [matrices["P_prev"], ca.vertcat(*p_prev), matrices["K"], ca.vertcat(*feedforward)],
                       ["P", "p", "H", "g", "AB", "c", "d", "r"], ["P_prev", "p_prev", "K", "k"],
                       GENERATED_SX_OPTIONS)


def _factors_matrix(matrices: dict[str, Any], m: int) -> Any:
    """The gram matrix's factors in one ``m × m`` matrix: the pivots ``D`` on the diagonal, ``U`` above it."""
    factors = ca.SX(m, m)
    for a in range(m):
        factors[a, a] = matrices["pivot"][a]
        for b in range(a + 1, m):
            factors[a, b] = matrices["upper"][a, b]
    return factors


def riccati_factor_function(nd: int, m: int) -> ca.Function:
    """The matrix half of :func:`riccati_stage_function`, ``rti_riccati_factor(P, H, [A B], d) → (P⁻, K, F, Z)``:
    ``F`` the gram matrix's ``UᵀDU`` factors (:func:`_factors_matrix`), ``Z = D⁻¹U⁻ᵀ cross`` — what
    :func:`riccati_solve_function` needs to solve with another right-hand side at a fraction of the cost."""
    size = nd + m
    P, H = ca.SX.sym("P", nd, nd), ca.SX.sym("H", size, size)
    AB, d = ca.SX.sym("AB", nd, size), ca.SX.sym("d", m)
    matrices = _riccati_matrices(P, H, AB, d, nd, m)
    Z = ca.SX(nd, m)
    for i in range(nd):
        for a in range(m):
            Z[i, a] = matrices["Z"][i][a]
    return ca.Function("rti_riccati_factor", [P, H, AB, d],
                       [matrices["P_prev"], matrices["K"], _factors_matrix(matrices, m), Z],
                       ["P", "H", "AB", "d"], ["P_prev", "K", "F", "Z"], GENERATED_SX_OPTIONS)


def riccati_solve_function(nd: int, m: int) -> ca.Function:
    """The vector half of :func:`riccati_stage_function` on a factored stage (:func:`riccati_factor_function`),
    ``rti_riccati_solve(p, P, F, Z, g, [A B], c, r) → (p⁻, k)``, ``P`` the cost-to-go matrix the stage was
    factored with (that of stage ``k+1``)."""
    size = nd + m
    p, P = ca.SX.sym("p", nd), ca.SX.sym("P", nd, nd)
    F, Zs = ca.SX.sym("F", m, m), ca.SX.sym("Z", nd, m)
    g, AB = ca.SX.sym("g", size), ca.SX.sym("AB", nd, size)
    c, r = ca.SX.sym("c", nd), ca.SX.sym("r", m)
    matrices = {"A": [[AB[i, j] for j in range(nd)] for i in range(nd)],
                "B": [[AB[i, nd + a] for a in range(m)] for i in range(nd)],
                "p_entry": lambda i, j: P[min(i, j), max(i, j)],
                "pivot": [F[a, a] for a in range(m)],
                "upper": {(a, b): F[a, b] for a in range(m) for b in range(a + 1, m)},
                "Z": [[Zs[i, a] for a in range(m)] for i in range(nd)]}
    p_prev, feedforward = _riccati_vectors(matrices, p, g, c, r, nd, m)
    return ca.Function("rti_riccati_solve", [p, P, F, Zs, g, AB, c, r], [ca.vertcat(*p_prev), ca.vertcat(*feedforward)],
                       ["p", "P", "F", "Z", "g", "AB", "c", "r"], ["p_prev", "k"], GENERATED_SX_OPTIONS)


def riccati_feedback_function(layout: StateLayout, n: int, m: int, low: np.ndarray, high: np.ndarray,
                              limits: np.ndarray, omega_valid: float, iterations: int, centering: float = 0.1,
                              boundary: float = 0.995, mu_min: float = QP_MU_MIN, method: str = "path",
                              sweep: ca.Function | None = None) -> tuple[ca.Function, ca.Function]:
    """One feedback iteration as a single CasADi function (compiled with the linearization):
    ``rti_feedback(X̄ (n_x,N+1), Ū (m,N), x0 (n_x), H (s,sN), H_N (n_δ,n_δ), g (s,N), g_N (n_δ),
    [A B] (n_δ,sN), c (n_δ,N)) → (X (n_x,N+1), U (m,N), step, μ, K (m,n_δN), k (m,N))``, ``s = n_δ + m``;
    ``n_x``, ``n_δ`` the ``layout``'s state and tangent dimensions (7 and 6 for a pivoted body, 13 and 12
    for a free one); ``K``, ``k`` the last Riccati solve's gains and feedforwards per stage. And the
    prepared feedback ``rti_apply(X̄, Ū, x0, K, k, [A B], c) → (X, U, step)``: the same update from a
    forward pass of given gains from ``δ_0 = local(x̄_0, x0)`` (``RTIOptions.feedback="prepared"``).

    The QP ``min Σ ½[δ;Δu]ᵀH_k[δ;Δu] + g_kᵀ[δ;Δu] + ½δ_NᵀH_Nδ_N + g_Nᵀδ_N`` s.t.
    ``δ_{k+1} = A_kδ_k + B_kΔu_k + c_k``, ``δ_0 = local(x̄_0, x0)``, ``low_k ≤ ū_k + Δu_k ≤ high_k`` is
    solved by a primal–dual interior-point method on the input boxes with a fixed number of
    ``iterations``: each solves the barrier-modified LQ problem (``R + diag(λ/s)``) by a Riccati
    recursion (``O(N)``, backward ``mapaccum``), takes the fraction-to-boundary step and reduces
    ``μ`` to ``centering ×`` the mean complementarity, not below ``mu_min`` (:data:`QP_MU_MIN`).
    ``sweep``: the path-following method's whole backward recursion as one function, ``(P_N, p_N, H, g, [A B], c,
    d, r) → (K, k)`` in the stages' order (the hand-written kernel, :mod:`fvin_mpc.control.riccati_kernel`);
    default: :func:`riccati_stage_function` run backward by a ``mapaccum``.
    ``method="mehrotra"`` (:data:`QP_METHODS`): Mehrotra's predictor–corrector instead — each iteration factors
    the LQ problem once (:func:`riccati_factor_function`) and solves it twice (:func:`riccati_solve_function`):
    the affine step (``μ = 0``), whose progress sets the centering ``σ = (μ_aff/μ)³``, then the step to
    ``σμ`` with the affine step's second-order term.
    Then the trust region (``limits``, per entry of ``δ``: :func:`step_limits`), the update on S³
    and ``|ω|`` within ``omega_valid`` (as :meth:`RealTimeMPC._iterate`). No Python between the
    stages: the whole iteration is one call. ``low``, ``high``: the control bounds, ``(m,)`` for every
    stage or ``(N, m)`` per stage (the torque reserve: :func:`fvin_mpc.control.problem.control_bounds`).
    """
    ns, nd = layout.state_dim, layout.tangent_dim
    stage_low, stage_high = (np.broadcast_to(np.asarray(bound, dtype=float), (n, m)).T for bound in (low, high))
    size = nd + m
    if sweep is not None and method != "path":
        raise ValueError("a given backward sweep runs the fused stage of method='path'")
    backward = riccati_stage_function(nd, m).mapaccum("rti_riccati", n, 2)
    # --- one forward stage
    abk, ck = ca.SX.sym("AB", nd, size), ca.SX.sym("c", nd)
    delta, gain_k, ff_k = ca.SX.sym("delta", nd), ca.SX.sym("K", m, nd), ca.SX.sym("k", m)
    v = ca.mtimes(gain_k, delta) + ff_k
    forward = ca.Function("rti_forward_stage", [delta, gain_k, ff_k, abk, ck],
                          [ca.mtimes(abk, ca.vertcat(delta, v)) + ck, v],
                          GENERATED_SX_OPTIONS).mapaccum("rti_forward", n, 1)

    def reverse(matrix: Any, width: int) -> Any:  # stage blocks of `width` columns in reverse order
        return matrix[:, [(n - 1 - k) * width + j for k in range(n) for j in range(width)]]

    states, controls = ca.MX.sym("X", ns, n + 1), ca.MX.sym("U", m, n)
    x0, hessians, terminal_hessian = ca.MX.sym("x0", ns), ca.MX.sym("H", size, size * n), ca.MX.sym("HN", nd, nd)
    gradients, terminal_gradient = ca.MX.sym("g", size, n), ca.MX.sym("gN", nd)
    jacobians, gaps = ca.MX.sym("AB", nd, size * n), ca.MX.sym("c", nd, n)
    delta0 = layout.local(states[:, 0], x0, CA)
    lower = ca.fmax(ca.DM(np.maximum(stage_low, -1e6)) - controls, -1e6)
    upper = ca.fmin(ca.DM(np.minimum(stage_high, 1e6)) - controls, 1e6)
    width = upper - lower
    hessians_rev, jacobians_rev = reverse(hessians, size), reverse(jacobians, size)
    gradients_rev, gaps_rev = reverse(gradients, 1), reverse(gaps, 1)

    def solve_lq(d: Any, r: Any) -> tuple[Any, Any, Any, Any]:
        if sweep is not None:
            gains, feedforwards = sweep(terminal_hessian, terminal_gradient, hessians, gradients, jacobians, gaps, d, r)
        else:
            _, _, gains, feedforwards = backward(terminal_hessian, terminal_gradient, hessians_rev, gradients_rev,
                                                 jacobians_rev, gaps_rev, reverse(d, 1), reverse(r, 1))
            gains, feedforwards = reverse(gains, nd), reverse(feedforwards, 1)
        deltas, v = forward(delta0, gains, feedforwards, jacobians, gaps)
        return deltas, v, gains, feedforwards

    if method not in QP_METHODS:
        raise ValueError(f"unknown interior-point method {method!r}; one of {QP_METHODS}")
    # interior start: Δu in the box, 1 % of its width away from a bound; λ = μ₀/s
    v = ca.fmin(ca.fmax(ca.MX.zeros(m, n), lower + 0.01 * width), upper - 0.01 * width)
    slack_low, slack_up = v - lower, upper - v
    mu = ca.MX(0.1)
    dual_low, dual_up = mu / slack_low, mu / slack_up

    # The elementwise work of an iteration runs as SX functions mapped over the stages
    # (:func:`_interior_point_stage_functions`): one loop per function in the generated code, where each
    # elementwise MX operation was a loop and a temporary of its own.
    longest, barrier, direction, update = _interior_point_stage_functions(m, n)

    def step_to(fraction: float, dv: Any, d_low: Any, d_up: Any) -> Any:
        """The longest step (at most 1, times ``fraction``) along ``(dv, d_low, d_up)`` that keeps the current
        slacks and duals nonnegative."""
        return ca.fmin(1.0, fraction * ca.mmin(longest(slack_low, slack_up, dual_low, dual_up, dv, d_low, d_up)))

    if method == "mehrotra":
        factor = riccati_factor_function(nd, m).mapaccum("rti_riccati_factor", n, 1)
        solve = riccati_solve_function(nd, m).mapaccum("rti_riccati_solve", n, 1)
        for _ in range(iterations):
            slack_low, slack_up = v - lower, upper - v
            curvature = dual_low / slack_low + dual_up / slack_up
            # the cost-to-go matrices per stage, in reverse order: the terminal one, then each factored stage's
            matrices, gains_rev, factors, crosses = factor(terminal_hessian, hessians_rev, jacobians_rev,
                                                           reverse(curvature, 1))
            next_matrices = ca.horzcat(terminal_hessian, matrices[:, :nd * (n - 1)])
            gains = reverse(gains_rev, nd)

            def solve_targets(low_target: Any, up_target: Any) -> tuple[Any, Any, Any, Any]:
                linear = gradients[nd:, :] - low_target / slack_low + up_target / slack_up - curvature * v
                _, feedforwards_rev = solve(terminal_gradient, next_matrices, factors, crosses, gradients_rev,
                                            jacobians_rev, gaps_rev, reverse(linear, 1))
                feedforwards = reverse(feedforwards_rev, 1)
                deltas, target = forward(delta0, gains, feedforwards, jacobians, gaps)
                dv = target - v
                return deltas, dv, feedforwards, (low_target / slack_low - dual_low - dual_low / slack_low * dv,
                                                  up_target / slack_up - dual_up + dual_up / slack_up * dv)

            complementarity = ca.sum1(ca.sum2(dual_low * slack_low)) + ca.sum1(ca.sum2(dual_up * slack_up))
            mu_now = complementarity / (2 * m * n)
            _, dv_affine, _, (d_low_affine, d_up_affine) = solve_targets(0.0, 0.0)
            alpha = step_to(1.0, dv_affine, d_low_affine, d_up_affine)
            affine = (ca.sum1(ca.sum2((dual_low + alpha * d_low_affine) * (slack_low + alpha * dv_affine)))
                      + ca.sum1(ca.sum2((dual_up + alpha * d_up_affine) * (slack_up - alpha * dv_affine))))
            sigma_mu = ca.fmax((affine / complementarity) ** 3 * mu_now, mu_min)
            deltas, dv, feedforwards, (d_low, d_up) = solve_targets(sigma_mu - dv_affine * d_low_affine,
                                                                     sigma_mu + dv_affine * d_up_affine)
            alpha = step_to(boundary, dv, d_low, d_up)
            v, dual_low, dual_up = v + alpha * dv, dual_low + alpha * d_low, dual_up + alpha * d_up
            mu = (ca.sum1(ca.sum2(dual_low * (v - lower))) + ca.sum1(ca.sum2(dual_up * (upper - v)))) / (2 * m * n)
    else:
        for _ in range(iterations):
            slack_low, slack_up, curvature, linear = barrier(v, lower, upper, dual_low, dual_up, gradients[nd:, :], mu)
            deltas, target, gains, feedforwards = solve_lq(curvature, linear)
            dv, d_low, d_up = direction(v, target, slack_low, slack_up, dual_low, dual_up, mu)
            alpha = step_to(boundary, dv, d_low, d_up)
            v, dual_low, dual_up, low_complementarity, up_complementarity = update(
                v, dv, dual_low, d_low, dual_up, d_up, lower, upper, alpha)
            mu = ca.fmax(centering * (ca.sum1(ca.sum2(low_complementarity))
                                      + ca.sum1(ca.sum2(up_complementarity))) / (2 * m * n), mu_min)
    # The states of the last Riccati solve (closed-loop forward pass, consistent with its controls to
    # within (1 − α)|Δu|): propagating the final controls open loop would amplify the interior-point
    # method's inexactness through the unstable upright dynamics (e^{λ·horizon} ≈ 10³–10⁴ here).
    new_states, new_controls, step = _trust_region_update(layout, states, controls, x0, deltas, v, limits,
                                                          omega_valid, stage_low, stage_high, n)
    feedback = ca.Function("rti_feedback", [states, controls, x0, hessians, terminal_hessian, gradients,
                                            terminal_gradient, jacobians, gaps],
                           [new_states, new_controls, step, mu, gains, feedforwards],
                           ["X", "U", "x0", "H", "HN", "g", "gN", "AB", "c"],
                           ["X_new", "U_new", "step", "mu", "K", "k"])
    # --- the prepared feedback: the last Riccati solve's gains applied to the measured δ_0 (a forward pass)
    gains_in, feedforwards_in = ca.MX.sym("K", m, nd * n), ca.MX.sym("k", m, n)
    deltas, v = forward(delta0, gains_in, feedforwards_in, jacobians, gaps)
    new_states, new_controls, step = _trust_region_update(layout, states, controls, x0, deltas, v, limits,
                                                          omega_valid, stage_low, stage_high, n)
    apply = ca.Function("rti_apply", [states, controls, x0, gains_in, feedforwards_in, jacobians, gaps],
                        [new_states, new_controls, step], ["X", "U", "x0", "K", "k", "AB", "c"],
                        ["X_new", "U_new", "step"])
    return feedback, apply


def _interior_point_stage_functions(m: int, n: int) -> tuple[ca.Function, ...]:
    """The per-stage parts of :func:`riccati_feedback_function`'s interior-point iteration, each an SX function
    mapped over the ``n`` stages (``m`` controls a stage), computing what the iteration's elementwise MX operations
    computed, in the same order (the same numbers to the bit):

    * ``longest(s_low, s_up, λ_low, λ_up, Δv, Δλ_low, Δλ_up) → ρ``: per stage the longest step that keeps its slacks
      and duals nonnegative (``∞`` where nothing binds; ``min(1, fraction · min ρ)`` is the step);
    * ``barrier(v, low, up, λ_low, λ_up, g_u, μ) → (s_low, s_up, d, r)``: the slacks, the barrier's curvature
      ``d = λ_low/s_low + λ_up/s_up`` and the LQ problem's control gradient ``r``;
    * ``direction(v, v⁺, s_low, s_up, λ_low, λ_up, μ) → (Δv, Δλ_low, Δλ_up)``: the step to the LQ solution ``v⁺``;
    * ``update(v, Δv, λ_low, Δλ_low, λ_up, Δλ_up, low, up, α) → (v, λ_low, λ_up, λ_low s_low, λ_up s_up)``: the step
      taken and the complementarity products its ``μ`` sums.

    A ratio is selected by a comparison, where ``s / max(−Δ, 1e-300)`` called libm's ``fmax`` per entry (their
    minimum keeps ``fmin``: a chain of comparisons measured slower)."""
    v, low, up, target = (ca.SX.sym(name, m) for name in ("v", "low", "up", "v_next"))
    slack_low, slack_up, dual_low, dual_up = (ca.SX.sym(name, m) for name in ("s_low", "s_up", "dual_low", "dual_up"))
    dv, d_low, d_up, g_u = (ca.SX.sym(name, m) for name in ("dv", "d_low", "d_up", "g_u"))
    mu, alpha = ca.SX.sym("mu"), ca.SX.sym("alpha")

    def ratio(room: Any, change: Any) -> Any:
        return ca.if_else(change < 0, room / -change, ca.inf)

    longest = ca.Function("rti_ipm_longest_step", [slack_low, slack_up, dual_low, dual_up, dv, d_low, d_up],
                          [ca.mmin(ca.vertcat(ratio(slack_low, dv), ratio(slack_up, -dv), ratio(dual_low, d_low),
                                              ratio(dual_up, d_up)))], GENERATED_SX_OPTIONS)
    slack_low_now, slack_up_now = v - low, up - v
    curvature = dual_low / slack_low_now + dual_up / slack_up_now
    barrier = ca.Function("rti_ipm_barrier", [v, low, up, dual_low, dual_up, g_u, mu],
                          [slack_low_now, slack_up_now, curvature,
                           g_u - mu / slack_low_now + mu / slack_up_now - curvature * v], GENERATED_SX_OPTIONS)
    step = target - v
    direction = ca.Function("rti_ipm_direction", [v, target, slack_low, slack_up, dual_low, dual_up, mu],
                            [step, mu / slack_low - dual_low - dual_low / slack_low * step,
                             mu / slack_up - dual_up + dual_up / slack_up * step], GENERATED_SX_OPTIONS)
    v_next, dual_low_next, dual_up_next = v + alpha * dv, dual_low + alpha * d_low, dual_up + alpha * d_up
    update = ca.Function("rti_ipm_update", [v, dv, dual_low, d_low, dual_up, d_up, low, up, alpha],
                         [v_next, dual_low_next, dual_up_next, dual_low_next * (v_next - low),
                          dual_up_next * (up - v_next)], GENERATED_SX_OPTIONS)
    return tuple(function.map(n) for function in (longest, barrier, direction, update))


def _trust_region_update(layout: StateLayout, states: Any, controls: Any, x0: Any, deltas: Any, v: Any,
                         limits: np.ndarray, omega_valid: float, stage_low: np.ndarray, stage_high: np.ndarray,
                         n: int) -> tuple[Any, Any, Any]:
    """The QP's step applied to the plan: each stage's state step clipped to the trust region, retracted on
    S³, ``|ω|`` within ``omega_valid``, the first state the measured one, the controls within their bounds;
    and the step's size (largest ``|Δu|`` over the control range or ``|δ|`` over the trust region)."""
    ns, nd = layout.state_dim, layout.tangent_dim
    x_bar, step_k = ca.SX.sym("x_bar", ns), ca.SX.sym("step", nd)
    retracted = ca.Function("rti_retract", [x_bar, step_k], [layout.retract(x_bar, step_k, CA)],
                            GENERATED_SX_OPTIONS).map(n)
    bound = ca.repmat(ca.DM(limits), 1, n)
    steps = ca.fmin(ca.fmax(deltas, -bound), bound)
    moved = retracted(states[:, 1:], steps)
    new_states = ca.horzcat(x0, clip_rows(moved, layout.angular_rates, omega_valid))
    new_controls = ca.fmin(ca.fmax(controls + v, ca.DM(stage_low)), ca.DM(stage_high))
    step = ca.fmax(ca.mmax(ca.fabs(v) / ca.DM(np.minimum(stage_high - stage_low, 1e6))),
                   ca.mmax(ca.fabs(steps) / bound))
    return new_states, new_controls, step
