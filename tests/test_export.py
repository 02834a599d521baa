"""The CasADi export against the torch model: values, Jacobians, smoothness at ξ = 0, files, cache."""

import casadi as ca
import numpy as np
import pytest
from helpers import random_states

from fvin_mpc.control import model_export as export
from fvin_mpc.core.checkpoint import save_checkpoint
from fvin_mpc.core.networks import ModelConfig, init_weights
from fvin_mpc.core.rigid_body import PENDULUM


@pytest.fixture(params=[("sign-invariant", 1, False, None), ("fixed-inertia", 1, False, None), ("plain", 3, True, None),
                        ("sign-invariant", 2, True, (0.2, -0.1, 1.0))],
                ids=["sign-invariant-m1", "fixed-inertia-m1", "plain-m3-damped", "vertical-m2-damped"])
def model_pair(request, tmp_path):
    """A random-weight checkpoint as a torch model and as its CasADi export."""
    torch = pytest.importorskip("torch")
    from fvin_mpc.learning.model import S3FVIN

    variant, control_dim, dissipation, vertical = request.param
    config = ModelConfig(variant=variant, control_dim=control_dim, dissipation=dissipation, newton_iters=3,
                         vertical=vertical)
    weights = init_weights(config, seed=7)
    stem = save_checkpoint(tmp_path / "model", config, weights, scene="test")
    return S3FVIN(config, weights), export.from_checkpoint(stem), torch


def test_export_equals_torch_step_to_1e_10(model_pair):
    torch_model, exported, torch = model_pair
    q, omega = random_states(16, seed=1)
    u = np.random.default_rng(2).uniform(-2, 2, size=(16, exported.control_dim))
    out = torch_model.step(*(torch.as_tensor(a) for a in (q, omega, u)))
    expected = np.concatenate([out.q.detach().numpy(), out.omega.detach().numpy()], axis=1)
    mapped = exported.step.map(16)
    actual = np.asarray(mapped(np.concatenate([q, omega], 1).T, u.T)[0]).T
    np.testing.assert_allclose(actual, expected, atol=1e-10, rtol=0)


def test_export_jacobian_equals_torch_autograd_to_1e_8(model_pair):
    torch_model, exported, torch = model_pair
    x_sym, u_sym = ca.SX.sym("x", 7), ca.SX.sym("u", exported.control_dim)
    x_next = exported.step(x_sym, u_sym)[0]
    jacobian = ca.Function("step_jacobian", [x_sym, u_sym], [ca.jacobian(x_next, ca.vertcat(x_sym, u_sym))])
    q, omega = random_states(4, seed=3)
    for i in range(4):
        x = np.concatenate([q[i], omega[i]])
        u = np.linspace(-1.0, 1.5, exported.control_dim)

        def torch_step(xu):
            out = torch_model.step(xu[None, :4], xu[None, 4:7], xu[None, 7:])
            return torch.cat([out.q[0], out.omega[0]])

        expected = torch.autograd.functional.jacobian(torch_step, torch.as_tensor(np.concatenate([x, u])))
        np.testing.assert_allclose(np.asarray(jacobian(x, u)), expected.numpy(), atol=1e-8, rtol=0)


def test_derivatives_finite_at_zero_increment():
    """At rest with no torque and no gravity gradient the increment ξ is exactly 0."""
    model = export.from_rigid_body(PENDULUM, 0.05, 3)
    x_sym, u_sym = ca.SX.sym("x", 7), ca.SX.sym("u", 1)
    x_next, residual = model.step(x_sym, u_sym)
    xu = ca.vertcat(x_sym, u_sym)
    derivatives = ca.Function(
        "step_derivatives",
        [x_sym, u_sym],
        [ca.jacobian(x_next, xu), ca.hessian(ca.sumsqr(x_next), xu)[0], ca.jacobian(residual, xu)],
    )
    for x in ([1.0, 0, 0, 0, 0, 0, 0], [0.0, 0, 1.0, 0, 0, 0, 0]):  # hanging and upright: ∇U·H = 0
        x_next_value, _ = model(np.array(x), np.zeros(1))
        np.testing.assert_allclose(x_next_value, x, atol=1e-15)
        for value in derivatives(x, [0.0]):
            assert np.all(np.isfinite(np.asarray(value)))


def test_save_and_load_round_trip(tmp_path):
    model = export.from_rigid_body(PENDULUM, 0.05, 2)
    loaded = export.load_function(export.save_function(model.step, tmp_path / "step.casadi"))
    x, u = np.array([0.8, 0.0, 0.6, 0.0, 0.0, 1.0, 0.0]), np.array([0.5])
    np.testing.assert_array_equal(np.asarray(loaded(x, u)[0]), np.asarray(model.step(x, u)[0]))


