"""The stop rule tells a poor plateau from convergence: far above the data's floor a plateau starts a fresh
run (and the last run keeps going), a poor result says so on stderr and in the checkpoint, and checkpoints
without a verdict still load."""

import json

import numpy as np
import pytest
from helpers import synthetic_hinge_data

from fvin_mpc.core.data import save_data
from fvin_mpc.core.networks import ModelConfig
from fvin_mpc.core.rigid_body import PENDULUM

torch = pytest.importorskip("torch")

from fvin_mpc.learning.training import (  # noqa: E402
    TrainSettings,
    _EarlyStopping,
    checkpoint_quality,
    hold_loss,
    restart_seed,
    rollout_loss,
    train,
)

SMALL = ModelConfig(hidden_width=6)

#: The validation losses of the default pendulum run whose early stop gave a model that cannot control
#: (seed 0): a fast descent that pauses at iterations 5–6, then goes on to 1e-3; the hold loss 1.86.
POOR_START = [0.752, 0.553, 0.420, 0.291, 0.290, 0.299, 0.270, 0.190, 0.142, 0.106, 0.095, 0.077, 0.051, 0.038,
              0.036, 0.026, 0.020, 0.018, 0.021, 0.012, 0.012, 0.0091, 0.010, 0.0067, 0.0065]
HOLD = 1.86


@pytest.fixture(scope="module")
def data():
    return synthetic_hinge_data(PENDULUM, trajectories=24, steps=6, seed=0)


class _Weights:
    """The least a model needs for :class:`_EarlyStopping`: named weights."""

    def __init__(self) -> None:
        self.weights = {"w": torch.zeros(2)}


def replay(losses, settings, poor_above=None, persist=False):
    """The evaluation at which :class:`_EarlyStopping` stops on ``losses`` (``None``: never), and it."""
    stopping, model = _EarlyStopping(settings, poor_above, persist), _Weights()
    for k, loss in enumerate(losses, start=1):
        if stopping.update(loss, model):
            return k, stopping
    return None, stopping


def test_the_bare_patience_rule_stops_on_the_poor_runs_first_pause():
    stop, stopping = replay(POOR_START, TrainSettings())
    assert stop == 6 and stopping.plateau and stopping.best == pytest.approx(0.290)


def test_far_from_the_floor_a_plateau_ends_the_run_as_a_poor_one():
    settings = TrainSettings()
    stop, stopping = replay(POOR_START, settings, poor_above=settings.poor_loss_ratio * HOLD)
    assert stop == 6 and stopping.plateau and stopping.far  # the caller starts a fresh run


def test_the_last_run_does_not_stop_on_a_plateau_far_from_the_floor():
    settings = TrainSettings()
    limit = settings.poor_loss_ratio * HOLD  # 0.0093
    stop, stopping = replay(POOR_START, settings, poor_above=limit, persist=True)
    assert stop is None and stopping.best == pytest.approx(0.0065)
    # Below the limit patience counts again: a plateau there is convergence.
    stop, stopping = replay(POOR_START[:22] + [0.0091] * 4, settings, poor_above=limit, persist=True)
    assert stop == 24 and stopping.plateau and not stopping.far


def test_the_hold_loss_is_the_loss_of_a_model_that_predicts_no_motion(data):
    q, omega, u = (torch.as_tensor(a, dtype=torch.float64) for a in data.windows(4))

    class Frozen:
        def rollout(self, q0, rest0, controls, step=None):
            steps = controls.shape[1] + 1
            return q0[:, None].expand(-1, steps, -1), rest0[:, None].expand(-1, steps, -1)

    expected = rollout_loss(Frozen(), q, omega, u, 0.1).item()
    assert hold_loss(q, omega, 0.1) == pytest.approx(expected, rel=1e-12)
    assert expected > 0.1  # the synthetic swings move


def test_restart_seeds_differ_from_the_seed_and_each_other():
    seeds = [restart_seed(5, run) for run in range(4)]
    assert seeds[0] == 5 and len(set(seeds)) == 4 and seeds == [restart_seed(5, run) for run in range(4)]


def stalling(**changes):
    """Adam held to a 50 % gain per evaluation: every run plateaus after two evaluations, far above the floor."""
    return TrainSettings(**{**dict(optimizer="adam", iterations=12, eval_every=1, patience=2, min_improvement=0.5,
                                   window=3, threads=1), **changes})


