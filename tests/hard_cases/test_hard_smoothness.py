"""ξ exactly 0 and tiny rotations (1e-12 … 1e-6): finite values and derivatives of the step in
both backends — torch autograd (first and second derivatives) and CasADi (jacobian, hessian).

At hanging or upright rest with no torque the increment is exactly ``ξ = 0`` (``H∇U = 0``);
tiny ``ω``/``u`` give tiny ``ξ``. The sinc/cos series branches and the safe square root of the
Newton residual must keep every derivative finite there (DESIGN.md, "Write sin|v|/|v| as a sinc
that is smooth at 0").
"""

import casadi as ca
import numpy as np
import pytest
import strategies as S
import torch  # noqa: E402  (a dependency: a missing torch is a failure, not a skip)
from hypothesis import given, settings
from hypothesis import strategies as st

from fvin_mpc.control import model_export as export
from fvin_mpc.core import fvin, s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.networks import LearnedTerms, ModelConfig, init_weights
from fvin_mpc.core.rigid_body import PENDULUM

H = 0.05
RESTS = [np.array([1.0, 0, 0, 0]), np.array([-1.0, 0, 0, 0]), np.array([0, 0, 1.0, 0]), np.array([0, 0, -1.0, 0])]

tiny = st.one_of(st.just(0.0), S.signed_log_uniform(1e-12, 1e-6))
tiny_vectors = st.tuples(tiny, tiny, tiny).map(np.array)


@pytest.fixture(scope="module")
def casadi_derivatives():
    """Value, Jacobian and Hessian (of |x'|² and of the residual) of the exported PENDULUM step, K = 2 and 4."""
    functions = {}
    for k in (2, 4):
        model = export.from_rigid_body(PENDULUM, H, k, name=f"smooth_k{k}")
        x, u = ca.SX.sym("x", 7), ca.SX.sym("u", 1)
        x_next, residual = model.step(x, u)
        xu = ca.vertcat(x, u)
        functions[k] = ca.Function(f"d{k}", [x, u], [
            x_next, residual, ca.jacobian(x_next, xu), ca.hessian(ca.sumsqr(x_next), xu)[0],
            ca.jacobian(residual, xu), ca.hessian(residual, xu)[0],
        ])
    return functions


@settings(max_examples=S.budget(600))
@given(rest=st.sampled_from(RESTS), omega=tiny_vectors, u=tiny, k=st.sampled_from([2, 4]))
@S.counted
def test_casadi_derivatives_finite_at_and_near_zero_increment(casadi_derivatives, rest, omega, u, k):
    values = casadi_derivatives[k](np.concatenate([rest, omega]), [u])
    for value in values:
        assert np.all(np.isfinite(np.asarray(value))), value
    x_next = np.asarray(values[0]).ravel()
    # A tiny increment: q moves by O(h|ω| + h²|u|) only.
    assert np.linalg.norm(x_next[:4] - rest) <= 10 * H * (np.linalg.norm(omega) + abs(u)) + 1e-15
    if not np.any(omega) and u == 0.0:
        np.testing.assert_array_equal(x_next[:4], rest)  # ξ exactly 0: q unchanged to the bit
        assert float(values[1]) == 0.0


def torch_step_function(terms_factory, k):
    ops = get_ops("torch")

    def step(xu):
        q = tuple(xu[i : i + 1] for i in range(4))
        omega = tuple(xu[4 + i : 5 + i] for i in range(3))
        u = (xu[7:8],)
        out = fvin.fvin_step(q, omega, u, terms_factory(ops), H, k, ops, with_residual=True)
        return torch.cat([*out.q, *out.omega, out.residual])

    return step


@settings(max_examples=S.budget(6))  # a torch Hessian costs ~0.2 s
@given(rest=st.sampled_from(RESTS), omega=tiny_vectors, u=tiny, k=st.sampled_from([2, 3]))
@S.counted
def test_torch_first_and_second_derivatives_finite_near_zero_increment(rest, omega, u, k):
    step = torch_step_function(PENDULUM.terms, k)
    xu = torch.tensor(np.concatenate([rest, omega, [u]]), dtype=torch.float64)
    jacobian = torch.autograd.functional.jacobian(step, xu)
    # One Hessian covers x' and the residual: Σ x'² + residual.
    hessian = torch.autograd.functional.hessian(lambda z: (step(z)[:7] ** 2).sum() + step(z)[7], xu)
    for value in (step(xu), jacobian, hessian):
        assert torch.all(torch.isfinite(value)), value


@pytest.fixture(scope="module")
def learned_pair():
    config = ModelConfig(variant="sign-invariant", newton_iters=2)
    weights = init_weights(config, seed=5)
    return config, weights


@settings(max_examples=S.budget(8))
@given(q=S.unit_quaternions(), omega=tiny_vectors, u=tiny)
@S.counted
def test_learned_model_derivatives_finite_for_tiny_velocities(learned_pair, q, omega, u):
    """The learned sign-invariant model at tiny ω and u (ξ small but not 0: U's gradient acts):
    torch Jacobian and Hessian finite."""
    config, weights = learned_pair
    step = torch_step_function(lambda ops: LearnedTerms(
        {n: torch.as_tensor(w) for n, w in weights.items()} if ops.name == "torch" else weights, config, ops), 2)
    xu = torch.tensor(np.concatenate([q, omega, [u]]), dtype=torch.float64)
    jacobian = torch.autograd.functional.jacobian(step, xu)
    hessian = torch.autograd.functional.hessian(lambda z: (step(z)[:7] ** 2).sum(), xu)
    assert torch.all(torch.isfinite(jacobian)) and torch.all(torch.isfinite(hessian))


def test_exp_and_log_series_are_smooth_through_zero():
    """s3.exp/log at exactly 0 and 1e-12 … 1e-6 in torch: value, gradient and second derivative
    finite and continuous with the closed form (the branches meet at the threshold)."""
    ops = get_ops("torch")
    for scale in (0.0, 1e-12, 1e-9, 1e-6, 0.09, 0.11):
        v = torch.tensor([scale, -0.5 * scale, 0.3 * scale], dtype=torch.float64, requires_grad=True)
        q = s3.exp(tuple(v[i] for i in range(3)), ops)
        total = sum(c * w for c, w in zip(q, (0.3, -1.0, 2.0, 0.5)))
        (grad,) = torch.autograd.grad(total, v, create_graph=True)
        second = torch.autograd.grad(grad.sum(), v)[0]
        assert torch.all(torch.isfinite(grad)) and torch.all(torch.isfinite(second))
        w = torch.stack(q).detach().clone().requires_grad_(True)
        back = s3.log(tuple(w[i] for i in range(4)), ops)
        (g,) = torch.autograd.grad(sum(back), w)
        assert torch.all(torch.isfinite(g))
        np.testing.assert_allclose(torch.stack(back).detach().numpy(), v.detach().numpy(), atol=1e-15)