def test_load_errors_are_clear(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        export.load_function(tmp_path / "missing.casadi")
    (tmp_path / "junk.casadi").write_bytes(b"not a casadi file")
    with pytest.raises(ValueError, match="not a readable CasADi function"):
        export.load_function(tmp_path / "junk.casadi")


def test_compiled_functions_are_cached_and_equal(tmp_path, monkeypatch):
    monkeypatch.setenv("FVIN_MPC_CACHE", str(tmp_path / "cache"))
    model = export.from_rigid_body(PENDULUM, 0.05, 2)
    x_sym, u_sym = ca.SX.sym("x", 7), ca.SX.sym("u", 1)
    step = ca.Function("step_only", [x_sym, u_sym], [model.step(x_sym, u_sym)[0]])
    first, report_first = export.compile_functions([step], prefix="test")
    second, report_second = export.compile_functions([step], prefix="test")
    assert not report_first.cached and report_first.compile_s > 0
    assert report_second.cached and report_second.compile_s == 0 and report_second.library == report_first.library
    x, u = np.array([0.8, 0.0, 0.6, 0.0, 0.0, 1.0, 0.0]), np.array([0.5])
    np.testing.assert_allclose(np.asarray(second["step_only"](x, u)), np.asarray(step(x, u)), atol=1e-15)
    # Different math (another K) is another library.
    other = export.from_rigid_body(PENDULUM, 0.05, 3)
    step_k3 = ca.Function("step_only", [x_sym, u_sym], [other.step(x_sym, u_sym)[0]])
    _, report_other = export.compile_functions([step_k3], prefix="test")
    assert not report_other.cached and report_other.library != report_first.library


def _pendulum_step() -> ca.Function:
    model = export.from_rigid_body(PENDULUM, 0.05, 2)
    x_sym, u_sym = ca.SX.sym("x", 7), ca.SX.sym("u", 1)
    return ca.Function("step_only", [x_sym, u_sym], [model.step(x_sym, u_sym)[0]])


@pytest.fixture
def fresh_target_flags():
    """The host's target flags found again in the test (they are cached per process), and after it."""
    export.generated_code_flags.cache_clear()
    yield
    export.generated_code_flags.cache_clear()


def test_code_compiled_for_this_cpu_is_keyed_by_it_and_equals_the_portable_build(tmp_path, monkeypatch,
                                                                                  fresh_target_flags):
    """``-march=native`` where the compiler takes it; the library's cache key names the CPU, so a cache shared
    with another CPU gives it its own library; the portable build (``FVIN_MPC_PORTABLE=1``) is another library
    with the same results to rounding."""
    monkeypatch.setenv("FVIN_MPC_CACHE", str(tmp_path / "cache"))
    step = _pendulum_step()
    if export.generated_code_flags() != ("-march=native",):
        pytest.skip("the compiler does not take -march=native")
    native, report = export.compile_functions([step], prefix="test")
    monkeypatch.setattr(export, "host_cpu", lambda: "another CPU")
    _, report_other_cpu = export.compile_functions([step], prefix="test")
    assert not report_other_cpu.cached and report_other_cpu.library != report.library
    monkeypatch.setenv(export.PORTABLE_ENV, "1")
    export.generated_code_flags.cache_clear()
    assert export.generated_code_flags() == ()
    portable, report_portable = export.compile_functions([step], prefix="test")
    assert report_portable.library not in (report.library, report_other_cpu.library)
    states = [np.array([np.cos(a / 2), np.sin(a / 2) * 0.6, np.sin(a / 2) * 0.8, 0.0, w, -w, 0.3])
              for a, w in zip(np.linspace(-3.0, 3.0, 7), np.linspace(-8.0, 8.0, 7))]
    for x in states:
        np.testing.assert_allclose(np.asarray(native["step_only"](x, [0.7])),
                                   np.asarray(portable["step_only"](x, [0.7])), rtol=1e-13, atol=1e-15)


def test_a_compiler_without_native_targets_builds_portable_code_and_says_so(tmp_path, monkeypatch,
                                                                           fresh_target_flags):
    compiler = tmp_path / "old-cc"
    compiler.write_text('#!/bin/sh\nfor a in "$@"; do [ "$a" = -march=native ] && { echo "unknown target" >&2; '
                        'exit 1; }; done\nexec gcc "$@"\n')
    compiler.chmod(0o755)
    with pytest.warns(RuntimeWarning, match="does not take -march=native"):
        assert export.generated_code_flags(str(compiler)) == ()
    monkeypatch.setenv("FVIN_MPC_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("CC", str(compiler))
    compiled, _ = export.compile_functions([_pendulum_step()], prefix="test")  # the baseline build works
    assert np.all(np.isfinite(np.asarray(compiled["step_only"]([1.0, 0, 0, 0, 0, 0, 0], [0.1]))))
