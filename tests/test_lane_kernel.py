"""Lane kernels (fvin_mpc.control.lane_kernel) against the scalar functions they translate: every operation, the
vector tanh against libm's, the learned and closed-form stages of the built-in scenes, a horizon that is not a
multiple of four, and the controller that maps its stages with them."""

from __future__ import annotations

import math
import shutil
import warnings

import casadi as ca
import numpy as np
import pytest
from helpers import stage_models

from fvin_mpc.control.lane_kernel import (
    LANES,
    UntranslatableCode,
    lane_map_kernel,
    lane_map_or_none,
    uses_lanes,
)
from fvin_mpc.control.model_export import GENERATED_SX_OPTIONS, kernel_function

pytestmark = pytest.mark.skipif(shutil.which("gcc") is None, reason="a lane kernel is C: it needs a compiler")


def lanes_of(function: ca.Function, count: int) -> ca.Function:
    return kernel_function(lane_map_kernel(function, count))


def ulps(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """How many doubles lie between ``a`` and ``b`` (same sign; 0 where both are equal)."""
    ia, ib = a.view(np.int64), b.view(np.int64)
    return np.where(a == b, 0, np.abs(ia - ib))


def test_vector_tanh_is_within_four_units_in_the_last_place_of_libms():
    """The prelude's tanh on whole vectors against ``math.tanh`` (libm) at 400,000 points: uniform on [-25, 25],
    log-spaced from 1e-300 to 30 with both signs (where expm1's reduction switches), and the special values:
    ±0 keep their sign, ±inf give ±1, NaN stays NaN."""
    x = ca.SX.sym("x")
    count = 100_000
    kernel = lanes_of(ca.Function("t", [x], [ca.tanh(x)]), count)
    rng = np.random.default_rng(3)
    small = np.logspace(-300, math.log10(30.0), count // 2)
    batches = [rng.uniform(-25.0, 25.0, count), np.concatenate([small, -small]),
               rng.uniform(-1.0, 1.0, count) * 10.0 ** rng.uniform(-8, 1, count)]
    for points in batches:
        got = np.asarray(kernel(points.reshape(1, -1))).ravel()
        want = np.array([math.tanh(value) for value in points])
        assert np.all(np.sign(got) == np.sign(want))
        assert ulps(got, want).max() <= 4
    special = np.array([0.0, -0.0, np.inf, -np.inf, np.nan, 22.0, 22.5, -1e-310])
    got = np.asarray(lanes_of(ca.Function("t", [x], [ca.tanh(x)]), special.size)(special.reshape(1, -1))).ravel()
    np.testing.assert_array_equal(got[:4], [0.0, -0.0, 1.0, -1.0])
    assert np.signbit(got[1]) and not np.signbit(got[0])
    assert np.isnan(got[4])
    np.testing.assert_array_equal(got[5:], [math.tanh(22.0), math.tanh(22.5), -1e-310])


def every_operation() -> ca.Function:
    """A function of two inputs (a 3-vector, a 2×2 matrix) and two outputs that makes CasADi write every
    operation a lane kernel translates: arithmetic with numbers, every function of the prelude, comparisons,
    logic, if_else, negation, copies."""
    x, y = ca.SX.sym("x", 3), ca.SX.sym("y", 2, 2)
    a, b, c = x[0], x[1], x[2]
    values = [a * b - c / 3.5, 1.0 / b, -a, ca.sqrt(ca.fabs(b)), ca.exp(c), ca.log(ca.fabs(a) + 1.0), ca.sin(a),
              ca.cos(b), ca.tan(c / 4.0), ca.asin(ca.tanh(a)), ca.acos(ca.tanh(b)), ca.atan(c), ca.sinh(a / 3.0),
              ca.cosh(b / 3.0), ca.floor(c), ca.ceil(a), ca.erf(b), ca.log1p(ca.fabs(c)), ca.expm1(a / 2.0), a ** 2,
              ca.sign(b), ca.fmax(a, b), ca.fmin(b, c), ca.atan2(a, b), ca.power(ca.fabs(c) + 0.5, a),
              ca.fmod(c, 0.7), ca.tanh(y[0, 1]), ca.if_else(a < b, c, y[1, 1]), ca.if_else(a <= c, y[0, 0], 0.0),
              a == b, a != c, ca.logic_and(a > 0, b < 0), ca.logic_or(a > 1, c < -1), ca.logic_not(c > 0), y[1, 0]]
    return ca.Function("every", [x, y], [ca.vertcat(*values), ca.horzcat(x[:2], y[:, 0] * a)], GENERATED_SX_OPTIONS)


@pytest.mark.parametrize("count", [1, LANES, 7, 13])
def test_every_operation_in_lanes_is_the_scalar_functions_map(count):
    """At ``count`` columns of random inputs (a horizon that is a multiple of four or not: the last lanes read
    the last stage and write nowhere), with zeros, ties and signs among them, the lane kernel gives the scalar
    map's outputs: bit for bit but for the vector tanh (4 units in the last place) and fused multiply–adds."""
    function = every_operation()
    rng = np.random.default_rng(count)
    x = rng.uniform(-2.0, 2.0, (3, count))
    x[:, 0] = [0.0, 0.0, -0.0]  # ties and signed zeros
    y = rng.uniform(-2.0, 2.0, (2, 2 * count))
    reference = [np.asarray(out) for out in function.map(count)(x, y)]
    translated = [np.asarray(out) for out in lanes_of(function, count)(x, y)]
    for want, got in zip(reference, translated):
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, rtol=1e-14, atol=1e-15)


def test_what_a_lane_kernel_does_not_translate_is_refused_with_the_reason():
    x = ca.SX.sym("x", 2)
    with pytest.raises(UntranslatableCode, match="sparse"):
        lane_map_kernel(ca.Function("sparse", [x], [ca.vertcat(x[0], ca.SX(1, 1))]), 8)
    with pytest.raises(UntranslatableCode, match="not a scalar"):
        symbol = ca.MX.sym("x")
        lane_map_kernel(ca.Function("mx", [symbol], [symbol * 2]), 8)
    inverse_erf = ca.Function("erfinv", [x], [ca.erfinv(x)])
    with pytest.raises(UntranslatableCode, match="erfinv"):
        lane_map_kernel(inverse_erf, 8)
    with pytest.raises(ValueError, match="count >= 1"):
        lane_map_kernel(every_operation(), 0)
    with pytest.warns(RuntimeWarning, match="not in lanes.*erfinv"):
        assert lane_map_or_none("auto", inverse_erf, 8) is None
    with pytest.raises(UntranslatableCode):
        lane_map_or_none("on", inverse_erf, 8)


def test_the_choice_of_lanes():
    assert uses_lanes("auto", compiled=True, relinearize_every=1, unrolled=True)
    assert not uses_lanes("auto", compiled=False, relinearize_every=1, unrolled=True)
    assert not uses_lanes("auto", compiled=True, relinearize_every=4, unrolled=True)
    assert not uses_lanes("auto", compiled=True, relinearize_every=1, unrolled=False)
    assert not uses_lanes("off", compiled=True, relinearize_every=1, unrolled=True)
    with pytest.raises(ValueError, match="relinearize_every=1"):
        uses_lanes("on", compiled=True, relinearize_every=3, unrolled=True)
    with pytest.raises(ValueError, match="unknown stage_lanes"):
        uses_lanes("sometimes", compiled=True, relinearize_every=1, unrolled=True)


def test_a_stage_in_lanes_is_the_generated_stage_to_rounding():
    """The dynamics stage the controllers map in lanes (:func:`~fvin_mpc.control.linearization.unrolled_stage_function`,
    parametric, with term expansions) of the learned and closed-form ball joint and quadrotor, at 10 random nodes
    (quaternions on and off unit norm): gaps and ``[A B]`` within 1e-12 of their size of the scalar map's."""
    from fvin_mpc.control.linearization import unrolled_stage_function

    rng = np.random.default_rng(5)
    count = 10
    for scene, true_model, model in stage_models(("spherical_pendulum", "quadrotor")):
        layout, m = model.space.layout, model.control_dim
        stage = unrolled_stage_function(model.parametric_step, layout, m, model=model)
        dense = ca.Function("stage", stage.sx_in(), [ca.densify(out) for out in stage.call(stage.sx_in())])
        nodes = []
        for _ in range(2):
            x = 0.7 * rng.standard_normal((layout.state_dim, count))
            q = rng.standard_normal((4, count))
            quaternion = layout.attitude("test").quaternion
            x[quaternion] = q * (1.0 + 1e-3 * (np.arange(count) % 2)) / np.linalg.norm(q, axis=0)
            nodes.append(x)
        inputs = [nodes[0], rng.uniform(-0.5, 0.5, (m, count)), nodes[1], rng.uniform(-0.1, 0.1, (m, count)),
                  np.repeat(model.model_parameters.defaults.reshape(-1, 1), count, axis=1)]
        reference = [np.asarray(out) for out in dense.map(count)(*inputs)]
        translated = [np.asarray(out) for out in lanes_of(dense, count)(*inputs)]
        for want, got in zip(reference, translated):
            assert np.all(np.isfinite(want))
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max(),
                                       err_msg=f"{scene} {'true' if true_model else 'learned'}")


