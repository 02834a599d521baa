"""Training sweep (fvin_mpc.studies.training_sweep, python -m fvin_mpc.sweep): every grid entry trained and
written with its sidecar, one table; the same weights on a real local Ray cluster as here; a run
that fails is listed while the others are written."""

import json

import numpy as np
import pytest
from test_pool import ray_cluster  # noqa: F401  (the session's local Ray cluster)

import fvin_mpc.learning.training
import fvin_mpc.studies.training_sweep
from fvin_mpc.core.checkpoint import load_checkpoint
from fvin_mpc.studies.training_sweep import SweepConfig, run_sweep, sweep_table, write_report

TRAIN = (("optimizer", "adam"), ("iterations", 3))


@pytest.fixture(scope="module")
def data_path(tmp_path_factory):
    from fvin_mpc.core.data import save_data
    from fvin_mpc.learning.collection import collect

    path = tmp_path_factory.mktemp("sweep") / "pendulum_tiny.npz"
    save_data(path, collect("pendulum", 8, 10, 0, progress=False))
    return path


def test_sweep_on_ray_equals_local_and_writes_every_checkpoint(data_path, tmp_path, ray_cluster):  # noqa: F811
    config = SweepConfig(data=str(data_path), widths=(4,), seeds=(0, 1), sizes=(6,), train=TRAIN)
    local = run_sweep(config, tmp_path / "local", progress=False)
    on_ray = run_sweep(config, tmp_path / "ray", workers=2, progress=False, backend="ray")
    assert [r["status"] for r in local.runs] == ["ok"] * 2 and not local.failures and not on_ray.failures
    for a, b in zip(local.runs, on_ray.runs, strict=True):
        assert (a["variant"], a["seed"], a["final_validation_loss"]) == (
            b["variant"],
            b["seed"],
            b["final_validation_loss"],
        )
        mine, theirs = load_checkpoint(a["checkpoint"]), load_checkpoint(b["checkpoint"])
        assert mine.weights.keys() == theirs.weights.keys()
        for key in mine.weights:
            np.testing.assert_array_equal(mine.weights[key], theirs.weights[key])
        sidecar = theirs.metadata
        assert sidecar["sweep"] == {"variant": b["variant"], "width": 4, "size": 6, "seed": b["seed"], "backend": "ray"}
        assert sidecar["data"]["trajectories"] == 6 and sidecar["training"]["settings"]["threads"] == 1
    assert local.runs[0]["final_validation_loss"] != local.runs[1]["final_validation_loss"]  # seeds differ
    md, js = write_report(on_ray, tmp_path / "ray", "test")
    assert md.read_text().count("| sign-invariant | 4 | 6 |") == 3  # two runs, one summary row
    assert len(json.loads(js.read_text())["summary"]) == 1


def test_a_failed_run_is_listed_and_the_others_are_written(data_path, tmp_path, monkeypatch):
    real_train = fvin_mpc.learning.training.train

    def train(data, config, settings, progress=True):
        if settings.seed == 1:
            raise FloatingPointError("training loss became nan at iteration 2")
        return real_train(data, config, settings, progress)

    monkeypatch.setattr(fvin_mpc.studies.training_sweep, "train", train)  # the name the sweep calls
    config = SweepConfig(data=str(data_path), widths=(4,), seeds=(0, 1, 2), train=TRAIN)
    result = run_sweep(config, tmp_path, progress=False)  # serial: the patch applies in this process
    assert [r["status"] for r in result.runs] == ["ok", "failed", "ok"]
    assert result.runs[1]["error"] == "FloatingPointError: training loss became nan at iteration 2"
    assert len(result.failures) == 1 and "('sign-invariant', 4, None, 1)" in result.failures[0]
    assert sorted(p.name for p in tmp_path.glob("*.json")) == ["pendulum_sign-invariant_w4_n8_s0.json",
                                                              "pendulum_sign-invariant_w4_n8_s2.json"]
    assert "**failed**: FloatingPointError" in sweep_table(result)


def test_config_is_validated(data_path):
    with pytest.raises(ValueError, match="variants"):
        SweepConfig(data=str(data_path), variants=("no-such",))
    with pytest.raises(ValueError, match="training options"):
        SweepConfig(data=str(data_path), train=(("threads", 4),))
    with pytest.raises(ValueError, match="iterations"):
        SweepConfig(data=str(data_path), train=(("iterations", 0),))


def test_cli_writes_checkpoints_and_the_table(data_path, tmp_path, capsys):
    from fvin_mpc.sweep import main

    assert main(["--data", str(data_path), "--widths", "4", "--seeds", "0", "--sizes", "all", "--optimizer", "adam",
                 "--iterations", "2", "--out-dir", str(tmp_path), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "| sign-invariant | 4 | 8 | 0 | 2 |" in out
    assert (tmp_path / "sweep.md").is_file() and (tmp_path / "pendulum_sign-invariant_w4_n8_s0.safetensors").is_file()
    assert main(["--data", str(data_path), "--workers", "0", "--out-dir", str(tmp_path)]) == 2
