"""Training: LM's residuals are the loss, LM beats Adam per iteration, early stopping stops,
threads and load are reported, and the CLI's defaults follow the data's scene."""

import json

import numpy as np
import pytest
from helpers import synthetic_hinge_data

from fvin_mpc.core.data import Trajectories, save_data
from fvin_mpc.core.networks import ModelConfig
from fvin_mpc.core.rigid_body import PENDULUM

torch = pytest.importorskip("torch")

from fvin_mpc.learning.training import (  # noqa: E402
    TrainSettings,
    default_checkpoint_stem,
    rollout_loss,
    rollout_residuals,
    safe_thread_count,
    scene_has_joint_damping,
    scene_stem,
    train,
)

SMALL = ModelConfig(hidden_width=6)


@pytest.fixture(scope="module")
def data():
    return synthetic_hinge_data(PENDULUM, trajectories=24, steps=6, seed=0)


def with_scene(data: Trajectories, **metadata) -> Trajectories:
    return Trajectories(data.state, data.u, {**data.metadata, **metadata})


def test_residual_squares_sum_to_the_rollout_loss(data):
    from fvin_mpc.learning.model import DTYPE, S3FVIN

    model = S3FVIN(SMALL, seed=1)
    q, omega, u = (torch.as_tensor(a, dtype=DTYPE) for a in data.windows(4))
    with torch.no_grad():
        q_hat, omega_hat = model.rollout(q[:, 0], omega[:, 0], u)
        residuals = rollout_residuals(q_hat, omega_hat, q, omega, 0.3)
        loss = rollout_loss(model, q, omega, u, 0.3)
        # q and −q are the same rotation: the residuals' squares do not change.
        flipped = rollout_residuals(q_hat, omega_hat, -q, omega, 0.3)
    assert residuals.shape == (q.shape[0], 4, 6)
    np.testing.assert_allclose((residuals**2).sum().item() / (q.shape[0] * 4), loss.item(), rtol=1e-12)
    np.testing.assert_allclose((flipped**2).sum().item(), (residuals**2).sum().item(), rtol=1e-12)


@pytest.mark.parametrize("variant", ["sign-invariant", "fixed-inertia", "plain"])
@pytest.mark.parametrize("dissipation", [False, True])
def test_rollout_is_the_loop_of_steps(variant, dissipation):
    """The rollout reuses J, ∇U, D at each q_{k+1} for the next step: the result is bit for bit
    the loop of ``S3FVIN.step``."""
    from fvin_mpc.learning.model import DTYPE, S3FVIN

    model = S3FVIN(ModelConfig(variant=variant, control_dim=2, hidden_width=5, dissipation=dissipation), seed=4)
    generator = torch.Generator().manual_seed(1)
    q = torch.randn(7, 4, generator=generator, dtype=DTYPE)
    q = q / q.norm(dim=-1, keepdim=True)
    omega, u = (
        torch.randn(7, 3, generator=generator, dtype=DTYPE),
        torch.randn(7, 5, 2, generator=generator, dtype=DTYPE),
    )
    with torch.no_grad():
        q_roll, omega_roll = model.rollout(q, omega, u)
        qs, omegas = [q], [omega]
        for k in range(u.shape[1]):
            out = model.step(qs[-1], omegas[-1], u[:, k])
            qs.append(out.q)
            omegas.append(out.omega)
    assert torch.equal(q_roll, torch.stack(qs, 1)) and torch.equal(omega_roll, torch.stack(omegas, 1))


