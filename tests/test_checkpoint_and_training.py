"""Checkpoints round-trip without pickle and fail loudly; training is seeded and learns."""

import json

import numpy as np
import pytest
from helpers import synthetic_hinge_data

from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from fvin_mpc.core.data import load_data, save_data
from fvin_mpc.core.networks import ModelConfig, init_weights
from fvin_mpc.core.rigid_body import PENDULUM

NP = get_ops("numpy")


@pytest.fixture
def saved(tmp_path):
    config = ModelConfig(variant="fixed-inertia", hidden_width=6)
    weights = init_weights(config, seed=0)
    stem = save_checkpoint(tmp_path / "model", config, weights, scene="pendulum", data={"transitions": 10})
    return stem, config, weights


def test_checkpoint_round_trip_keeps_weights_and_metadata(saved):
    stem, config, weights = saved
    loaded = load_checkpoint(stem.with_suffix(".safetensors"))
    assert loaded.config == config
    assert loaded.scene == "pendulum" and loaded.metadata["data"] == {"transitions": 10}
    for name, value in weights.items():
        np.testing.assert_array_equal(loaded.weights[name], value)


def test_truncated_weights_give_a_one_line_error(saved):
    stem, *_ = saved
    path = stem.with_suffix(".safetensors")
    path.write_bytes(path.read_bytes()[:-40])
    with pytest.raises(CheckpointError, match="truncated") as info:
        load_checkpoint(stem)
    assert "\n" not in str(info.value)


def test_mismatched_config_names_the_weight(saved):
    stem, *_ = saved
    sidecar = json.loads(stem.with_suffix(".json").read_text())
    sidecar["model"]["hidden_width"] = 7
    stem.with_suffix(".json").write_text(json.dumps(sidecar))
    with pytest.raises(CheckpointError, match="potential_w0.*shape"):
        load_checkpoint(stem)


@pytest.mark.parametrize(
    "content, message",
    [
        ("{not json", "not valid JSON"),
        ('{"format": "other"}', "format"),
        ('{"format": "fvin_mpc.checkpoint/1", "model": {"variant": "bogus"}}', "invalid model config"),
    ],
)
def test_malformed_sidecar(saved, content, message):
    stem, *_ = saved
    stem.with_suffix(".json").write_text(content)
    with pytest.raises(CheckpointError, match=message):
        load_checkpoint(stem)


def test_missing_checkpoint(tmp_path):
    with pytest.raises(CheckpointError, match="not found"):
        load_checkpoint(tmp_path / "nothing")


def test_nan_weights_rejected(tmp_path):
    config = ModelConfig(hidden_width=4)
    weights = init_weights(config, seed=0)
    weights["potential_b0"][0] = np.nan
    stem = save_checkpoint(tmp_path / "nan", config, weights)
    with pytest.raises(CheckpointError, match="NaN"):
        load_checkpoint(stem)


def synthetic_pendulum_data(trajectories=48, steps=10, seed=0):
    return synthetic_hinge_data(PENDULUM, trajectories, steps, seed)


def test_data_round_trip(tmp_path):
    data = synthetic_pendulum_data(trajectories=4, steps=3)
    loaded = load_data(save_data(tmp_path / "d.npz", data))
    np.testing.assert_array_equal(loaded.q, data.q)
    assert loaded.metadata == data.metadata
    q, omega, u = data.windows(2)
    assert q.shape == (8, 3, 4) and u.shape == (8, 2, 1)


def test_training_is_seeded_and_reduces_the_rollout_loss():
    pytest.importorskip("torch")
    from fvin_mpc.learning.training import TrainSettings, train

    data = synthetic_pendulum_data()
    settings = TrainSettings(optimizer="adam", iterations=100, window=4, seed=3, eval_every=20, learning_rate=2e-2,
                             patience=0, threads=1)
    model_a, report_a = train(data, ModelConfig(hidden_width=8), settings, progress=False)
    model_b, report_b = train(data, ModelConfig(hidden_width=8), settings, progress=False)
    assert report_a["final_train_loss"] == report_b["final_train_loss"]
    first = report_a["history"][0]["train"]
    assert report_a["final_train_loss"] < 0.05 * first, report_a["history"]
    assert np.isfinite(report_a["final_validation_loss"])


def test_dots_in_a_checkpoint_name_are_kept(tmp_path):
    """``pendulum-h0.02_x`` once became ``pendulum-h0.*``: ``Path.with_suffix`` took ``.02_x`` for a suffix."""
    config = ModelConfig(hidden_width=4)
    stem = save_checkpoint(tmp_path / "pendulum-h0.02_sign-invariant", config, init_weights(config, seed=0))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pendulum-h0.02_sign-invariant.json",
                                                         "pendulum-h0.02_sign-invariant.safetensors"]
    assert load_checkpoint(stem).config == config
    assert load_checkpoint(tmp_path / "pendulum-h0.02_sign-invariant.json").config == config


def test_a_flipped_bit_inside_the_weights_is_caught_by_the_checksum(saved):
    stem, *_ = saved
    path = stem.with_suffix(".safetensors")
    data = bytearray(path.read_bytes())
    data[-3] ^= 0x01  # inside the last float: the file still parses, the number changed
    path.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="SHA-256"):
        load_checkpoint(stem)


def test_shipped_checkpoints_carry_a_matching_checksum():
    from fvin_mpc.core.checkpoint import CHECKPOINT_DIR

    sidecars = sorted(CHECKPOINT_DIR.glob("*.json"))
    assert sidecars, "no shipped checkpoints"
    for sidecar in sidecars:
        assert "weights_sha256" in json.loads(sidecar.read_text()), sidecar
        load_checkpoint(sidecar)  # verifies the digest
