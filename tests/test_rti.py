"""The real-time iteration MPC (``fvin_mpc.control.rti``): its S³ chart, convergence to the IPOPT
MPC's optimum on a fixed problem, the swing-up's first torque from exact rest, the safe fallback,
deterministic fixed-latency episodes and the offset-free estimator against a known torque (oracle).
Behaviour only: no timings are asserted."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from helpers import iterated_rti_plan, stage_models

from fvin_mpc.control.closed_loop import episode_metrics, run_episode
from fvin_mpc.control.mpc import MPC
from fvin_mpc.control.riccati_qp import riccati_feedback_function
from fvin_mpc.control.rti import RealTimeMPC
from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings
from fvin_mpc.envs.disturbance import ConstantTorqueDisturbance

#: Cold budgets this generous let the iteration caps, not the wall clock, decide: deterministic runs.
DETERMINISTIC = {"rti": {"cold_budget_s": 60.0}}


@pytest.fixture(scope="module")
def pendulum():
    env = scene_env("pendulum", true_model=True)
    return env, scene_model(env, true_model=True)


@pytest.fixture(scope="module")
def spherical():
    env = scene_env("spherical_pendulum", true_model=True)
    return env, scene_model(env, true_model=True)


def rti(env, model, **overrides):
    options = {**DETERMINISTIC["rti"], **overrides.pop("rti", {})}
    return scene_mpc(env, model, scene_mpc_settings(env, solver="rti", rti=options, **overrides))


def test_scene_mpc_dispatches_on_the_solver_setting(pendulum):
    env, model = pendulum
    assert isinstance(rti(env, model), RealTimeMPC)
    assert type(scene_mpc(env, model, scene_mpc_settings(env, cold_starts=("rollout+",)))) is MPC


@pytest.mark.parametrize("scene, dynamics", [("spherical", "unrolled"), ("pendulum", "implicit")])
def test_iterations_reach_the_ipopt_optimum_on_a_fixed_problem(scene, dynamics, request):
    """From rest, the same first guess: IPOPT solved to convergence, and RTI iterations with the
    measured state fixed. The Gauss–Newton SQP converges to the same plan's cost — with the implicit
    dynamics too, whose converged step differs from IPOPT's K = 2 one by the Newton error only."""
    env, model = request.getfixturevalue(scene)
    settings = scene_mpc_settings(env, cold_starts=("goal",), solver="rti", terminal_energy_weight=0.0,
                                  rti={**DETERMINISTIC["rti"], "dynamics": dynamics})
    # the same problem: the scene's RTI settings may change its horizon and weights (the ω weight)
    reference = scene_mpc(env, model, scene_mpc_settings(env, cold_starts=("goal",), terminal_energy_weight=0.0,
                                                         omega_weight=settings.omega_weight, horizon=settings.horizon))
    x0, _ = env.reset()
    _, info = reference(x0)
    assert info["success"]
    controller = scene_mpc(env, model, settings)
    plan, cost, gap = iterated_rti_plan(controller, x0, 20)
    assert gap < 1e-6
    assert abs(cost - info["cost"]) <= 1e-3 * info["cost"]
    # the problem is mirror-symmetric about the hanging state: the same optimum may swing either way
    np.testing.assert_allclose(np.abs(plan.controls[0]), np.abs(info["controls"][0]), atol=1e-2)


@pytest.mark.parametrize("scene", ["pendulum", "spherical"])
def test_first_torque_from_exact_rest_is_nonzero(scene, request):
    env, model = request.getfixturevalue(scene)
    controller = rti(env, model)
    x0, _ = env.reset()  # hanging exactly at rest: a stationary point of the swing-up problem
    u, info = controller(x0)
    assert info["success"] and info["iterations"] >= 1
    assert np.max(np.abs(u)) > 0.1 * np.max(env.unwrapped.torque_high)