def test_orientation_residuals_have_lagranges_gauss_newton_matrix(data):
    """The three ``2 Im(q̄ ⊗ q̂)`` give the sum of squares, ``JᵀJ`` and ``Jᵀr`` of the six
    ``2(q̂ᵢqⱼ − q̂ⱼqᵢ)`` of Lagrange's identity, for predictions ``q̂`` moved by any parameters."""
    q = torch.as_tensor(data.windows(3)[0][:5], dtype=torch.float64)
    generator = torch.Generator().manual_seed(0)
    mixing = torch.randn(*q.shape, 7, generator=generator, dtype=torch.float64)
    omega = torch.zeros(q.shape[:-1] + (3,), dtype=torch.float64)
    i, j = torch.triu_indices(4, 4, 1)

    def residual_sets(theta):
        q_hat = q + 0.3 * (mixing @ theta)
        q_hat = q_hat / q_hat.norm(dim=-1, keepdim=True)
        ours = rollout_residuals(q_hat, omega, q, omega, 0.1)[..., :3].reshape(-1)
        a, b = q_hat[:, 1:], q[:, 1:]
        lagrange = (2.0 * (a[..., i] * b[..., j] - a[..., j] * b[..., i])).reshape(-1)
        return ours, lagrange

    theta = torch.randn(7, generator=generator, dtype=torch.float64)
    ours, lagrange = residual_sets(theta)
    j_ours, j_lagrange = torch.autograd.functional.jacobian(residual_sets, theta)
    assert ours.numel() * 2 == lagrange.numel()
    np.testing.assert_allclose((ours**2).sum().item(), (lagrange**2).sum().item(), rtol=1e-12)
    np.testing.assert_allclose((j_ours.T @ j_ours).numpy(), (j_lagrange.T @ j_lagrange).numpy(), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose((j_ours.T @ ours).numpy(), (j_lagrange.T @ lagrange).numpy(), rtol=1e-10, atol=1e-12)


def test_lm_window_jacobian_matches_the_loss_gradient(data):
    """LM's per-window residuals (through ``torch.func``) give ``∇loss = 2 Jᵀr`` exactly."""
    from fvin_mpc.learning.model import DTYPE, S3FVIN
    from fvin_mpc.learning.training import _LevenbergMarquardt

    model = S3FVIN(ModelConfig(hidden_width=4, dissipation=True), seed=2)
    windows = tuple(torch.as_tensor(a, dtype=DTYPE)[:6] for a in data.windows(3))
    lm = _LevenbergMarquardt(model, windows, TrainSettings(omega_weight=0.2))
    theta = lm._theta()
    jacobian = lm._jacobian(theta, *windows).reshape(-1, theta.numel())
    residuals = torch.cat([lm._window_residuals(theta, *(w[i] for w in windows)) for i in range(windows[0].shape[0])])
    loss = rollout_loss(model, *windows, 0.2)
    loss.backward()
    gradient = torch.cat([p.grad.reshape(-1) for p in model.weights.values()])
    np.testing.assert_allclose((residuals**2).sum().item(), loss.item(), rtol=1e-12)
    np.testing.assert_allclose((2 * jacobian.T @ residuals).numpy(), gradient.numpy(), rtol=1e-8, atol=1e-14)


def test_lm_needs_far_fewer_iterations_than_adam(data):
    common = dict(iterations=8, window=3, seed=3, patience=0, threads=1)
    _, lm = train(data, SMALL, TrainSettings(optimizer="lm", **common), progress=False)
    _, adam = train(
        data, SMALL, TrainSettings(optimizer="adam", learning_rate=2e-2, eval_every=1, **common), progress=False
    )
    initial = lm["history"][0]["train"]
    assert initial == adam["history"][0]["train"]  # same seed, same start
    assert lm["final_train_loss"] < 0.02 * initial, lm["history"]
    assert lm["final_train_loss"] < 0.05 * adam["final_train_loss"], (lm["history"], adam["history"])


def test_lbfgs_reduces_the_loss(data):
    _, report = train(data, SMALL, TrainSettings(optimizer="lbfgs", iterations=3, window=3, patience=0, threads=1),
                      progress=False)
    assert report["final_train_loss"] < 0.8 * report["history"][0]["train"], report["history"]


def test_early_stopping_stops_and_keeps_the_best_weights(data):
    # A 50 % improvement per evaluation is never met: stop after `patience` stale evaluations (the bare
    # patience rule: no verdict, so no fresh run however poor the plateau).
    settings = TrainSettings(optimizer="adam", iterations=200, eval_every=1, patience=2, min_improvement=0.5,
                             window=3, threads=1, poor_loss_ratio=None)
    _, report = train(data, SMALL, settings, progress=False)
    assert report["iterations"] == 3, report["history"]
    assert "did not improve" in report["stopped"]
    assert report["final_validation_loss"] == min(h["validation"] for h in report["history"])


def test_a_reached_target_stops_training(data):
    settings = TrainSettings(optimizer="lm", iterations=30, window=3, target_loss=0.5, threads=1)
    _, report = train(data, SMALL, settings, progress=False)
    assert report["history"][-1]["validation"] <= 0.5
    assert "target" in report["stopped"] and report["iterations"] < 30


def test_compile_is_refused_for_lm():
    with pytest.raises(ValueError, match="compile"):
        TrainSettings(optimizer="lm", compile=True)


@pytest.mark.parametrize(
    "cores, load, threads", [(2, 0.05, 2), (2, 0.6, 1), (2, 1.2, 1), (2, 7.0, 1), (8, 2.5, 6), (8, 0.0, 8), (1, 0.0, 1)]
)
def test_safe_thread_count_leaves_busy_cores_alone(cores, load, threads):
    assert safe_thread_count(cores, load) == threads


@pytest.mark.parametrize("scene, stem", [("pendulum", "pendulum"), ("pendulum-h0.02", "pendulum-h0.02"),
                                         ("/abs/path/to/arm.xml", "arm"), ("rel/arm.XML", "arm"), ("arm.xml", "arm")])
def test_scene_stem(scene, stem):
    assert scene_stem(scene) == stem


def test_damping_is_read_from_the_metadata_or_the_scene():
    assert scene_has_joint_damping({"scene": "pendulum_damped"}) is True
    assert scene_has_joint_damping({"scene": "pendulum"}) is False
    assert scene_has_joint_damping({"scene": "pendulum", "physics": {"joint_damping": True}}) is True
    assert scene_has_joint_damping({"scene": "/no/such/scene.xml"}) is None
    assert scene_has_joint_damping({}) is None


def run_cli(tmp_path, monkeypatch, data, *args, data_file="d.npz"):
    from fvin_mpc.core.checkpoint import load_checkpoint
    from fvin_mpc.train import main

    monkeypatch.chdir(tmp_path)
    path = save_data(tmp_path / data_file, data)
    assert (
        main(["--data", str(path), "--iterations", "2", "--hidden-width", "4", "--window", "3", "--quiet", *args]) == 0
    )
    checkpoints = sorted((tmp_path / "checkpoints").glob("*.json"))
    assert len(checkpoints) == 1, checkpoints
    return checkpoints[0], load_checkpoint(checkpoints[0])


def test_cli_default_output_is_the_scene_stem_for_an_absolute_mjcf_path(tmp_path, monkeypatch, data):
    scene = str(tmp_path / "scenes" / "arm.xml")  # absolute; the file need not exist to name the checkpoint
    sidecar, checkpoint = run_cli(tmp_path, monkeypatch, with_scene(data, scene=scene), "--variant", "plain",
                                  "--no-dissipation", data_file="arm.npz")  # named after the scene, as collect does
    assert sidecar == tmp_path / "checkpoints" / "arm_plain.json"
    assert checkpoint.scene == scene
    assert not (tmp_path / "scenes").exists()
    assert default_checkpoint_stem(with_scene(data, scene="rel/arm.xml"), "plain").as_posix() == "checkpoints/arm_plain"


def test_cli_records_threads_and_load(tmp_path, monkeypatch, data):
    sidecar, _ = run_cli(tmp_path, monkeypatch, data, "--threads", "1", "--optimizer", "adam")
    training = json.loads(sidecar.read_text())["training"]
    assert training["threads"] == 1 and training["threads_chosen"] == "given"
    assert len(training["load_average_start"]) == 3 and len(training["load_average_end"]) == 3
    assert training["optimizer"] == "adam" and training["iterations"] == 2


@pytest.mark.parametrize("scene, flag, expected", [("pendulum_damped", (), True), ("pendulum", (), False),
                                                   ("pendulum_damped", ("--no-dissipation",), False),
                                                   ("pendulum", ("--dissipation",), True)])
def test_cli_dissipation_defaults_to_the_scene_damping(tmp_path, monkeypatch, data, scene, flag, expected):
    sidecar, checkpoint = run_cli(tmp_path, monkeypatch, with_scene(data, scene=scene), *flag, data_file=f"{scene}.npz")
    assert checkpoint.config.dissipation is expected
    assert sidecar.name == f"{scene}_sign-invariant.json"
