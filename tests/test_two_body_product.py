"""A coupled two-body product, S³ × S³ (``tests/two_tops.py``: two tops joined by a torsion spring, its step
written in the test), runs through every layer with no package edit: the blocks' chart and check on NumPy,
torch and CasADi, the export and a rollout, a learned model saved and loaded, IPOPT, the real-time iteration
and the generated C loop (equal to the Python loop to 1e-9).
"""

from __future__ import annotations

import dataclasses
import shutil

import casadi as ca
import numpy as np
import pytest
import torch
from two_tops import TWO_TOPS, TwoTops, TwoTopsConfig

from fvin_mpc.control import model_export as export
from fvin_mpc.control.mpc import MPC, MPCSettings, RTIOptions
from fvin_mpc.control.rti import RealTimeMPC
from fvin_mpc.core import fvin
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.checkpoint import load_checkpoint, save_checkpoint
from fvin_mpc.core.goals import GoalSet
from fvin_mpc.core.rigid_body import PivotedRigidBody
from fvin_mpc.core.space import register, spaces, unregister

NP, TORCH, CA = get_ops("numpy"), get_ops("torch"), get_ops("casadi")
LAYOUT = TWO_TOPS.layout
#: Both tops held at given attitudes, at rest: a goal set a user makes (a whole state, no energy term).
POSES = GoalSet("poses", "both tops at their attitudes, at rest", attitude_at_rest=False)

#: Three motors on each top (fully actuated: any attitude can be held against gravity and the spring).
EYE = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
TOP_A = PivotedRigidBody(inertia=((0.9, 0.1, -0.2), (0.1, 0.6, 0.05), (-0.2, 0.05, 0.4)),
                         center_of_mass=(0.1, -0.2, -0.5), mass_gravity=3.0, actuator_axes=EYE,
                         damping=0.2)
TOP_B = PivotedRigidBody(inertia=((0.5, 0.0, 0.1), (0.0, 0.7, 0.0), (0.1, 0.0, 0.6)),
                         center_of_mass=(0.0, 0.1, -0.4), mass_gravity=2.0, actuator_axes=EYE,
                         damping=0.2)
BODY = TwoTops(TOP_A, TOP_B, stiffness=1.5)
H = 0.05


@pytest.fixture
def two_tops():
    """The product space, registered for one test and taken out again (xdist may run others in between)."""
    before = spaces()
    register(TWO_TOPS)
    yield TWO_TOPS
    unregister(TWO_TOPS.name)
    assert spaces() == before


