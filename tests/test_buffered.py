"""BufferedFunction against CasADi's own call: same numbers, shapes callers can rely on."""

import casadi as ca
import numpy as np
import pytest

from fvin_mpc.control.buffered import BufferedFunction


def _function() -> ca.Function:
    states, control = ca.MX.sym("X", 3, 4), ca.MX.sym("u", 2)
    return ca.Function("f", [states, control],
                       [ca.sin(states) * control[0], ca.diag(control), ca.sumsqr(states), states[:, 1], states[0, :]])


def test_matches_casadi_call_for_dense_sparse_column_and_scalar_results():
    function, rng = _function(), np.random.default_rng(0)
    buffered = BufferedFunction(function)
    for _ in range(3):  # buffers are reused: later calls must not see earlier arguments
        states, control = rng.normal(size=(3, 4)), rng.normal(size=2)
        results, expected = buffered(states, control), function(states, control)
        assert [r.shape for r in results] == [(3, 4), (2, 2), (), (3,), (1, 4)]
        for result, reference in zip(results, expected):
            np.testing.assert_array_equal(result, np.asarray(reference).reshape(result.shape))
        assert float(results[2]) == pytest.approx(np.sum(states ** 2))


def test_results_are_copies_not_views_of_the_buffers():
    buffered = BufferedFunction(_function())
    first = buffered(np.ones((3, 4)), np.ones(2))[0]
    kept = first.copy()
    buffered(np.zeros((3, 4)), np.zeros(2))
    np.testing.assert_array_equal(first, kept)


def test_transposed_and_column_arguments_are_read_in_casadi_order():
    x = ca.MX.sym("x", 2, 3)
    function = ca.Function("g", [x], [x])
    value = np.arange(6.0).reshape(3, 2).T  # a transposed (non C-contiguous) view, as rti passes plans
    np.testing.assert_array_equal(BufferedFunction(function)(value)[0], value)


def test_bad_calls_are_refused():
    buffered = BufferedFunction(_function())
    with pytest.raises(TypeError, match="takes 2 arguments"):
        buffered(np.ones((3, 4)))
    with pytest.raises(ValueError):
        buffered(np.ones((4, 4)), np.ones(2))
    sparse = ca.MX.sym("s", ca.Sparsity.diag(3))
    with pytest.raises(ValueError, match="sparse"):
        BufferedFunction(ca.Function("h", [sparse], [ca.sum1(sparse)]))


def test_compiled_rti_functions_agree_with_their_unbuffered_calls():
    from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings

    env = scene_env("pendulum")
    controller = scene_mpc(env, scene_model(env, true_model=True),
                           scene_mpc_settings(env, solver="rti", rti={"relinearize_every": 3}))
    x0 = np.array([0.0, 1.0, 0.0, 0.0, 0.0, 0.3, 0.0])
    controller(x0)
    controller.prepare()
    plan = controller.plan
    buffered = controller.loop_function("rti_linearize_blocks")
    _, _, scales, references = controller._sample_reference()
    targets = np.clip(scales[:, None] * controller._u_goal, controller.torque_low, controller.torque_high).T
    renewed = controller.kept_jacobians[3]
    assert 0 < renewed.sum() < renewed.size
    arguments = (plan.states.T, plan.controls.T, references, controller.disturbance, targets, controller.parameters,
                 *controller.nothing_kept, renewed.reshape(1, -1))  # some items kept (as zeros)
    for result, reference in zip(buffered(*arguments), buffered.function(*arguments)):
        np.testing.assert_allclose(result, np.asarray(reference).reshape(result.shape), rtol=0, atol=0)
