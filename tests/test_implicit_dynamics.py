"""The real-time iteration's implicit dynamics (``fvin_mpc.control.implicit_dynamics``) against the
unrolled step it replaces: at consistent nodes its gap and Jacobians are the converged step's, by the
implicit function theorem; off them the gap is one exact Newton step in ``ω``. Then the controller
built on it: the swing-up from exact rest, and a clear error where it does not apply."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from fvin_mpc.control import implicit_dynamics
from fvin_mpc.control import model_export as export
from fvin_mpc.control.closed_loop import episode_metrics, run_episode
from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.networks import LearnedTerms, ModelConfig, init_weights
from fvin_mpc.core.rigid_body import PENDULUM_DAMPED
from fvin_mpc.core.space import PIVOTED

CA = get_ops("casadi")


def unrolled_stage(terms, step_size, newton_iters):
    """The unrolled formulation's gap and ``[A B]`` (as :mod:`fvin_mpc.control.rti` builds them)."""
    m = terms.control_dim
    step = export.step_function(terms, step_size, newton_iters)
    x_bar, x_next_bar, u_bar, d = ca.SX.sym("x", 7), ca.SX.sym("xn", 7), ca.SX.sym("u", m), ca.SX.sym("d", m)
    delta, du = ca.SX.sym("delta", 6), ca.SX.sym("du", m)
    gap = PIVOTED.local(x_next_bar, step(PIVOTED.retract(x_bar, delta, CA), u_bar + du + d)[0], CA)
    zero = ca.DM.zeros(6 + m)
    gap_at, jacobian = ca.substitute([gap, ca.jacobian(gap, ca.vertcat(delta, du))], [ca.vertcat(delta, du)], [zero])
    return ca.Function("unrolled", [x_bar, u_bar, x_next_bar, d], [gap_at, jacobian]), step


@pytest.mark.parametrize("terms", [
    LearnedTerms(init_weights(ModelConfig(variant="sign-invariant", control_dim=3), seed=2),
                 ModelConfig(variant="sign-invariant", control_dim=3), CA),
    LearnedTerms(init_weights(ModelConfig(variant="fixed-inertia", control_dim=1), seed=2),
                 ModelConfig(variant="fixed-inertia", control_dim=1), CA),
    PENDULUM_DAMPED.terms(CA),
], ids=["sign-invariant", "fixed-inertia", "closed-form-damped"])
def test_implicit_stage_is_the_converged_steps_linearization(terms):
    h, m = 0.05, terms.control_dim
    node, layout = implicit_dynamics.node_terms_function(terms)
    stage = implicit_dynamics.implicit_stage_function(terms, layout, h)
    reference, step = unrolled_stage(terms, h, newton_iters=8)
    rng = np.random.default_rng(3)
    for _ in range(4):
        q = rng.normal(size=4)
        x = np.concatenate([q / np.linalg.norm(q), 3.0 * rng.normal(size=3)])
        u, d = rng.normal(size=m), 0.1 * rng.normal(size=m)
        x_next = np.asarray(step(x, u + d)[0]).ravel()
        for omega_offset in (0.0, 1e-3):
            x_next_bar = x_next + np.concatenate([np.zeros(4), np.full(3, omega_offset)])
            gap, jacobian = (np.asarray(a) for a in stage(x, u, x_next_bar, d, *node(x[:4]), *node(x_next_bar[:4])))
            gap_ref, jacobian_ref = (np.asarray(a) for a in reference(x, u, x_next_bar, d))
            # the residual is linear in ω_{k+1}: the gap is exact off the nodes too
            np.testing.assert_allclose(gap, gap_ref, atol=1e-12)
            if omega_offset == 0.0:  # consistent nodes: the implicit function theorem, exactly
                np.testing.assert_allclose(jacobian, jacobian_ref, atol=1e-11)
            else:  # the Jacobian is taken at the node, not at F's end: off by the gap's order
                assert np.abs(jacobian - jacobian_ref).max() < 0.1