def states(n: int, seed: int, speed: float = 1.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = np.empty((n, LAYOUT.state_dim))
    for quaternion in LAYOUT.quaternions:
        q = rng.normal(size=(n, 4))
        x[:, quaternion] = q / np.linalg.norm(q, axis=1, keepdims=True)
    x[:, LAYOUT.rates] = speed * rng.normal(size=(n, LAYOUT.state_dim - LAYOUT.rates.start))
    return x


def test_the_product_of_two_balls_is_told_by_its_blocks():
    assert (LAYOUT.state_dim, LAYOUT.tangent_dim) == (14, 12)
    assert LAYOUT.quaternions == (slice(0, 4), slice(4, 8)) and LAYOUT.rates == slice(8, 14)
    assert LAYOUT.angular_rates == slice(8, 14) and LAYOUT.tangent_units == ("angle",) * 6 + ("angular rate",) * 6
    with pytest.raises(ValueError, match="one body's attitude.*has 2"):
        LAYOUT.attitude(by="a single-body controller")


@pytest.mark.parametrize("backend", ["numpy", "torch", "casadi"])
def test_retract_and_local_are_inverse_sign_free_and_the_same_on_every_backend(backend):
    x_bar, y = states(6, seed=1), states(6, seed=2)
    delta = 0.4 * np.random.default_rng(3).normal(size=(6, LAYOUT.tangent_dim))
    x = LAYOUT.retract(x_bar, delta)
    np.testing.assert_allclose(LAYOUT.local(x_bar, x), delta, rtol=0, atol=1e-12)
    flipped = y.copy()
    flipped[:, LAYOUT.quaternions[1]] *= -1.0  # the second top's other sign: the same state
    np.testing.assert_allclose(LAYOUT.local(x_bar, flipped), LAYOUT.local(x_bar, y), rtol=0, atol=1e-12)
    ops = get_ops(backend)
    for i in range(len(x_bar)):
        if backend == "torch":
            there = LAYOUT.retract(torch.as_tensor(x_bar[i]), torch.as_tensor(delta[i]), ops).numpy()
            back = LAYOUT.local(torch.as_tensor(x_bar[i]), torch.as_tensor(y[i]), ops).numpy()
        elif backend == "casadi":
            there = np.asarray(ca.evalf(LAYOUT.retract(ca.DM(x_bar[i]), ca.DM(delta[i]), ops))).ravel()
            back = np.asarray(ca.evalf(LAYOUT.local(ca.DM(x_bar[i]), ca.DM(y[i]), ops))).ravel()
        else:
            there, back = LAYOUT.retract(x_bar[i], delta[i], ops), LAYOUT.local(x_bar[i], y[i], ops)
        np.testing.assert_allclose(there, x[i], rtol=0, atol=1e-14)
        np.testing.assert_allclose(back, LAYOUT.local(x_bar, y)[i], rtol=0, atol=1e-14)


def test_the_check_and_the_distance_read_every_block():
    x = states(1, seed=4)[0]
    slightly = x.copy()
    slightly[LAYOUT.quaternions[1]] *= 1.0 + 5e-4
    np.testing.assert_allclose(np.linalg.norm(LAYOUT.check(slightly)[LAYOUT.quaternions[1]]), 1.0, atol=1e-15)
    wrong = x.copy()
    wrong[LAYOUT.quaternions[1]] *= 1.1
    with pytest.raises(ValueError, match="q of b is not a unit quaternion"):
        LAYOUT.check(wrong)
    goal = states(1, seed=5)[0]
    halves = [1.0 - float(x[q] @ goal[q]) ** 2 for q in LAYOUT.quaternions]
    assert LAYOUT.distance(x, goal) == pytest.approx(sum(halves), abs=1e-14)
    other_sign = goal.copy()
    other_sign[LAYOUT.quaternions[0]] *= -1.0
    assert LAYOUT.distance(x, other_sign) == pytest.approx(LAYOUT.distance(x, goal), abs=1e-14)


def test_the_step_couples_the_tops_and_without_the_spring_is_two_s3_steps(two_tops):
    x, u = states(5, seed=6), 0.3 * np.random.default_rng(6).normal(size=(5, 6))
    loose = TwoTops(TOP_A, TOP_B, stiffness=0.0)
    stepped, _ = two_tops.step(x, u, loose.terms(NP), H, 3, NP)
    for top, body, inputs in ((0, TOP_A, u[:, :3]), (1, TOP_B, u[:, 3:])):
        q, omega = LAYOUT.slots[top].position, LAYOUT.slots[top].rate
        alone = fvin.fvin_step(tuple(x[:, q].T), tuple(x[:, omega].T), tuple(inputs.T), body.terms(NP), H, 3, NP)
        np.testing.assert_allclose(stepped[:, q], np.array(alone.q).T, rtol=0, atol=1e-12)
        np.testing.assert_allclose(stepped[:, omega], np.array(alone.omega).T, rtol=0, atol=1e-12)
    # without gravity and at rest nothing moves; with the spring, pushing top a alone moves top b
    weightless = TwoTops(dataclasses.replace(TOP_A, mass_gravity=0.0), dataclasses.replace(TOP_B, mass_gravity=0.0),
                         stiffness=BODY.stiffness)
    still = np.tile(np.r_[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, np.zeros(6)], (1, 1))
    pushed = still.copy()
    for _ in range(10):
        still = two_tops.step(still, np.zeros((1, 6)), weightless.terms(NP), H, 3, NP)[0]
        pushed = two_tops.step(pushed, np.array([[2.0, 0.0, 0.0, 0.0, 0.0, 0.0]]), weightless.terms(NP), H, 3, NP)[0]
    b_rate = LAYOUT.slots[1].rate
    assert np.abs(still[0, b_rate]).max() < 1e-12 and np.abs(pushed[0, b_rate]).max() > 1e-3


def test_the_product_exports_rolls_out_on_torch_and_saves_and_loads(two_tops, tmp_path):
    model = export.from_terms(two_tops, BODY.terms(CA), BODY.terms(NP), H, 3, "two-tops")
    assert model.state_dim == 14 and model.control_dim == 6
    x0, controls = states(1, seed=7)[0], 0.5 * np.random.default_rng(7).normal(size=(20, 6))
    rollout, x = model.rollout(x0, controls), x0
    for k, u in enumerate(controls):
        x = two_tops.step(x, u, BODY.terms(NP), H, 3, NP)[0]
        np.testing.assert_allclose(rollout[k + 1], x, rtol=0, atol=1e-12)
    assert model.energy(x0) == pytest.approx(float(two_tops.energy(x0, BODY.terms(NP), NP)), abs=1e-12)
    # a learned model: the same step on torch and NumPy, and through a checkpoint
    config = TwoTopsConfig(control_dim=6, step_size=H)
    weights = two_tops.init_weights(config, seed=3)
    stem = save_checkpoint(tmp_path / "two-tops", config, weights, scene="synthetic")
    checkpoint = load_checkpoint(stem)
    assert checkpoint.space is two_tops and checkpoint.config == config
    loaded = export.from_checkpoint(checkpoint)
    xs, us = states(4, seed=8), 0.2 * np.random.default_rng(8).normal(size=(4, 6))
    on_numpy = two_tops.step(xs, us, two_tops.learned_terms(weights, config, NP), H, config.newton_iters, NP)[0]
    torch_weights = {name: torch.as_tensor(value) for name, value in weights.items()}
    on_torch = two_tops.step(torch.as_tensor(xs), torch.as_tensor(us),
                             two_tops.learned_terms(torch_weights, config, TORCH), H, config.newton_iters, TORCH)[0]
    np.testing.assert_allclose(on_torch.numpy(), on_numpy, rtol=0, atol=1e-12)
    for i in range(len(xs)):
        np.testing.assert_allclose(np.asarray(loaded.step(xs[i], us[i])[0]).ravel(), on_numpy[i], rtol=0, atol=1e-10)


def _controllers(model, goal, **rti):
    settings = MPCSettings(solver="rti", horizon=8, compile="none", cold_starts=("rollout+", "rollout-"),
                           orientation_residual="rotation-vector", omega_weight=0.05, terminal_orientation_weight=20.0,
                           control_weight=0.01, rti=RTIOptions(cold_budget_s=600.0, budget_s=600.0, **rti))
    low, high = -3.0 * np.ones(6), 3.0 * np.ones(6)
    return settings, low, high


def test_ipopt_and_the_real_time_iteration_bring_both_tops_to_their_goal(two_tops):
    model = export.from_terms(two_tops, BODY.terms(CA), BODY.terms(NP), H, 3, "two-tops")
    start = np.r_[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, np.zeros(6)]
    goal = np.r_[np.cos(0.3), np.sin(0.3), 0.0, 0.0, np.cos(0.3), 0.0, np.sin(0.3), 0.0, np.zeros(6)]
    settings, low, high = _controllers(model, goal)
    controllers = {"rti": RealTimeMPC(model, settings, goal, low, high, goal_set=POSES),
                   "ipopt": MPC(model, dataclasses.replace(settings, solver="ipopt"), goal, low, high, goal_set=POSES)}
    for name, controller in controllers.items():
        x = start.copy()
        for k in range(60):
            u, info = controller(x)
            assert np.all(np.isfinite(u)) and np.all(u >= low) and np.all(u <= high), (name, k, u)
            x = model(x, u)[0]
            if name == "rti":
                controller.prepare()
        assert LAYOUT.distance(x, goal) < 0.1 * LAYOUT.distance(start, goal), (name, LAYOUT.distance(x, goal))
    with pytest.raises(ValueError, match="one body's attitude"):  # an upright goal needs one attitude
        RealTimeMPC(model, settings, goal[:4], low, high)


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler: the C loop cannot be built")
def test_the_generated_loop_turns_both_bodies_toward_the_goal(two_tops):
    """The library's loop on the product S³ × S³ (its block table: two quaternions, six angular rates), against
    the model as the plant; its plan stays on both unit spheres."""
    model = export.from_terms(two_tops, BODY.terms(CA), BODY.terms(NP), H, 3, "two-tops")
    goal = np.r_[np.cos(0.3), np.sin(0.3), 0.0, 0.0, np.cos(0.3), 0.0, np.sin(0.3), 0.0, np.zeros(6)]
    settings, low, high = _controllers(model, goal)
    controller = RealTimeMPC(model, settings.updated(compile="cached"), goal, low, high, goal_set=POSES)
    x_c = np.r_[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, np.zeros(6)]
    for _ in range(25):
        u_c, info = controller(x_c)
        assert info["success"] and np.all(np.isfinite(u_c))
        x_c = model(x_c, u_c)[0]
        controller.prepare()
    for quaternion in LAYOUT.quaternions:
        np.testing.assert_allclose(np.linalg.norm(controller.plan.states[:, quaternion], axis=1), 1.0, atol=1e-12)
    assert LAYOUT.distance(x_c, goal) < 0.5 * LAYOUT.distance(np.r_[1.0, 0, 0, 0, 1.0, 0, 0, 0, np.zeros(6)], goal)