def test_a_poor_plateau_starts_fresh_runs_and_the_result_is_reported_poor(data):
    _, report = train(data, SMALL, stalling(restarts=2), progress=False)
    runs = report["runs"]
    assert [run["run"] for run in runs] == [0, 1, 2] and report["restarts"] == 2
    assert [run["iterations"] for run in runs] == [3, 3, 6]  # the last run ends at the iteration limit
    assert len({run["seed"] for run in runs}) == 3
    starts = [next(h for h in report["history"] if h["run"] == k)["train"] for k in range(3)]
    assert len(set(starts)) == 3  # fresh initializations, not the same start again
    assert report["final_validation_loss"] == pytest.approx(min(run["best_validation"] for run in runs))
    quality = report["quality"]
    assert quality["verdict"] == "poor" and quality["loss_ratio"] > quality["poor_loss_ratio"]
    assert quality["loss_ratio"] == pytest.approx(report["final_validation_loss"] / quality["hold_loss"])


def test_a_plateau_near_the_floor_is_convergence(data):
    _, report = train(data, SMALL, stalling(poor_loss_ratio=10.0), progress=False)
    assert report["restarts"] == 0 and report["iterations"] == 3 and "did not improve" in report["stopped"]
    assert report["quality"]["verdict"] == "good"


def test_without_a_verdict_every_plateau_ends_training(data):
    _, report = train(data, SMALL, stalling(poor_loss_ratio=None), progress=False)
    assert report["restarts"] == 0 and report["iterations"] == 3
    assert report["quality"]["verdict"] == "unknown"


def test_continued_training_is_not_restarted_from_the_same_weights(data):
    from fvin_mpc.learning.model import model_for

    start = model_for(SMALL, seed=7).numpy_weights()
    _, report = train(data, SMALL, stalling(), progress=False,
                      model_factory=lambda config, seed: model_for(config, start, seed))
    assert report["restarts"] == 0 and report["iterations"] == 3


def test_the_cli_says_a_poor_model_is_poor_in_one_line_and_in_the_checkpoint(tmp_path, monkeypatch, capsys, data):
    from fvin_mpc.core.checkpoint import load_checkpoint
    from fvin_mpc.train import main

    monkeypatch.chdir(tmp_path)
    path = save_data(tmp_path / "d.npz", data)
    assert main(["--data", str(path), "--out", str(tmp_path / "poor"), "--iterations", "2", "--hidden-width", "4",
                 "--window", "3", "--quiet", "--threads", "1"]) == 0
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if "warning" in line]
    assert len(lines) == 1 and lines[0].startswith("train: warning: the trained model is poor"), captured.err
    assert json.loads(captured.out)["quality"] == "poor"
    checkpoint = load_checkpoint(tmp_path / "poor")
    assert checkpoint_quality(checkpoint.metadata)["verdict"] == "poor"
    assert json.loads((tmp_path / "poor.json").read_text())["training"]["quality"]["verdict"] == "poor"
    # The same run judged against a lenient ratio is not poor: no warning.
    assert main(["--data", str(path), "--out", str(tmp_path / "lenient"), "--iterations", "2", "--hidden-width", "4",
                 "--window", "3", "--quiet", "--threads", "1", "--poor-loss-ratio", "10"]) == 0
    captured = capsys.readouterr()
    assert "warning" not in captured.err and json.loads(captured.out)["quality"] == "good"
    # `none` is the former rule: no verdict, no warning.
    assert main(["--data", str(path), "--out", str(tmp_path / "former"), "--iterations", "2", "--hidden-width", "4",
                 "--window", "3", "--quiet", "--threads", "1", "--poor-loss-ratio", "none"]) == 0
    captured = capsys.readouterr()
    assert "warning" not in captured.err and json.loads(captured.out)["quality"] == "unknown"


def test_checkpoints_without_a_verdict_still_load():
    from fvin_mpc.core.checkpoint import load_checkpoint

    checkpoint = load_checkpoint("pendulum_sign-invariant")  # shipped, trained before verdicts
    assert "quality" not in checkpoint.metadata.get("training", {})
    assert checkpoint_quality(checkpoint.metadata) is None
    assert checkpoint_quality({}) is None and checkpoint_quality({"training": {"quality": "x"}}) is None
    assert np.all(np.isfinite(np.asarray(checkpoint.weights["potential_w0"])))
