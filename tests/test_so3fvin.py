"""The SO3FVIN baseline (LieFVIN on 3×3 rotation matrices) against independent references: a
high-accuracy ODE solution of a heavy top's Euler equations (second order), the S³ step on the
same physics (the two are the same map — ``core/fvin_so3``'s docstring says why), orthogonality
of ``R`` over long rollouts, finite differences of the Newton Jacobian and of the learned torque,
and torch ↔ NumPy parity."""

import numpy as np
import pytest
from helpers import random_states
from scipy.integrate import solve_ivp

from fvin_mpc.core import fvin, fvin_so3, s3, so3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.networks_so3 import SO3_VARIANTS, LearnedSO3Terms, SO3ModelConfig, init_weights
from fvin_mpc.core.rigid_body import PENDULUM, PivotedRigidBody

NP = get_ops("numpy")

#: An asymmetric heavy top with an off-axis centre of mass, two actuators and joint damping:
#: every term of the step is exercised and nothing is planar.
_A = np.array([[0.9, 0.1, -0.2], [0.1, 0.6, 0.05], [-0.2, 0.05, 0.4]])
TOP = PivotedRigidBody(inertia=tuple(map(tuple, _A)), center_of_mass=(0.1, -0.2, -0.5), mass_gravity=7.0,
                       actuator_axes=((1.0, 0.2), (0.3, -1.0), (0.5, 0.4)), damping=0.3)


def components(a):
    return tuple(a[..., i] for i in range(a.shape[-1]))


def matrix(r):
    return np.moveaxis(np.array(r, dtype=float), (0, 1), (-2, -1))


def rows(r):
    return tuple(tuple(r[..., i, j] for j in range(3)) for i in range(3))


def rollout_so3(r, omega, u, terms, h, steps, newton_iters=6):
    for _ in range(steps):
        out = fvin_so3.so3_step(r, omega, u, terms, h, newton_iters, NP)
        r, omega = out.rotation, out.omega
    return r, omega


def euler_equations(body, u):
    """``Ṙ = R[ω]×``, ``J ω̇ = Jω × ω + M(R) + B u − d ω`` with ``M = m g (R₃ × c)`` (R₃: third row)."""
    inertia, axes = np.array(body.inertia), np.array(body.actuator_axes)
    com = body.mass_gravity * np.array(body.center_of_mass)

    def rhs(_, y):
        r, omega = y[:9].reshape(3, 3), y[9:]
        torque = np.cross(inertia @ omega, omega) + np.cross(r[2], com) + axes @ u - body.damping * omega
        return np.concatenate([(r @ np.array(s3.skew(tuple(omega)))).ravel(), np.linalg.solve(inertia, torque)])

    return rhs


def test_second_order_against_a_high_accuracy_ode_solution():
    """The 1 s error against DOP853 at rtol = atol = 1e-12 falls ≈ 4× per halving of h."""
    rng = np.random.default_rng(0)
    q0, omega0 = random_states(1, seed=3, omega_scale=2.0)
    r0 = matrix(s3.rotation_matrix(components(q0[0])))
    u = rng.uniform(-1, 1, 2)
    exact = solve_ivp(euler_equations(TOP, u), (0, 1.0), np.concatenate([r0.ravel(), omega0[0]]), method="DOP853",
                      rtol=1e-12, atol=1e-12).y[:, -1]
    terms = fvin_so3.PivotedRigidBodySO3Terms(TOP, NP)
    steps = np.array([0.04, 0.02, 0.01, 0.005])
    errors = []
    for h in steps:
        r, omega = rollout_so3(rows(r0), tuple(omega0[0]), tuple(u), terms, h, int(round(1.0 / h)))
        errors.append(np.linalg.norm(matrix(r).ravel() - exact[:9]) + np.linalg.norm(np.array(omega) - exact[9:]))
    slope = np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert 1.8 < slope < 2.2, (slope, errors)


@pytest.mark.parametrize("newton_iters", [1, 2, 3, 6])
@pytest.mark.parametrize("body", [PENDULUM, TOP], ids=["pendulum", "heavy-top"])
def test_same_map_as_the_s3_step_with_twice_the_gains(body, newton_iters):
    """``R(q_{k+1})`` and ``ω_{k+1}`` of the S³ step equal the SO(3) step's to rounding, for every
    number of Newton iterations, when the S³ gains are twice the torques (core.rigid_body does that)."""
    q, omega = random_states(32, seed=1, omega_scale=4.0)
    u = np.random.default_rng(2).normal(size=(32, body.control_dim))
    s3_out = fvin.fvin_step(components(q), components(omega), components(u), body.terms(NP), 0.05, newton_iters, NP,
                            with_residual=True)
    so3_out = fvin_so3.so3_step(s3.rotation_matrix(components(q)), components(omega), components(u),
                                fvin_so3.PivotedRigidBodySO3Terms(body, NP), 0.05, newton_iters, NP, with_residual=True)
    np.testing.assert_allclose(matrix(s3.rotation_matrix(s3_out.q)), matrix(so3_out.rotation), atol=1e-14)
    np.testing.assert_allclose(np.array(s3_out.omega), np.array(so3_out.omega), atol=1e-12)
    np.testing.assert_allclose(s3_out.residual, so3_out.residual, atol=1e-12)


