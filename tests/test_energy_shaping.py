"""Energy shaping + LQR catch on the closed-form pendulum, and scale invariance."""

import numpy as np
import pytest
import scipy.linalg
from helpers import hinge

from fvin_mpc.control.energy_shaping import EnergyShapingController
from fvin_mpc.core import fvin, s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.rigid_body import PENDULUM, PivotedRigidBody

NP = get_ops("numpy")
GOAL = np.array([0.0, 0.0, 1.0, 0.0])
REST = np.array([1.0, 0.0, 0.0, 0.0])  # hanging


def simulate(controller, terms, q, omega, periods, substeps=10, h=0.05):
    """Closed loop with the true model integrated at h/substeps (a finer plant than the model)."""
    log = []
    for _ in range(periods):
        u, info = controller(np.r_[q, omega])
        log.append((info["mode"], info["energy"], info["angle_from_goal"], u.copy()))
        for _ in range(substeps):
            out = fvin.fvin_step(tuple(q), tuple(omega), tuple(u), terms, h / substeps, 4, NP)
            q, omega = np.array(out.q, float), np.array(out.omega, float)
    return q, omega, log


def make(body=PENDULUM):
    return EnergyShapingController(body.terms(NP), 0.05, 3, GOAL, np.array([-2.0]), np.array([2.0]), REST)


def test_swings_up_from_exact_rest_and_holds_upright():
    controller = make()
    q, omega, log = simulate(controller, PENDULUM.terms(NP), np.array([1.0, 0, 0, 0]), np.zeros(3), 200)
    assert max(abs(entry[3][0]) for entry in log) <= 2.0
    assert float(s3.geodesic_angle(tuple(GOAL), tuple(q), NP)) < 1e-3
    assert all(entry[2] < 0.05 for entry in log[-40:])  # the last 2 s stay upright


def test_energy_rises_monotonically_while_pumping():
    controller = make()
    _, _, log = simulate(controller, PENDULUM.terms(NP), np.array([1.0, 0, 0, 0]), np.zeros(3), 60)
    energies = [energy for mode, energy, *_ in log if mode in ("kick", "pump")]
    first_at_goal = next(i for i, e in enumerate(energies) if e >= 0.99 * controller.goal_energy)
    pumping = energies[: first_at_goal + 1]  # the rise from rest up to the upright energy
    assert len(pumping) > 20
    # Between control updates energy follows the applied power; sampled per period it may dip
    # only by integrator-level noise while E < E*.
    drops = np.diff(pumping)
    assert drops.min() > -1e-2 * controller.energy_scale, drops.min()


def test_scale_of_the_model_cancels():
    """(J, U, g) → λ(J, U, g) is the same dynamics; the controller must act identically."""
    lam = 3.7
    scaled = PivotedRigidBody(
        inertia=tuple(tuple(lam * x for x in row) for row in PENDULUM.inertia),
        center_of_mass=PENDULUM.center_of_mass, mass_gravity=lam * PENDULUM.mass_gravity,
        actuator_axes=tuple(tuple(lam * x for x in row) for row in PENDULUM.actuator_axes),
    )
    # The actuator gain λ·b means one unit of u is λ times the torque; compare with u scaled back.
    a, b = make(), make(scaled)
    for q, omega in [
        (np.array([0.9, 0, 0.43589, 0]), np.array([0, 1.2, 0])),
        (np.array([0.1, 0, 0.99499, 0]), np.array([0, -0.3, 0])),
    ]:
        ua, _ = a(np.r_[q / np.linalg.norm(q), omega])
        ub, _ = b(np.r_[q / np.linalg.norm(q), omega])
        np.testing.assert_allclose(ua, ub, rtol=1e-6, atol=1e-9)


def test_rejects_non_finite_state():
    with pytest.raises(ValueError):
        make()(np.array([np.nan, 0, 0, 1.0, 0, 0, 0]))


# ---------------------------------------------------------------------- LQR oracle
def test_lqr_catch_cost_on_the_linear_model_equals_the_riccati_value():
    """dm_control's lqr_test in spirit: closed-loop cost of u = −Kx on x⁺ = Ax + Bu is xᵀPx."""
    design = make().lqr
    closed = design.a - design.b @ design.k
    assert np.max(np.abs(np.linalg.eigvals(closed))) < 1.0  # stabilizing
    rng = np.random.default_rng(0)
    for _ in range(5):
        x0 = rng.normal(size=design.a.shape[0]) * 0.1
        x, cost = x0.copy(), 0.0
        for _ in range(5000):
            u = -design.k @ x
            cost += x @ design.q_cost @ x + u @ design.r_cost @ u
            x = closed @ x
        np.testing.assert_allclose(cost, x0 @ design.p @ x0, rtol=1e-9)