def test_implicit_stage_ignores_the_next_nodes_quaternion_sign_for_a_sign_invariant_model():
    config = ModelConfig(variant="sign-invariant", control_dim=3)
    terms = LearnedTerms(init_weights(config, seed=4), config, CA)
    node, layout = implicit_dynamics.node_terms_function(terms)
    stage = implicit_dynamics.implicit_stage_function(terms, layout, 0.05)
    step = export.step_function(terms, 0.05, 8)
    x, u, d = np.array([0.5, 0.5, -0.5, 0.5, 1.0, -2.0, 0.5]), np.array([0.3, -0.2, 0.1]), np.zeros(3)
    x_next = np.asarray(step(x, u)[0]).ravel()
    flipped = np.concatenate([-x_next[:4], x_next[4:]])
    plus = stage(x, u, x_next, d, *node(x[:4]), *node(x_next[:4]))
    minus = stage(x, u, flipped, d, *node(x[:4]), *node(flipped[:4]))
    for a, b in zip(plus, minus):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-12)


@pytest.fixture(scope="module")
def pendulum():
    env = scene_env("pendulum", true_model=True)
    return env, scene_model(env, true_model=True)


def test_implicit_rti_swings_up_from_exact_rest_and_holds(pendulum):
    env, model = pendulum
    settings = scene_mpc_settings(env, solver="rti", rti={"dynamics": "implicit", "cold_budget_s": 60.0})
    controller = scene_mpc(env, model, settings)
    trajectory, _ = run_episode(env, controller, 8.0, latency=0.01)  # hanging exactly at rest
    metrics = episode_metrics(trajectory)
    assert metrics["success"] and metrics["hold_error_rad"] < 1e-3
    assert metrics["deadline_misses"] == 0 and metrics["controller_failures"] == 0


def test_implicit_rti_refuses_a_model_without_rigid_body_terms(pendulum):
    env, model = pendulum
    bare = export.ExportedModel(step=model.step, step_size=model.step_size, newton_iters=model.newton_iters,
                                control_dim=model.control_dim, numpy_terms=model.numpy_terms, name="bare",
                                energy_function=model.energy_function)
    with pytest.raises(ValueError, match="rti.dynamics='implicit'"):
        scene_mpc(env, bare, scene_mpc_settings(env, solver="rti", rti={"dynamics": "implicit"}))


def test_implicit_gap_agrees_with_the_exact_gap_to_second_order_off_the_nodes():
    """Off consistent nodes (the next node's orientation and rate both off) the gap is one Newton step
    on the step's equations: it matches the exact gap of the converged step up to O(ε²)."""
    config = ModelConfig(variant="sign-invariant", control_dim=3)
    terms = LearnedTerms(init_weights(config, seed=2), config, CA)
    node, layout = implicit_dynamics.node_terms_function(terms)
    stage = implicit_dynamics.implicit_stage_function(terms, layout, 0.05)
    reference, step = unrolled_stage(terms, 0.05, newton_iters=8)
    rng = np.random.default_rng(5)
    q = rng.normal(size=4)
    x, u, d = np.concatenate([q / np.linalg.norm(q), 3.0 * rng.normal(size=3)]), rng.normal(size=3), np.zeros(3)
    x_next = np.asarray(step(x, u)[0]).ravel()
    direction = rng.normal(size=6)
    errors = []
    for eps in (1e-2, 1e-3):
        x_next_bar = PIVOTED.retract(x_next[None], eps * direction[None])[0]
        gap = np.asarray(stage(x, u, x_next_bar, d, *node(x[:4]), *node(x_next_bar[:4]))[0])
        exact = np.asarray(reference(x, u, x_next_bar, d)[0])
        assert np.abs(exact).max() > 0.5 * eps  # the nodes are off by O(ε) …
        errors.append(np.abs(gap - exact).max())
    assert errors[1] < 3e-2 * errors[0]  # … and the gaps agree to O(ε²): ÷100 for ε ÷ 10


def test_plan_nodes_are_kept_on_one_sheet_for_the_implicit_dynamics(pendulum):
    """A measured state with the other quaternion sign than the plan: the nodes after it are flipped
    with it (the same rotations), so a stage never reads its two ends' terms on different sheets — the
    linearization is the unflipped plan's."""
    from fvin_mpc.control.mpc import Plan

    env, model = pendulum
    controller = scene_mpc(env, model, scene_mpc_settings(env, solver="rti", rti={"dynamics": "implicit"}))
    x0, _ = env.reset(options={"qpos": np.array([2.0]), "qvel": np.array([1.0])})
    controller(x0)
    plan = controller.plan
    states = plan.states.copy()
    states[0, :4] *= -1.0  # the measurement arrives on the other sheet
    flipped = Plan(states, plan.controls.copy(), None, None)
    for kept, on_one_sheet in zip(controller.linearize(flipped), controller.linearize(plan)):
        np.testing.assert_allclose(kept, on_one_sheet, rtol=1e-9, atol=1e-9)