def test_a_gain_not_doubled_on_s3_gives_another_trajectory():
    """The factor of two is not cosmetic: an S³ model with the SO(3) torque as its gain is another system."""
    halved = PivotedRigidBody(inertia=TOP.inertia, center_of_mass=TOP.center_of_mass, mass_gravity=TOP.mass_gravity,
                              actuator_axes=tuple(tuple(0.5 * a for a in row) for row in TOP.actuator_axes),
                              damping=TOP.damping)
    q, omega = random_states(8, seed=4)
    u = np.ones((8, 2))
    s3_out = fvin.fvin_step(components(q), components(omega), components(u), halved.terms(NP), 0.05, 4, NP)
    so3_out = fvin_so3.so3_step(s3.rotation_matrix(components(q)), components(omega), components(u),
                                fvin_so3.PivotedRigidBodySO3Terms(TOP, NP), 0.05, 4, NP)
    assert np.abs(np.array(s3_out.omega) - np.array(so3_out.omega)).max() > 1e-3


def test_rotation_stays_orthogonal_and_rollouts_agree_with_s3():
    """2,000 unforced heavy-top steps: ``R`` stays orthogonal to 1e-12 and the energy bounded (no
    damping); the S³ rollout of the same physics gives the same rotations over the first 200 steps
    (later, rounding differences grow along the top's chaotic motion)."""
    body = PivotedRigidBody(inertia=TOP.inertia, center_of_mass=TOP.center_of_mass, mass_gravity=TOP.mass_gravity,
                            actuator_axes=TOP.actuator_axes)
    q, omega = random_states(4, seed=5, omega_scale=2.0)
    r = s3.rotation_matrix(components(q))
    q, omega_s3, omega = components(q), components(omega), components(omega)
    terms, terms_s3 = fvin_so3.PivotedRigidBodySO3Terms(body, NP), body.terms(NP)
    zero = (0.0 * omega[0], 0.0 * omega[0])
    e0 = fvin_so3.total_energy(r, omega, terms)
    worst_orthogonality = worst_energy = worst_difference = 0.0
    for k in range(2000):
        out = fvin_so3.so3_step(r, omega, zero, terms, 0.02, 3, NP)
        r, omega = out.rotation, out.omega
        rm = matrix(r)
        worst_orthogonality = max(worst_orthogonality, np.abs(np.swapaxes(rm, -1, -2) @ rm - np.eye(3)).max())
        worst_energy = max(worst_energy, np.max(np.abs(fvin_so3.total_energy(r, omega, terms) - e0)))
        if k < 200:
            out_s3 = fvin.fvin_step(q, omega_s3, zero, terms_s3, 0.02, 3, NP)
            q, omega_s3 = out_s3.q, out_s3.omega
            worst_difference = max(worst_difference, np.abs(rm - matrix(s3.rotation_matrix(q))).max())
    assert worst_orthogonality < 1e-12, worst_orthogonality
    assert worst_energy < 0.05 * np.max(np.abs(e0)), worst_energy
    assert worst_difference < 1e-10, worst_difference


def test_newton_jacobian_matches_finite_differences_and_is_finite_at_zero():
    inertia = tuple(map(tuple, _A))
    rng = np.random.default_rng(0)
    for f0 in [np.zeros(3), np.array([1e-4, -2e-4, 3e-5]), 0.3 * rng.normal(size=3), 1.2 * rng.normal(size=3)]:
        gamma, jacobian = fvin_so3.implicit_lhs_jacobian(tuple(f0), inertia, NP)
        numeric = np.empty((3, 3))
        for j, e in enumerate(1e-6 * np.eye(3)):
            plus = np.array(fvin_so3.implicit_lhs(tuple(f0 + e), inertia, NP), dtype=float)
            minus = np.array(fvin_so3.implicit_lhs(tuple(f0 - e), inertia, NP), dtype=float)
            numeric[:, j] = (plus - minus) / 2e-6
        np.testing.assert_allclose(np.array(jacobian, dtype=float), numeric, atol=1e-8)
        np.testing.assert_allclose(np.array(gamma, dtype=float),
                                   np.array(fvin_so3.implicit_lhs(tuple(f0), inertia, NP), dtype=float))
    np.testing.assert_allclose(
        np.array(fvin_so3.implicit_lhs_jacobian((0.0, 0.0, 0.0), inertia, NP)[1]), _A, atol=1e-15
    )