def test_lqr_linearization_matches_the_continuous_pendulum():
    """A, B of the model's step at upright agree with θ̈ = 15 φ + 3τ (φ = angle from upright) to O(h²)."""
    design = make().lqr
    h = 0.05
    continuous_a, continuous_b = np.array([[0.0, 1.0], [15.0, 0.0]]), np.array([[0.0], [3.0]])
    exact_a = scipy.linalg.expm(continuous_a * h)
    # The basis vector of the actuated axis may point along ±y; the reduced coordinates then flip sign together.
    sign = np.sign(design.b[1, 0])
    np.testing.assert_allclose(design.a, exact_a, atol=5 * h**3 * 15)
    np.testing.assert_allclose(
        sign * design.b[:, 0], (exact_a - np.eye(2)) @ np.linalg.solve(continuous_a, continuous_b)[:, 0], rtol=0.05
    )


def test_controller_applies_the_lqr_gain_near_upright_and_its_closed_loop_cost_approaches_xPx():
    """On the model's own (nonlinear) step near upright the catch is u = −Kx, and its cost → xᵀPx as x → 0."""
    controller = make()
    terms = PENDULUM.terms(NP)
    design = controller.lqr
    ratios = []
    for scale in (0.2, 0.05, 0.0125):
        q, omega = hinge(np.pi - scale, 0.5 * scale)
        controller.reset()
        x0 = controller.reduced_state(np.r_[q, omega])
        cost = 0.0
        for _ in range(400):
            x = controller.reduced_state(np.r_[q, omega])
            u, info = controller(np.r_[q, omega])
            assert info["mode"] == "lqr"
            np.testing.assert_allclose(u, np.clip(-design.k @ x, -2, 2), atol=1e-12)
            cost += x @ design.q_cost @ x + u @ design.r_cost @ u
            out = fvin.fvin_step(tuple(q), tuple(omega), tuple(u), terms, 0.05, 3, NP)
            q, omega = np.array(out.q, float), np.array(out.omega, float)
        ratios.append(cost / (x0 @ design.p @ x0))
    errors = np.abs(np.array(ratios) - 1.0)
    assert errors[-1] < 1e-2, ratios
    assert errors[2] < errors[1] < errors[0], ratios  # the linearization error shrinks with the deviation




# ---------------------------------------------------------------------- constructors and scenes
def test_constructors_agree_with_the_direct_one():
    from fvin_mpc.control import model_export as export

    direct = EnergyShapingController(PENDULUM.terms(NP), 0.05, 2, GOAL, np.array([-2.0]), np.array([2.0]), REST)
    via_model = EnergyShapingController.from_model(export.from_rigid_body(PENDULUM, 0.05, 2), GOAL, [-2.0], [2.0], REST)
    for x in [np.r_[hinge(0.3, 1.0)], np.r_[hinge(2.9, -0.4)], np.r_[hinge(np.pi - 0.1, 0.2)]]:
        np.testing.assert_allclose(via_model(x)[0], direct(x)[0], atol=1e-12)
    np.testing.assert_allclose(via_model.lqr.p, direct.lqr.p, rtol=1e-9)


def test_scene_energy_shaping_rejects_a_ball_joint_with_a_reason():
    from fvin_mpc.control.energy_shaping import EnergyShapingNotApplicable
    from fvin_mpc.control.scene import scene_energy_shaping, scene_env, scene_model

    env = scene_env("spherical_pendulum", true_model=True)
    with pytest.raises(EnergyShapingNotApplicable, match="hinge"):
        scene_energy_shaping(env, scene_model(env, true_model=True))


def test_true_model_swings_up_the_mujoco_pendulum_from_rest():
    from fvin_mpc.control.closed_loop import episode_metrics, run_episode
    from fvin_mpc.control.scene import scene_energy_shaping, scene_model
    from fvin_mpc.envs import RigidBodyEnv

    env = RigidBodyEnv("pendulum")
    controller = scene_energy_shaping(env, scene_model(env, true_model=True))
    metrics = episode_metrics(run_episode(env, controller, 8.0)[0])
    assert metrics["swung_up"], metrics
    assert metrics["max_abs_torque"] <= 2.0


def test_learned_model_swings_up_the_mujoco_pendulum_from_rest():
    """Energy shaping from the shipped learned J, U, g alone (its own E*, its own LQR) on MuJoCo."""
    from fvin_mpc.control.closed_loop import episode_metrics, run_episode
    from fvin_mpc.control.scene import scene_energy_shaping, scene_model
    from fvin_mpc.envs import RigidBodyEnv

    env = RigidBodyEnv("pendulum")
    controller = scene_energy_shaping(env, scene_model(env))  # the scene's shipped checkpoint; missing = failure
    episode, _ = run_episode(env, controller, 10.0)
    metrics = episode_metrics(episode)
    assert metrics["success"], metrics
    assert metrics["max_abs_torque"] <= 2.0