def test_a_controller_linearizes_in_lanes_as_it_does_without():
    """The learned ball joint's real-time MPC with ``stage_lanes`` "auto" (its two maps in lanes) and "off": at the
    plans of a short closed loop (a swing-up's first periods, cold start included), the same linearization to
    1e-11 of each output's size. (Whole episodes are not compared: a swing-up's multi-start and unconverged QPs
    carry a 1e-16 difference to visibly different torques within a second, as any change of rounding does.)"""
    from fvin_mpc.control.closed_loop import run_episode
    from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings

    env = scene_env("spherical_pendulum")
    model = scene_model(env)
    controllers = {}
    for choice in ("auto", "off"):
        settings = scene_mpc_settings(env, solver="rti", rti={"stage_lanes": choice})
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)  # "auto" translates the whole stage
            controllers[choice] = scene_mpc(env, model, settings)
    horizon = controllers["auto"].horizon
    assert [kernel.name for kernel in controllers["auto"].loop_kernels] == [
        f"fvin_lanes_rti_dynamics_{horizon}", f"fvin_lanes_rti_stage_cost_{horizon}"]
    assert controllers["off"].loop_kernels == ()
    lanes, generated = controllers["auto"], controllers["off"]
    plans, prepare = [], lanes.prepare

    def recorded() -> None:  # the plans its preparations linearize at
        plans.append(lanes.plan)
        prepare()

    lanes.prepare = recorded
    episode, _ = run_episode(env, lanes, 0.3, {"random": True}, seed=2, latency="none")
    assert len(plans) == episode.u.shape[0] > 0
    generated.reset()
    for plan in plans:
        want = [np.array(out, dtype=float) for out in generated.linearize(plan)]
        got = [np.array(out, dtype=float) for out in lanes.linearize(plan)]
        for a, b in zip(got, want):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-11 * max(np.abs(b).max(), 1e-300))