def test_fixed_latency_swing_up_is_deterministic(pendulum):
    env, model = pendulum
    controller = rti(env, model)
    first, _ = run_episode(env, controller, 8.0, latency=0.01)
    second, _ = run_episode(env, controller, 8.0, latency=0.01)
    np.testing.assert_array_equal(first.u, second.u)
    np.testing.assert_array_equal(first.q, second.q)
    metrics = episode_metrics(first)
    assert metrics["success"] and metrics["hold_error_rad"] < 1e-3
    assert metrics["deadline_misses"] == 0 and metrics["controller_failures"] == 0


@pytest.mark.parametrize("scene, torque", [("pendulum", [0.3]), ("spherical", [0.2, -0.15, 0.1])])
def test_disturbance_estimate_converges_to_the_oracle_torque(scene, torque, request):
    """A known constant torque on the plant (closed-form model, fixed latency): the estimate
    converges to it and the goal is held with no steady error; without the estimator it is not."""
    env, model = request.getfixturevalue(scene)
    near_goal = ({"qpos": np.array([np.pi - 0.3]), "qvel": np.array([0.0])} if scene == "pendulum"
                 else {"qpos": np.array([0.0, 0.8, 0.6, 0.0]), "qvel": np.zeros(3)})
    disturbed = ConstantTorqueDisturbance(env, torque)
    horizon = 20 if scene == "pendulum" else None
    episode, _ = run_episode(disturbed, rti(env, model, horizon=horizon), 4.0, near_goal, latency=0.01)
    estimate = episode.controller_info[-1]["disturbance"]
    np.testing.assert_allclose(estimate, torque, atol=2e-3)
    offset_free = episode.angle_from_goal[-20:].max()
    plain, _ = run_episode(disturbed, rti(env, model, horizon=horizon, disturbance_gain=0.0), 4.0, near_goal,
                           latency=0.01)
    assert offset_free < 2e-3 < plain.angle_from_goal[-20:].max()


@pytest.mark.parametrize("qp_iterations", [10, 40])
def test_many_qp_iterations_stay_finite_and_hold_the_goal(pendulum, qp_iterations):
    """Hard case: without a floor on the barrier parameter, 20 interior-point iterations drove it to
    where λ/s swamps the Riccati recursion: μ turned NaN on the cold call and near-upright starts were
    lost. With the floor, more iterations only re-solve the same barrier problem."""
    env, model = pendulum
    controller = rti(env, model, rti={"qp_iterations": qp_iterations})
    start = {"qpos": np.array([np.pi - 0.5]), "qvel": np.array([0.0])}  # 0.5 rad from upright
    episode, _ = run_episode(env, controller, 3.0, start, latency="none")
    assert np.isfinite(controller.qp_mu) and controller.qp_mu >= 1e-10
    assert np.all(np.isfinite(controller.plan.states)) and np.all(np.isfinite(controller.plan.controls))
    assert episode_metrics(episode)["success"]
    assert episode.angle_from_goal[-1] < 0.01


