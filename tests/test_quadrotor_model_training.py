"""Training the learned R³ × S³ model (``python -m fvin_mpc.train`` on free-body data) end to end on a few
seconds of quadrotor flight: the loss falls, the checkpoint records the configuration space and
exports to CasADi, the evaluation reports the learned and the closed-form model side by side."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fvin_mpc.control.model_export import from_checkpoint
from fvin_mpc.core.checkpoint import load_checkpoint
from fvin_mpc.core.data import load_data, save_data
from fvin_mpc.core.networks_r3s3 import R3S3Config
from fvin_mpc.core.space import R3S3, S3
from fvin_mpc.learning.collection import collect_quadrotor
from fvin_mpc.learning.space_training import train_model
from fvin_mpc.learning.training import TrainSettings
from fvin_mpc.train import main


@pytest.fixture(scope="module")
def flights():
    return collect_quadrotor(trajectories=8, steps=12, seed=5, progress=False)


def test_levenberg_marquardt_lowers_the_loss(flights):
    config = R3S3Config(hidden_width=4, step_size=flights.control_period)
    model, report = train_model(flights, config, TrainSettings(iterations=4, window=3, jacobian_windows=16,
                                                              threads=1, validation_fraction=0.25, patience=0),
                               progress=False)
    history = report["history"]
    assert report["iterations"] == 4 and history[-1]["train"] < 0.7 * history[0]["train"]
    assert report["final_train_loss"] <= history[-1]["train"]


def test_the_command_writes_a_checkpoint_that_exports(flights, tmp_path, capsys):
    data, test = tmp_path / "q.npz", tmp_path / "q_test.npz"
    save_data(data, flights)
    save_data(test, flights.subset(np.arange(2)))
    stem = tmp_path / "quadrotor_tiny"
    assert main(["--data", str(data), "--test-data", str(test), "--hidden-width", "3", "--window", "2",
                 "--iterations", "2", "--jacobian-windows", "8", "--out", str(stem), "--quiet"]) == 0
    printed = json.loads(capsys.readouterr().out)
    closed = printed["open_loop_closed_form"]["position_m"]["median"]
    assert closed < 0.01 and printed["open_loop_learned"]["all_finite"]  # the closed form through the same step
    assert 0.0 < printed["recovered"]["scale"] and "inertia" in printed["recovered"]
    checkpoint = load_checkpoint(stem)
    assert checkpoint.configuration_space == "R3xS3" and checkpoint.metadata["data"]["transitions"] == 96
    exported = from_checkpoint(checkpoint)
    x_next, residual = exported(flights.state[0, 0], flights.u[0, 0])
    assert x_next.shape == (13,) and np.isfinite(residual)


def test_the_training_command_trains_the_free_body_model_on_free_body_data(flights, tmp_path, capsys):
    """``python -m fvin_mpc.train`` reads the data's configuration space: R³ × S³ data give an
    R³ × S³ checkpoint (through the same loop), pivoted data are not mistaken for it."""
    data = tmp_path / "q.npz"
    save_data(data, flights)
    stem = tmp_path / "quadrotor_via_train"
    assert main(["--data", str(data), "--hidden-width", "3", "--window", "2", "--iterations", "1",
                               "--jacobian-windows", "8", "--out", str(stem), "--quiet"]) == 0
    capsys.readouterr()
    checkpoint = load_checkpoint(stem)
    assert checkpoint.configuration_space == "R3xS3" and checkpoint.config.hidden_width == 3
    assert checkpoint.metadata["training"]["iterations"] == 1
    from helpers import synthetic_hinge_data

    from fvin_mpc.core.rigid_body import PENDULUM

    pivoted = save_data(tmp_path / "p.npz", synthetic_hinge_data(PENDULUM, trajectories=2, steps=3))
    assert load_data(data).space is R3S3 and load_data(pivoted).space is S3
