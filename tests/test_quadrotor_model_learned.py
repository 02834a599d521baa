"""The learned R³ × S³ terms (:mod:`fvin_mpc.core.networks_r3s3`), the torch shell, checkpoints and the
CasADi export: gradients against differences, sign invariance, NumPy ↔ torch ↔ CasADi parity of the
step (value and Jacobian), and the closed-form and learned exports behind one call signature."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
import torch

from fvin_mpc.control.model_export import from_checkpoint, from_quadrotor
from fvin_mpc.core import fvin_r3s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.checkpoint import load_checkpoint, save_checkpoint
from fvin_mpc.core.networks_r3s3 import LearnedCombinedTerms, R3S3Config, init_weights, physical_scale
from fvin_mpc.core.quadrotor import QUADROTOR
from fvin_mpc.learning.model import FVINModel

NP, CA = get_ops("numpy"), get_ops("casadi")
H = 0.02


def lively_weights(config: R3S3Config, seed: int) -> dict[str, np.ndarray]:
    """Initial weights with output layers scaled up, so every term matters in the step."""
    weights = init_weights(config, seed, mass=0.7, inertia=0.01, gravity_force=5.0)
    rng = np.random.default_rng(seed + 100)
    for name in weights:
        if name.endswith(f"_w{config.hidden_layers}") or name.endswith(f"_b{config.hidden_layers}"):
            weights[name] = weights[name] * 10.0 + rng.normal(scale=0.3, size=weights[name].shape)
    weights["mass_cholesky"][3:] = [0.1, -0.05, 0.08]
    if "inertia_cholesky" in weights:
        weights["inertia_cholesky"][3:] = [0.01, 0.0, -0.01]
    return weights


def random_state(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return np.concatenate(
        [rng.normal(size=3), q / np.linalg.norm(q), rng.normal(size=3), rng.normal(scale=4.0, size=3)]
    )


CONFIGS = [R3S3Config(variant=v, hidden_width=6, step_size=H, newton_iters=3) for v in
           ("fixed-inertia", "sign-invariant", "plain")] + [
    R3S3Config(variant="fixed-inertia", hidden_width=5, step_size=H, position_in_forces=True, force_rule="hold",
               force_frame="world")]


@pytest.mark.parametrize("config", CONFIGS, ids=lambda c: f"{c.variant}-{c.force_rule}-{c.force_frame}")
def test_potential_gradients_match_differences_and_sign_invariance_holds(config):
    rng = np.random.default_rng(0)
    terms = LearnedCombinedTerms(lively_weights(config, 1), config, NP)
    state = random_state(rng)
    x, q = tuple(state[:3]), tuple(state[3:7])
    grad_x, grad_q = np.array(terms.potential_gradient_x(x, q)), np.array(terms.potential_gradient_q(x, q))
    eps = 1e-6
    for i in range(3):
        e = np.eye(3)[i] * eps
        diff = (terms.potential(tuple(state[:3] + e), q) - terms.potential(tuple(state[:3] - e), q)) / (2 * eps)
        assert diff == pytest.approx(grad_x[i], abs=1e-7)
    for i in range(4):
        e = np.eye(4)[i] * eps
        diff = (terms.potential(x, tuple(state[3:7] + e)) - terms.potential(x, tuple(state[3:7] - e))) / (2 * eps)
        assert diff == pytest.approx(grad_q[i], abs=1e-7)
    mass = np.array(terms.mass_matrix())
    assert np.all(np.linalg.eigvalsh(0.5 * (mass + mass.T)) > 0)
    u = tuple(rng.uniform(0, 2, size=4))
    flipped = tuple(-c for c in q)
    pairs = [(terms.potential(x, q), terms.potential(x, flipped)), (terms.inertia(q), terms.inertia(flipped)),
             (terms.translational_force(x, q, u), terms.translational_force(x, flipped, u)),
             (terms.control_gain(x, q), terms.control_gain(x, flipped))]
    same = all(np.allclose(a, b, rtol=0, atol=1e-14) for a, b in pairs)
    assert same == config.sign_invariant


@pytest.mark.parametrize("config", CONFIGS, ids=lambda c: f"{c.variant}-{c.force_rule}-{c.force_frame}")
def test_numpy_torch_and_casadi_take_the_same_step(config):
    weights = lively_weights(config, 2)
    rng = np.random.default_rng(1)
    states = np.array([random_state(rng) for _ in range(4)])
    controls = rng.uniform(0.0, 2.5, size=(4, 4))
    expected, residual = fvin_r3s3.step_state(states, controls, LearnedCombinedTerms(weights, config, NP), H,
                                              config.newton_iters, NP, config.force_rule)
    assert np.all(np.abs(expected - states) > 0)  # every entry moves
    model = FVINModel(config, weights)
    with torch.no_grad():
        out_state, out_residual = model.step_state(torch.as_tensor(states), torch.as_tensor(controls))
    np.testing.assert_allclose(out_state.numpy(), expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(out_residual.numpy(), residual, rtol=0, atol=1e-12)
    # The training layout round-trips.
    scaled = FVINModel(config, weights, rest_scale=(30.0,) * 3 + (10.0,) * 3 + (1.0,) * 3)
    with torch.no_grad():
        rolled = scaled.rollout_states(torch.as_tensor(states), torch.as_tensor(controls[:, None]))
    np.testing.assert_allclose(rolled[:, 1].numpy(), expected, rtol=0, atol=1e-12)
    # CasADi: value and Jacobian against central differences.
    x, u = ca.SX.sym("x", 13), ca.SX.sym("u", 4)
    x_next, res = fvin_r3s3.step_state(x, u, LearnedCombinedTerms(weights, config, CA), H, config.newton_iters, CA,
                                       config.force_rule)
    function = ca.Function("f", [x, u], [x_next, res, ca.jacobian(x_next, ca.vertcat(x, u))])
    for i in range(4):
        value, value_residual, jacobian = function(states[i], controls[i])
        np.testing.assert_allclose(np.asarray(value).ravel(), expected[i], rtol=0, atol=1e-12)
        assert float(value_residual) == pytest.approx(residual[i], abs=1e-12)
        point, eps = np.concatenate([states[i], controls[i]]), 1e-6
        numeric = np.column_stack([
            (np.asarray(function(*np.split(point + e, [13])) [0]).ravel()
             - np.asarray(function(*np.split(point - e, [13]))[0]).ravel()) / (2 * eps)
            for e in np.eye(17) * eps])
        np.testing.assert_allclose(np.asarray(jacobian), numeric, rtol=1e-5, atol=1e-6)


def test_a_checkpoint_says_its_configuration_space_and_exports_to_the_same_step(tmp_path):
    config = CONFIGS[0]
    weights = lively_weights(config, 3)
    stem = save_checkpoint(tmp_path / "quadrotor_test", config, weights, scene="quadrotor")
    checkpoint = load_checkpoint(stem)
    assert isinstance(checkpoint.config, R3S3Config) and checkpoint.config == config
    assert checkpoint.configuration_space == "R3xS3" and checkpoint.metadata["configuration_space"] == "R3xS3"
    exported = from_checkpoint(checkpoint)
    assert exported.state_dim == 13 and exported.configuration_space == "R3xS3"
    rng = np.random.default_rng(4)
    state, u = random_state(rng), rng.uniform(0.0, 2.5, size=4)
    expected, residual = fvin_r3s3.step_state(state, u, LearnedCombinedTerms(weights, config, NP), H,
                                              config.newton_iters, NP)
    value, value_residual = exported(state, u)
    np.testing.assert_allclose(value, expected, rtol=0, atol=1e-12)
    assert value_residual == pytest.approx(float(residual), abs=1e-12)
    truth = from_quadrotor(QUADROTOR, H, 3)
    assert truth.step.name_in() == exported.step.name_in() and truth.step.size_in(0) == exported.step.size_in(0)
    assert truth.step.size_out(0) == exported.step.size_out(0) == (13, 1)
    expected_truth, _ = fvin_r3s3.step_state(state, u, QUADROTOR.terms(NP), H, 3, NP)
    np.testing.assert_allclose(truth(state, u)[0], expected_truth, rtol=0, atol=1e-12)
    assert exported.energy(state) == pytest.approx(float(fvin_r3s3.total_energy(
        *fvin_r3s3.split_free_state(state, NP), LearnedCombinedTerms(weights, config, NP))), rel=1e-12)


def test_the_scale_is_read_off_the_thrust():
    """A model that is the truth times c: physical_scale gives c back, and the recovered M/c is m."""
    config = R3S3Config(variant="fixed-inertia", hidden_width=3, step_size=H)
    weights = init_weights(config, 0)
    last = config.hidden_layers
    weights[f"force_w{last}"][:] = 0.0
    c = 3.0
    weights[f"force_b{last}"][:] = np.array([[0, 0, 0, 0], [0, 0, 0, 0], [c, c, c, c]]).reshape(-1)
    weights["mass_cholesky"][:3] = np.sqrt(c * 0.5)
    terms = LearnedCombinedTerms(weights, config, NP)
    assert physical_scale(terms) == pytest.approx(c)
    assert np.array(terms.mass_matrix())[0, 0] / physical_scale(terms) == pytest.approx(0.5, rel=1e-5)