@pytest.mark.parametrize("nd, m", [(6, 1), (6, 3), (12, 4), (12, 8)])
def test_riccati_stage_matches_the_matrix_formulas(nd, m):
    """The entry-wise Riccati stage (symmetric reads, one UᵀDU factorization) against the textbook
    matrix recursion in NumPy: gains, feedforwards and the cost-to-go, and ``P⁻`` symmetric."""
    from fvin_mpc.control.riccati_qp import riccati_stage_function

    rng = np.random.default_rng(nd * 10 + m)
    size = nd + m
    root = rng.standard_normal((nd, nd))
    P = root @ root.T
    jacobian = rng.standard_normal((size + 2, size))
    H = 2.0 * jacobian.T @ jacobian + 1e-6 * np.eye(size)
    p, g, c = rng.standard_normal(nd), rng.standard_normal(size), rng.standard_normal(nd)
    AB, d, r = rng.standard_normal((nd, size)), rng.random(m), rng.standard_normal(m)
    A, B = AB[:, :nd], AB[:, nd:]
    gram = H[nd:, nd:] + np.diag(d) + B.T @ P @ B
    cross = H[nd:, :nd] + B.T @ P @ A
    r_tilde = r + B.T @ (P @ c + p)
    K, k = -np.linalg.solve(gram, cross), -np.linalg.solve(gram, r_tilde)
    P_prev = H[:nd, :nd] + A.T @ P @ A + cross.T @ K
    p_prev = g[:nd] + A.T @ (P @ c + p) + cross.T @ k
    # the lower triangle of P must not be read: spoil it
    P_upper = np.triu(P) + np.tril(np.full((nd, nd), np.nan), -1)
    out = [np.asarray(o, dtype=float) for o in riccati_stage_function(nd, m)(P_upper, p, H, g, AB, c, d, r)]
    scale = max(1.0, np.abs(P_prev).max())
    np.testing.assert_allclose(out[0], P_prev, atol=1e-12 * scale)
    np.testing.assert_array_equal(out[0], out[0].T)
    np.testing.assert_allclose(out[1].ravel(), p_prev, atol=1e-12 * scale)
    np.testing.assert_allclose(out[2], K, atol=1e-12 * max(1.0, np.abs(K).max()))
    np.testing.assert_allclose(out[3].ravel(), k, atol=1e-12 * max(1.0, np.abs(k).max()))
    # its matrix and vector halves (Mehrotra's iteration: one factorization, two solves) give the same bits
    from fvin_mpc.control.riccati_qp import riccati_factor_function, riccati_solve_function

    P_half, K_half, factors, crosses = riccati_factor_function(nd, m)(P_upper, H, AB, d)
    p_half, k_half = riccati_solve_function(nd, m)(p, P_upper, factors, crosses, g, AB, c, r)
    for half, whole in zip((P_half, p_half, K_half, k_half), out):
        np.testing.assert_array_equal(np.asarray(half, dtype=float).reshape(whole.shape), whole)


def test_the_generated_qp_reaches_an_active_set_solvers_solution(pendulum):
    """The interior-point QP generated with the Riccati recursion against an independent solver: every QP of a
    swing-up, written out whole (``benchmarks.qp_accuracy.exact_controls``) and solved by qpOASES. With enough
    iterations the first control is the exact one; the default count leaves a few hard QPs short
    (``python -m benchmarks.qp_accuracy`` measures how many, docs/realtime.md)."""
    from benchmarks.qp_accuracy import exact_controls, exact_solver, record_qps

    env, model = pendulum
    controller = rti(env, model)
    records = record_qps(env, controller, 3.0, {"qpos": np.array([0.3]), "qvel": np.array([0.0])})
    n, m, active_set = controller.horizon, model.control_dim, exact_solver(controller)
    many = riccati_feedback_function(controller.layout, n, m, *controller._control_bounds, controller._step_limits,
                                     controller._omega_valid, 40)[0]
    span = float(np.max(controller._control_bounds[1] - controller._control_bounds[0]))
    distances = {"default": [], "40": []}
    feedback = controller.loop_function("rti_feedback")
    for arguments in records:
        exact = exact_controls(controller, arguments, active_set)[:, 0]
        distances["default"].append(np.max(np.abs(feedback(*arguments)[1][:, 0] - exact)) / span)
        distances["40"].append(np.max(np.abs(np.array(many(*arguments)[1])[:, 0] - exact)) / span)
    assert len(records) > 40
    assert np.median(distances["40"]) < 1e-9 and np.mean(np.array(distances["40"]) < 1e-6) >= 0.9
    assert np.median(distances["default"]) < 1e-8
    # Mehrotra's predictor–corrector (rti.qp_method) reaches the same solutions
    mehrotra = riccati_feedback_function(controller.layout, n, m, *controller._control_bounds,
                                         controller._step_limits, controller._omega_valid, 30, method="mehrotra")[0]
    corrected = [np.max(np.abs(np.array(mehrotra(*arguments)[1])[:, 0] - exact_controls(controller, arguments,
                                                                                          active_set)[:, 0])) / span
                 for arguments in records]
    assert np.median(corrected) < 1e-9 and np.mean(np.array(corrected) < 1e-6) >= 0.9
    with pytest.raises(ValueError, match="unknown interior-point method"):
        riccati_feedback_function(controller.layout, n, m, *controller._control_bounds, controller._step_limits,
                                  controller._omega_valid, 3, method="newton")