def test_exp_is_rodrigues_and_quaternion_preimage_maps_back():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(1)
    vectors = np.concatenate([rng.normal(size=(20, 3)), 1e-9 * rng.normal(size=(3, 3)),
                              np.pi * np.eye(3), [[0.0, 0.0, 0.0]]])
    np.testing.assert_allclose(matrix(so3.exp(components(vectors), NP)), Rotation.from_rotvec(vectors).as_matrix(),
                               atol=1e-14)
    # Preimages, including half turns (where w = 0 and Shepperd's other branches are needed).
    q = np.concatenate([random_states(50, seed=2)[0], [[0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [0, 0.6, 0.8, 0]]])
    r = s3.rotation_matrix(components(q))
    preimage = np.array(so3.quaternion_from_rotation(r, NP))
    np.testing.assert_allclose(np.linalg.norm(preimage, axis=0), 1.0, atol=1e-14)
    np.testing.assert_allclose(np.abs(np.sum(preimage * q.T, axis=0)), 1.0, atol=1e-14)


def test_torch_gradients_are_finite_at_zero_rotation_and_at_half_turns():
    torch = pytest.importorskip("torch")
    ops = get_ops("torch")
    f = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    inertia = tuple(map(tuple, _A))
    gamma, jacobian = fvin_so3.implicit_lhs_jacobian(tuple(f.unbind()), inertia, ops)
    (
        sum(gamma) + sum(sum(row) for row in jacobian) + sum(sum(row) for row in so3.exp(tuple(f.unbind()), ops))
    ).backward()
    assert torch.isfinite(f.grad).all()
    q = torch.tensor([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 0, 1.0], [0.5, 0.5, 0.5, 0.5]], dtype=torch.float64,
                     requires_grad=True)
    sum(so3.quaternion_from_rotation(s3.rotation_matrix(q.unbind(-1)), ops)).sum().backward()
    assert torch.isfinite(q.grad).all()


@pytest.mark.parametrize("variant", SO3_VARIANTS)
def test_learned_torque_is_minus_the_derivative_of_the_potential(variant):
    config = SO3ModelConfig(variant=variant)
    terms = LearnedSO3Terms(init_weights(config, seed=5), config, NP)
    for q in random_states(5, seed=6)[0]:
        r = matrix(s3.rotation_matrix(tuple(q)))
        torque = np.array(terms.potential_torque(rows(r)), dtype=float)
        numeric = [-(terms.potential(rows(r @ matrix(so3.exp(tuple(e), NP))))
                     - terms.potential(rows(r @ matrix(so3.exp(tuple(-e), NP))))) / 2e-6 for e in 1e-6 * np.eye(3)]
        np.testing.assert_allclose(torque, np.array(numeric, dtype=float).ravel(), atol=1e-8)


@pytest.mark.parametrize("variant", SO3_VARIANTS)
def test_torch_and_numpy_backends_agree(variant):
    torch = pytest.importorskip("torch")
    from fvin_mpc.learning.model import SO3FVIN

    config = SO3ModelConfig(variant=variant, control_dim=2, newton_iters=3)
    weights = init_weights(config, seed=1)
    q, omega = random_states(8, seed=7)
    u = np.random.default_rng(8).normal(size=(8, 2))
    out = SO3FVIN(config, weights).step(*(torch.as_tensor(a) for a in (q, omega, u)))
    reference = fvin_so3.so3_step(s3.rotation_matrix(components(q)), components(omega), components(u),
                                  LearnedSO3Terms(weights, config, NP), config.step_size, 3, NP)
    np.testing.assert_allclose(matrix(s3.rotation_matrix(components(out.q.detach().numpy()))),
                               matrix(reference.rotation), atol=1e-14)
    np.testing.assert_allclose(out.omega.detach().numpy(), np.stack(reference.omega, -1), atol=1e-13)


def test_quaternion_variant_starts_where_the_plain_s3fvin_starts():
    """Same seed, same weights: the comparison of the two in the paper study starts from one point."""
    from fvin_mpc.core import networks

    config = SO3ModelConfig(variant="so3-quaternion")
    plain = networks.init_weights(config.s3_equivalent(), seed=3)
    assert all(np.array_equal(plain[name], value) for name, value in init_weights(config, seed=3).items())


def test_train_and_checkpoint_round_trip(tmp_path):
    """``training.train``'s loop trains an SO3FVIN (the loss falls) and the checkpoint reloads bit for bit."""
    pytest.importorskip("torch")
    from helpers import synthetic_hinge_data

    from fvin_mpc.core.checkpoint import load_checkpoint, save_checkpoint
    from fvin_mpc.learning.model import SO3FVIN
    from fvin_mpc.learning.training import TrainSettings, train

    data = synthetic_hinge_data(PENDULUM, trajectories=24, steps=6)
    config = SO3ModelConfig(variant="so3-matrix", step_size=data.control_period)
    model, report = train(data, config, TrainSettings(iterations=3, window=4, jacobian_windows=32, threads=1,
                                                      patience=0), progress=False)
    assert isinstance(model, SO3FVIN)
    history = [h["train"] for h in report["history"]]
    assert history[-1] < history[0]
    stem = save_checkpoint(tmp_path / "so3", config, model.numpy_weights(), training=report)
    loaded = load_checkpoint(stem)
    assert loaded.configuration_space == "SO3"
    assert loaded.config == config
    assert all(np.array_equal(loaded.weights[k], v) for k, v in model.numpy_weights().items())

