"""q vs −q: the sign-invariant variant predicts the same physical motion from ``q`` and ``−q``
(``q' → −q'``, ``ω'`` unchanged) in torch and in the CasADi export, for random weights.
The MPC's cost and torque under ``q → −q`` and ``goal → −goal`` are in ``test_hard_mpc.py``."""

import numpy as np
import pytest
import strategies as S
import torch  # noqa: E402  (a dependency: a missing torch is a failure, not a skip)
from hypothesis import given, settings
from hypothesis import strategies as st

from fvin_mpc.control import model_export as export
from fvin_mpc.core.checkpoint import save_checkpoint
from fvin_mpc.core.networks import ModelConfig, init_weights

WEIGHT_SEEDS = (0, 1, 2)


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """Random-weight sign-invariant models (m = 1 and m = 3 with damping) in torch and CasADi."""
    from fvin_mpc.learning.model import S3FVIN

    built = {}
    for seed in WEIGHT_SEEDS:
        control_dim = 1 if seed < 2 else 3
        config = ModelConfig(variant="sign-invariant", control_dim=control_dim, dissipation=control_dim == 3,
                             newton_iters=3)
        weights = init_weights(config, seed=seed)
        # Random output layers of a useful size (init_weights makes them small on purpose).
        rng = np.random.default_rng(100 + seed)
        weights = {k: (v + rng.normal(scale=0.3, size=v.shape)) if k.endswith("_w2") else v for k, v in weights.items()}
        stem = save_checkpoint(tmp_path_factory.mktemp("sign") / f"sign_{seed}", config, weights, scene="test")
        built[seed] = (S3FVIN(config, weights), export.from_checkpoint(stem), control_dim)
    return built


def as_batch(array):
    """One state as a float64 batch of size 1, the torch model's input layout."""
    return torch.as_tensor(array, dtype=torch.float64)[None]


states = st.tuples(
    S.unit_quaternions(), S.vectors(3, -8.0, 8.0), S.vectors(3, -2.0, 2.0), st.sampled_from(WEIGHT_SEEDS)
)


@settings(max_examples=S.budget(150))
@given(state=states)
@S.counted
def test_torch_sign_invariant_step_is_the_same_motion_for_q_and_minus_q(models, state):
    q, omega, u, seed = state
    model, _, m = models[seed]
    with torch.no_grad():
        plus = model.step(as_batch(q), as_batch(omega), as_batch(u[:m]), with_residual=True)
        minus = model.step(as_batch(-q), as_batch(omega), as_batch(u[:m]), with_residual=True)
    np.testing.assert_allclose(minus.q.numpy(), -plus.q.numpy(), atol=1e-13)
    np.testing.assert_allclose(
        minus.omega.numpy(), plus.omega.numpy(), atol=1e-12 * (1 + np.abs(plus.omega.numpy()).max())
    )
    np.testing.assert_allclose(minus.residual.numpy(), plus.residual.numpy(), atol=1e-12)


@settings(max_examples=S.budget(1000))
@given(state=states)
@S.counted
def test_casadi_sign_invariant_export_is_the_same_motion_for_q_and_minus_q(models, state):
    q, omega, u, seed = state
    _, exported, m = models[seed]
    x_plus, r_plus = exported(np.concatenate([q, omega]), u[:m])
    x_minus, r_minus = exported(np.concatenate([-q, omega]), u[:m])
    np.testing.assert_allclose(x_minus[:4], -x_plus[:4], atol=1e-13)
    np.testing.assert_allclose(x_minus[4:], x_plus[4:], atol=1e-12 * (1 + np.abs(x_plus[4:]).max()))
    assert r_minus == pytest.approx(r_plus, abs=1e-12)


@settings(max_examples=S.budget(100))
@given(state=states)
@S.counted
def test_torch_and_casadi_agree_on_random_states(models, state):
    q, omega, u, seed = state
    model, exported, m = models[seed]
    with torch.no_grad():
        out = model.step(as_batch(q), as_batch(omega), as_batch(u[:m]))
    x_next, _ = exported(np.concatenate([q, omega]), u[:m])
    np.testing.assert_allclose(x_next, np.concatenate([out.q[0].numpy(), out.omega[0].numpy()]),
                               atol=1e-10 * (1 + np.abs(x_next).max()))