def test_first_order_terms_give_a_stage_the_same_derivatives_with_fewer_operations():
    """``unrolled_stage_function(…, model=)`` differentiates the step on its terms' first-order expansions
    (:mod:`fvin_mpc.control.term_expansion`): against the step differentiated as written, at random nodes of
    every built-in scene's learned and closed-form model, with and without the model parameters as an input, and
    with quaternions on and off unit norm, the gap is the same to the bit and ``[A B]`` the same to rounding; a
    learned stage has fewer instructions."""
    from fvin_mpc.control.linearization import unrolled_stage_function

    rng = np.random.default_rng(11)
    for scene, true_model, model in stage_models():
        layout, m = model.space.layout, model.control_dim
        for parametric in (False, True):
            step = model.parametric_step if parametric else model.step
            as_written = unrolled_stage_function(step, layout, m)
            expanded = unrolled_stage_function(step, layout, m, model=model)
            if not true_model:
                assert expanded.n_instructions() < 0.96 * as_written.n_instructions(), scene
            for trial in range(4):
                states = []
                for _ in range(2):
                    x = 0.7 * rng.standard_normal(layout.state_dim)
                    quaternion = layout.attitude("test").quaternion
                    x[quaternion] = rng.standard_normal(4)
                    # unit, or off it by 1e-3 (a measured state the C loop still takes)
                    x[quaternion] *= (1.0 + 1e-3 * (trial % 2)) / np.linalg.norm(x[quaternion])
                    states.append(x)
                inputs = [states[0], rng.uniform(-0.5, 0.5, m), states[1], rng.uniform(-0.1, 0.1, m)]
                if parametric:
                    inputs.append(model.model_parameters.defaults)
                (gap, jacobian), (gap_expanded, jacobian_expanded) = as_written.call(inputs), expanded.call(inputs)
                np.testing.assert_array_equal(np.asarray(gap), np.asarray(gap_expanded))
                jacobian, jacobian_expanded = np.asarray(jacobian), np.asarray(jacobian_expanded)
                assert np.all(np.isfinite(jacobian))
                scale = np.abs(jacobian).max()
                np.testing.assert_allclose(jacobian_expanded, jacobian, rtol=0, atol=1e-11 * scale,
                                           err_msg=f"{scene} {'true' if true_model else 'learned'}")


def test_first_order_terms_are_exact_to_first_order_and_pass_the_rest_through(monkeypatch):
    """:class:`~fvin_mpc.control.term_expansion.FirstOrderTerms` on toy terms: the value and the slope at the
    point are the term's own and the second-order part is dropped, for a plain argument and for a unit quaternion
    ``q`` moving on the sphere (expanded along its tangent); calls that do not depend on the perturbation,
    attributes, constants and terms cheaper than :data:`MIN_INSTRUCTIONS` are the wrapped object's."""
    from fvin_mpc.control import term_expansion
    from fvin_mpc.control.term_expansion import FirstOrderTerms

    class Toy:
        control_dim = 2

        def square(self, a):
            return (a[0] * a[0], (a[0] * a[1], 3.0), None)

        def rotated(self, q):
            return (q[0] * q[1] + q[2] * q[3] * q[3],)

        def constant(self):
            return ((1.0, 2.0),)

    e, a = ca.SX.sym("e"), ca.SX.sym("a")
    wrapped = FirstOrderTerms(Toy(), [e])
    (cheap, _, _) = wrapped.square((a + e, a - e))
    assert ca.is_equal(cheap, (a + e) * (a + e), 2)  # a few instructions: differentiated as written
    monkeypatch.setattr(term_expansion, "MIN_INSTRUCTIONS", 0)
    assert wrapped.control_dim == 2 and wrapped.constant() == ((1.0, 2.0),)
    (square, (product, three), nothing) = wrapped.square((a + e, a - e))
    assert three == 3.0 and nothing is None
    f = ca.Function("f", [a, e], [square, product])
    # (a + e)² → a² + 2a e; (a + e)(a − e) → a² (its slope in e is 0)
    for a_value, e_value in ((0.3, 0.0), (0.3, 0.5), (-1.2, 2.0)):
        s, p = (float(v) for v in f(a_value, e_value))
        assert s == pytest.approx(a_value ** 2 + 2 * a_value * e_value, abs=1e-15)
        assert p == pytest.approx(a_value ** 2, abs=1e-15)
    (untouched, _, _) = wrapped.square((a, a))
    assert ca.is_equal(untouched, a * a, 2)
    # a unit quaternion turning about an axis through a: q(e) = q̄ ⊗ exp(e·axis/2)
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    q_bar = np.array([0.5, 0.1, -0.7, 0.3]) / np.linalg.norm([0.5, 0.1, -0.7, 0.3])
    from fvin_mpc.core import s3
    turn = (ca.cos(e / 2), *(ca.sin(e / 2) * float(component) for component in axis))
    q = s3.multiply(tuple(q_bar), turn)
    exact, = Toy().rotated(q)
    expanded, = wrapped.rotated(q)
    derivatives = ca.Function("d", [e], [exact, expanded, ca.jacobian(exact, e), ca.jacobian(expanded, e)])
    value, value_expanded, slope, slope_expanded = (float(v) for v in derivatives(0.0))
    assert value_expanded == pytest.approx(value, abs=1e-15) and slope_expanded == pytest.approx(slope, abs=1e-14)


