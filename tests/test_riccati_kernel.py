"""The hand-written Riccati stage (fvin_mpc.control.riccati_kernel) against the generated one, its reference."""

from __future__ import annotations

import shutil

import casadi as ca
import numpy as np
import pytest

from fvin_mpc.control.model_export import kernel_function
from fvin_mpc.control.riccati_kernel import riccati_stage_kernel, uses_kernel
from fvin_mpc.control.riccati_qp import riccati_stage_function

pytestmark = pytest.mark.skipif(shutil.which("gcc") is None, reason="the kernel is C: it needs a compiler")


def _stage_inputs(rng, nd, m, symmetric=True):
    """Random inputs of a stage as the QP builds them: ``P``, ``H`` symmetric positive definite, ``d ≥ 0``.
    ``symmetric=False``: ``P`` and ``H`` with different numbers in the triangles neither stage reads."""
    s = nd + m
    root = rng.standard_normal((s + 2, s))
    H = root.T @ root / s + 1e-3 * np.eye(s)
    root = rng.standard_normal((nd + 2, nd))
    P = root.T @ root / nd + np.eye(nd)
    if not symmetric:
        P = np.triu(P) + np.tril(rng.standard_normal((nd, nd)), -1)
        H[:nd, :nd] = np.triu(H[:nd, :nd]) + np.tril(rng.standard_normal((nd, nd)), -1)
        H[nd:, nd:] = np.triu(H[nd:, nd:]) + np.tril(rng.standard_normal((m, m)), -1)
        H[:nd, nd:] = rng.standard_normal((nd, m))  # the upper-right block: S is read from the lower-left
    AB = np.hstack([np.eye(nd) + 0.3 * rng.standard_normal((nd, nd)), rng.standard_normal((nd, m))])
    return [P, rng.standard_normal(nd), H, rng.standard_normal(s), AB, rng.standard_normal(nd),
            np.abs(rng.standard_normal(m)) * 10.0 ** rng.uniform(-3, 3, m), rng.standard_normal(m)]


@pytest.mark.parametrize(("nd", "m"), [(12, 4), (12, 1), (12, 6), (6, 3), (6, 1), (9, 2), (3, 5)])
def test_the_kernel_computes_the_generated_stage(nd, m):
    """Every output of the kernel equals the generated stage's to rounding (1e-12 of its size), at random
    stages of the sizes in use (free bodies 12, pivoted 6) and others (padding: 9, 3), with barrier curvatures
    from 1e-3 to 1e3 — and reads the same triangles: numbers where neither reads change nothing."""
    reference, kernel = riccati_stage_function(nd, m), kernel_function(riccati_stage_kernel(nd, m))
    rng = np.random.default_rng(nd * 10 + m)
    for trial in range(20):
        inputs = _stage_inputs(rng, nd, m, symmetric=trial % 2 == 0)
        for name, expected, got in zip(("P_prev", "p_prev", "K", "k"), reference.call(inputs), kernel.call(inputs)):
            expected, got = np.asarray(expected), np.asarray(got)
            assert np.all(np.isfinite(got)), name
            np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12 * max(1.0, np.abs(expected).max()),
                                       err_msg=f"{name}, n_delta={nd}, m={m}")


@pytest.mark.parametrize(("nd", "m", "n"), [(12, 4, 5), (6, 3, 7), (12, 1, 1)])
def test_the_sweep_kernel_runs_the_generated_stages_backward(nd, m, n):
    """The whole-sweep kernel (what the feedback calls) gives the gains and feedforwards of the generated stage run
    backward by a ``mapaccum`` over the reversed stages (as the generated feedback runs it), in the stages' order
    and to rounding; and the C generated from a graph that calls it declares and calls its symbol."""
    rng = np.random.default_rng(nd + 10 * m + 100 * n)
    stages = [_stage_inputs(rng, nd, m) for _ in range(n)]
    terminal, terminal_gradient = stages[0][0], stages[0][1]

    def stacked(index, order):
        blocks = [stages[k][index] for k in order]
        return np.column_stack(blocks) if blocks[0].ndim == 1 else np.hstack(blocks)

    forward, backward = range(n), range(n - 1, -1, -1)
    _, _, gains, feedforwards = riccati_stage_function(nd, m).mapaccum("acc", n, 2).call(
        [terminal, terminal_gradient, *(stacked(i, backward) for i in range(2, 8))])
    gains, feedforwards = np.asarray(gains), np.asarray(feedforwards)
    gains = np.hstack([gains[:, (n - 1 - k) * nd:(n - k) * nd] for k in range(n)])  # back to the stages' order
    feedforwards = feedforwards[:, ::-1]
    kernel = riccati_stage_kernel(nd, m, n)
    sweep = kernel_function(kernel)
    got_gains, got_feedforwards = (np.asarray(x) for x in sweep.call(
        [terminal, terminal_gradient, *(stacked(i, forward) for i in range(2, 8))]))
    for expected, got in ((gains, got_gains), (feedforwards, got_feedforwards)):
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-11 * max(1.0, np.abs(expected).max()))
    generator = ca.CodeGenerator("graph.c")
    inputs = [ca.MX.sym(f"i{i}", sweep.sparsity_in(i)) for i in range(sweep.n_in())]
    generator.add(ca.Function("graph", inputs, sweep.call(inputs)))
    source = generator.dump()
    assert f"int {kernel.name}(const casadi_real** arg" in source and f"{kernel.name}(arg" in source


def test_which_stage_a_controller_runs():
    """``riccati_stage``: "auto" takes the kernel for free bodies with compiled code and the path-following
    method only; "kernel" where it cannot run is refused with the reason; unknown names are refused."""
    assert uses_kernel("auto", 12, True, "path") and not uses_kernel("auto", 6, True, "path")
    assert not uses_kernel("auto", 12, False, "path") and not uses_kernel("auto", 12, True, "mehrotra")
    assert not uses_kernel("generated", 12, True, "path") and uses_kernel("kernel", 6, True, "path")
    with pytest.raises(ValueError, match="compile='cached'"):
        uses_kernel("kernel", 12, False, "path")
    with pytest.raises(ValueError, match="predictor-corrector"):
        uses_kernel("kernel", 12, True, "mehrotra")
    with pytest.raises(ValueError, match="unknown riccati_stage"):
        uses_kernel("fast", 12, True, "path")
    with pytest.raises(ValueError, match="n_delta >= 1"):
        riccati_stage_kernel(0, 2)
    with pytest.raises(ValueError, match="horizon >= 1"):
        riccati_stage_kernel(12, 4, 0)
