"""The unstructured baseline (benchmarks.mlp_baseline): its CasADi export is its torch step,
it is sign-equivariant when asked (and only then), it trains through the package's loop, and the
package's MPC runs on it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from benchmarks.data_efficiency import export_mlp
from benchmarks.mlp_baseline import (
    IncrementMLP,
    MLPConfig,
    init_mlp_weights,
    load_mlp,
    mlp_step_function,
    save_mlp,
    train_mlp,
)


def _lively_weights(config: MLPConfig, seed: int = 0) -> dict[str, np.ndarray]:
    """Initial weights with an O(1) last layer: the untrained step is nearly the identity, which
    would make any comparison pass trivially."""
    weights = init_mlp_weights(config, seed)
    rng = np.random.default_rng(seed + 1)
    return {name: value * 100.0 + (rng.normal(scale=0.3, size=value.shape) if "_b" in name else 0.0)
            if name.endswith(f"_w{config.hidden_layers}") or "_b" in name else value for name, value in weights.items()}


def _states(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q, rng.normal(scale=4.0, size=(n, 3)), rng.uniform(-2.0, 2.0, size=(n, 1))


def _torch_step(model, q, omega, u):
    with torch.no_grad():
        out = model.step(*(torch.as_tensor(a, dtype=torch.float64) for a in (q, omega, u)))
    return np.concatenate([out.q.numpy(), out.omega.numpy()], axis=1)


@pytest.mark.parametrize("symmetric", [True, False])
def test_casadi_export_matches_torch_step_to_1e_10(symmetric):
    config = MLPConfig(sign_symmetric=symmetric)
    weights = _lively_weights(config)
    model = IncrementMLP(config, weights)
    function = mlp_step_function(weights, config)
    q, omega, u = _states(20, seed=3)
    expected = _torch_step(model, q, omega, u)
    moved = np.abs(expected[:, 4:] - omega).max()
    assert moved > 0.1, "the step must do something for the comparison to mean anything"
    for i in range(len(q)):
        x_next, residual = function(np.concatenate([q[i], omega[i]]), u[i])
        np.testing.assert_allclose(np.asarray(x_next).ravel(), expected[i], rtol=0, atol=1e-10)
        assert float(residual) == 0.0
    np.testing.assert_allclose(np.linalg.norm(expected[:, :4], axis=1), 1.0, atol=1e-14)


def test_sign_equivariant_only_when_symmetrized():
    q, omega, u = _states(10, seed=5)
    symmetric = IncrementMLP(MLPConfig(sign_symmetric=True), _lively_weights(MLPConfig()))
    plus, minus = _torch_step(symmetric, q, omega, u), _torch_step(symmetric, -q, omega, u)
    np.testing.assert_allclose(minus[:, :4], -plus[:, :4], atol=1e-13)
    np.testing.assert_allclose(minus[:, 4:], plus[:, 4:], atol=1e-13)
    bare = IncrementMLP(MLPConfig(sign_symmetric=False), _lively_weights(MLPConfig(sign_symmetric=False)))
    plus, minus = _torch_step(bare, q, omega, u), _torch_step(bare, -q, omega, u)
    assert np.abs(minus[:, 4:] - plus[:, 4:]).max() > 1e-3


def test_trains_through_the_package_loop_and_lowers_the_loss():
    from fvin_mpc.learning.collection import collect
    from fvin_mpc.learning.training import TrainSettings

    data = collect("pendulum", trajectories=6, steps=10, seed=2, progress=False)
    model, report = train_mlp(data, MLPConfig(hidden_width=16),
                              TrainSettings(iterations=8, jacobian_windows=16, threads=1, patience=0), progress=False)
    losses = [entry["train"] for entry in report["history"]]
    assert report["iterations"] == 8 and len(losses) == 8
    # Levenberg–Marquardt on the rollout loss: the training loss falls several-fold in 8 iterations
    # (≈ 0.96 → 0.05 here); the returned weights are the best on the validation trajectory.
    assert losses[-1] < 0.25 * losses[0]
    assert report["final_validation_loss"] <= min(entry["validation"] for entry in report["history"]) + 1e-15
    assert all(p.dtype == torch.float64 for p in model.parameters())


def test_save_load_round_trip_and_shape_check(tmp_path):
    config = MLPConfig(hidden_width=5)
    weights = _lively_weights(config)
    stem = save_mlp(tmp_path / "m", config, weights, note="x")
    loaded_config, loaded = load_mlp(stem)
    assert loaded_config == config
    for name in weights:
        np.testing.assert_array_equal(loaded[name], weights[name])
    broken = dict(weights, increment_w0=np.zeros((5, 3)))
    with pytest.raises(ValueError):
        save_mlp(tmp_path / "bad", config, broken)


def test_the_package_mpc_runs_on_the_exported_mlp_with_the_closed_form_energy():
    from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings
    from fvin_mpc.core.rigid_body import from_mujoco

    env = scene_env("pendulum", true_model=True)
    base = env.unwrapped
    body = from_mujoco(base.model, base.body_name)
    config = MLPConfig()
    model = export_mlp(_lively_weights(config), config, body, name="test")
    assert model.name.endswith("+true-energy")
    truth = scene_model(env, true_model=True)
    x = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0])
    assert model.energy(x) == pytest.approx(truth.energy(x), abs=1e-12)
    settings = scene_mpc_settings(env).updated(compile="none", horizon=5, cold_starts=("rollout+",),
                                               ipopt={"cold_max_iter": 20, "max_iter": 10})
    controller = scene_mpc(env, model, settings)
    u, _ = controller(np.concatenate([base.rest, [0.0, 0.0, 0.0]]))
    assert np.all(np.isfinite(u)) and np.all(np.abs(u) <= base.torque_high + 1e-12)
    env.close()