def test_common_subexpression_elimination_changes_no_bit_of_a_learned_stage(monkeypatch):
    """The generated stage functions are built with CSE (``GENERATED_SX_OPTIONS``): fewer operations, and
    outputs identical to the bit to the same function built without it, at random nodes of a learned ball joint
    (unrolled step) and of the learned planar pendulum's node terms (implicit dynamics)."""
    from fvin_mpc.control import implicit_dynamics
    from fvin_mpc.control.linearization import unrolled_stage_function
    from fvin_mpc.control.model_export import GENERATED_SX_OPTIONS

    def built(cse, scene):
        monkeypatch.setitem(GENERATED_SX_OPTIONS, "cse", cse)
        model = scene_model(scene_env(scene), true_model=False)
        if scene == "pendulum":
            return implicit_dynamics.node_terms_function(model.casadi_terms, None)[0]
        return unrolled_stage_function(model.step, model.space.layout, model.control_dim)

    rng = np.random.default_rng(7)
    for scene in ("spherical_pendulum", "pendulum"):
        plain, eliminated = built(False, scene), built(True, scene)
        assert eliminated.n_instructions() < plain.n_instructions()
        for _ in range(5):
            inputs = []
            for index in range(plain.n_in()):
                value = rng.standard_normal(plain.size_in(index))
                if plain.name_in(index) in ("x_bar", "x_next_bar", "q_bar"):
                    value[:4] /= np.linalg.norm(value[:4])
                inputs.append(value)
            for a, b in zip(plain.call(inputs), eliminated.call(inputs)):
                assert np.all(np.isfinite(np.asarray(a)))
                np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize(("items", "every", "head"), [(20, 1, 4), (21, 4, 4), (50, 4, 0), (30, 5, 3), (7, 10, 2)])
def test_kept_jacobians_are_never_older_than_the_rule_says(items, every, head):
    """:func:`relinearized` as the shift moves the items: following each node through 3·items periods, its
    Jacobians are renewed at least every ``every`` periods, the first ``head`` items every period, and each
    linearization renews the same number of items."""
    from fvin_mpc.control.linearization import relinearized

    renewed = relinearized(items, every, head).astype(bool)
    assert renewed[:head].all() and renewed[-1] and renewed[0]
    age = np.zeros(items, dtype=int)
    oldest = 0
    for _ in range(3 * items):
        age = np.concatenate([age[1:] + 1, [0]])  # the shift: a new item at the end
        age[renewed] = 0
        oldest = max(oldest, int(age.max()))
    assert oldest <= every - 1
    if every == 1:
        assert renewed.all()


