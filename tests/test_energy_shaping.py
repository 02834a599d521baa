"""Energy shaping + LQR catch on the closed-form pendulum, and scale invariance."""

import numpy as np
import pytest

from fvin_mpc import fvin, s3
from fvin_mpc.backend import get_ops
from fvin_mpc.energy_shaping import EnergyShapingController
from fvin_mpc.rigid_body import PENDULUM, PivotedRigidBody

NP = get_ops("numpy")
GOAL = np.array([0.0, 0.0, 1.0, 0.0])


def simulate(controller, terms, q, omega, periods, substeps=10, h=0.05):
    """Closed loop with the true model integrated at h/substeps (a finer plant than the model)."""
    log = []
    for _ in range(periods):
        u, info = controller(q, omega)
        log.append((info["mode"], info["energy"], info["angle_from_goal"], u.copy()))
        for _ in range(substeps):
            out = fvin.fvin_step(tuple(q), tuple(omega), tuple(u), terms, h / substeps, 4, NP)
            q, omega = np.array(out.q, float), np.array(out.omega, float)
    return q, omega, log


def make(body=PENDULUM):
    return EnergyShapingController(body.terms(NP), 0.05, 3, GOAL, np.array([-2.0]), np.array([2.0]))


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
    for q, omega in [(np.array([0.9, 0, 0.43589, 0]), np.array([0, 1.2, 0])), (np.array([0.1, 0, 0.99499, 0]), np.array([0, -0.3, 0]))]:
        ua, _ = a(q / np.linalg.norm(q), omega)
        ub, _ = b(q / np.linalg.norm(q), omega)
        np.testing.assert_allclose(ua, ub, rtol=1e-6, atol=1e-9)


def test_rejects_non_finite_state():
    with pytest.raises(ValueError):
        make()(np.array([np.nan, 0, 0, 1.0]), np.zeros(3))