@pytest.mark.parametrize("every", [1, 3])
def test_only_kept_jacobians_let_a_periods_further_iterations_keep_any(spherical, every):
    """The default (``relinearize_every=1``) renews every item in every linearization, the further iterations of a
    period included; with kept Jacobians those renew only the items that moved (none by the rule)."""
    controller = rti(*spherical, rti={"relinearize_every": every})
    items, _, _, preparation, further = controller.kept_jacobians
    assert controller.settings.rti.max_iter == 3
    if every == 1:
        assert preparation.all() and further.all()
    else:
        assert 0 < preparation.sum() < items and not further.any()


@pytest.mark.parametrize("scene", ["spherical_pendulum", "pendulum"])
def test_a_linearization_renews_the_jacobians_it_is_told_to_and_keeps_the_rest(scene):
    """The generated linearization with kept Jacobians (``rti.relinearize_every``): renewed items are the full
    linearization's to the bit, kept ones the given ones to the bit, with the points they were computed at; an item
    renews where its node moved more than ``rti.relinearize_tol`` from its kept point, and only there; on the
    unrolled stages (learned ball joint) the gaps, Hessians and gradients do not depend on which were kept (to
    rounding); the
    implicit dynamics' node slopes (learned pendulum) are kept the same way."""
    env = scene_env(scene)
    controller = rti(env, scene_model(env, true_model=False), rti={"relinearize_every": 3})
    controller(env.reset(seed=1, options={"random": True})[0])
    plan = controller.plan
    full = controller.linearize(plan)
    full_jacobians, here = controller.last_jacobians
    items, size, point_size, rule, _ = controller.kept_jacobians
    assert 1 < rule.sum() < items and here.shape == (point_size, items)
    given = np.random.default_rng(3).standard_normal(full_jacobians.shape)
    # every point where its item is now, but the item after each one the rule keeps moved by 1.5 tolerances
    points = here.copy()
    moved = np.zeros(items, dtype=bool)
    moved[np.flatnonzero(rule == 0)[::2]] = True
    shift = 1.5 * controller.settings.rti.relinearize_tol * (controller.torque_high - controller.torque_low)
    if scene == "spherical_pendulum":
        points[-len(shift):, moved] += shift[:, None]  # the stage's control
    else:  # the node's rotation: a chart step (tan of half the angle) of 1.5 tolerances of STEP_LIMIT_ANGLE
        from fvin_mpc.control.linearization import STEP_LIMIT_ANGLE
        from fvin_mpc.core import s3

        half = np.arctan(1.5 * controller.settings.rti.relinearize_tol * STEP_LIMIT_ANGLE)
        for item in np.flatnonzero(moved):
            points[:, item] = s3.multiply(tuple(here[:, item]), (np.cos(half), np.sin(half), 0.0, 0.0))
    kept = controller.linearize(plan, (given, points), renewed=rule)
    jacobians, new_points = controller.last_jacobians
    renewed = (rule > 0) | moved
    assert moved.any() and not renewed.all()
    width = full_jacobians.shape[1] // items
    for item in range(items):
        columns = slice(item * width, (item + 1) * width)
        expected = full_jacobians if renewed[item] else given
        np.testing.assert_array_equal(jacobians[:, columns], expected[:, columns])
        np.testing.assert_array_equal(new_points[:, item], (here if renewed[item] else points)[:, item])
    assert jacobians.size == items * size
    if scene == "spherical_pendulum":  # unrolled: the stages' [A B] are the kept Jacobians
        np.testing.assert_array_equal(kept[4], jacobians)
        # A kept stage's values come from the value-only branch, a renewed one's from the branch with the
        # derivatives: the same expressions, but compiled for this CPU (fused multiply–adds) the two round apart.
        for index in (0, 1, 2, 3, 5, 6):  # H, H_N, g, g_N, gaps, cost
            np.testing.assert_allclose(kept[index], full[index], rtol=1e-12, atol=1e-14)
