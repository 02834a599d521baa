"""Learning in the loop (fvin_mpc/studies/learning_loop.py, ``python -m fvin_mpc.learn``): a small
end-to-end run on a tiny budget, its counting checked against the data it saved, the evaluation starts
kept out of the training data, and the final checkpoint an ordinary one."""

import json
from pathlib import Path

import numpy as np
import pytest

from fvin_mpc.studies.learning_loop import Exploring, LoopSettings, episode_segments

WEAK = str(Path(__file__).parent / "data" / "weak_damped_point_pendulum.xml")
#: A tiny, uncompiled controller (the test's speed, not the loop's defaults).
TINY_MPC = {"horizon": 5, "compile": "none", "cold_starts": ("rollout+",)}


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    from fvin_mpc.studies.learning_loop import run_loop, write_loop_report

    out = tmp_path_factory.mktemp("learn")
    settings = LoopSettings(budget=100, excitation_trajectories=3, segment_steps=10, explore_episodes=2,
                            explore_segments=2, evaluation_starts=2, evaluation_duration_s=0.3, max_rounds=2,
                            train_iterations=2, seed=3, mpc=TINY_MPC)
    result = run_loop(WEAK, settings, out, progress=False)
    write_loop_report(result, out, "python -m fvin_mpc.learn (the test's settings)")
    return out, result


def test_every_reported_transition_is_in_the_saved_data_and_no_other(tiny_run):
    from fvin_mpc.core.data import load_data

    out, result = tiny_run
    data = load_data(out / "data.npz")
    rounds = result["rounds"]
    assert len(rounds) == 3  # round 0 and two exploring rounds: the tiny model never swings up
    assert result["training_transitions"] == rounds[-1]["transitions"] == data.num_transitions
    # 3 × 10 excitation, then 2 episodes × 2 segments × 10 per round: 30, 70, 100 (the budget cuts the last)
    assert [r["transitions"] for r in rounds] == [30, 70, 100]
    assert [r["excitation_transitions"] for r in rounds] == [30, 30, 30]
    assert [r["closed_loop_transitions"] for r in rounds] == [0, 40, 70]
    # Round 0 starts from the initialization; later rounds keep whichever start trained to the lower loss.
    assert rounds[0]["trained_from"] == "initial" and {r["trained_from"] for r in rounds[1:]} <= {"initial", "previous"}
    assert data.metadata["excitation_transitions"] + data.metadata["closed_loop_transitions"] == 100
    # evaluation: 2 starts × 0.3 s at the scene's control period per round, counted apart and never trained on
    per_round = 2 * round(0.3 / data.control_period)
    assert [r["evaluation_transitions"] for r in rounds] == [per_round, 2 * per_round, 3 * per_round] == [
        sum(e["periods"] for r2 in rounds[: i + 1] for e in r2["learned"]) for i in range(3)]
    for i, r in enumerate(rounds):
        assert load_data(out / "data.npz").num_transitions >= r["transitions"]
        assert json.loads((out / f"round_{i}.json").read_text())["data"]["transitions"] == r["transitions"]


def test_the_evaluation_starts_are_not_in_the_training_data(tiny_run):
    from fvin_mpc.core.data import load_data

    out, result = tiny_run
    states = load_data(out / "data.npz").state.reshape(-1, 7)
    starts = np.array([e["initial_state"] for e in result["closed_form"]["episodes"]])
    assert np.array_equal(starts, np.array([e["initial_state"] for e in result["rounds"][-1]["learned"]]))
    distance = np.linalg.norm(states[:, None, :] - starts[None], axis=-1).min()
    assert distance > 1e-3


def test_the_final_checkpoint_is_an_ordinary_one_the_swingup_command_loads(tiny_run):
    from fvin_mpc.control.scene import scene_env, scene_model

    out, result = tiny_run
    assert Path(result["final_checkpoint"]) == out / "final"
    final = json.loads((out / "final.json").read_text())
    last = json.loads((out / "round_2.json").read_text())
    assert final["weights_sha256"] == last["weights_sha256"]
    env = scene_env(WEAK, checkpoint=str(out / "final"))  # what swingup --checkpoint builds its model from
    assert scene_model(env, str(out / "final")).step_size == env.unwrapped.dt
    report = (out / "learn.md").read_text()
    assert "python -m fvin_mpc.learn" in report and "not trained on" in report
    assert (out / "learn.png").stat().st_size > 0


@pytest.fixture(scope="module")
def tiny_flight(tmp_path_factory):
    """The loop on the built-in quadrotor with a tiny budget (uncompiled, short horizon): the free body's
    task, collector and counting."""
    from fvin_mpc.studies.learning_loop import run_loop

    out = tmp_path_factory.mktemp("learn_flight")
    settings = LoopSettings(budget=60, excitation_trajectories=3, segment_steps=10, explore_episodes=1,
                            explore_segments=3, evaluation_starts=2, evaluation_duration_s=0.2, max_rounds=1,
                            train_iterations=1, seed=5, mpc={"horizon": 5, "compile": "none"})
    return out, run_loop("quadrotor", settings, out, progress=False)


def test_a_free_body_runs_flys_recovery_task_and_counts_its_bursts(tiny_flight):
    from fvin_mpc.control.flight import quadrotor_model
    from fvin_mpc.core.data import load_data
    from fvin_mpc.learning.free_body_excitation import EXCITATION
    from fvin_mpc.studies.flight_report import make_env

    out, result = tiny_flight
    data = load_data(out / "data.npz")
    assert result["task"] == "recovery" and result["success_key"] == "recovered"
    assert data.metadata["collector"] == EXCITATION  # the MJCF's bursts, no closed-form pilot
    assert [r["transitions"] for r in result["rounds"]] == [30, 60] == [30, data.num_transitions]
    assert [r["closed_loop_transitions"] for r in result["rounds"]] == [0, 30]
    assert data.state.shape[-1] == 13
    # fly's starts, never trained on: upside down at rest first
    starts = np.array([e["initial_state"] for e in result["closed_form"]["episodes"]])
    np.testing.assert_allclose(starts[0, 3:7], [0.0, 1.0, 0.0, 0.0], atol=1e-12)
    assert np.linalg.norm(data.state.reshape(-1, 13)[:, None, :] - starts[None], axis=-1).min() > 1e-3
    assert all("recovered" in e for e in result["rounds"][-1]["learned"])
    env = make_env()  # the final checkpoint is an ordinary one fly loads
    assert quadrotor_model(env, str(out / "final")).step_size == env.unwrapped.dt


def test_a_free_body_takes_its_own_defaults_and_refuses_a_pivoted_collector():
    from fvin_mpc.studies.learning_loop import FREE_BODY_DEFAULTS

    filled = LoopSettings().for_scene(pivoted=False)
    assert (filled.budget, filled.excitation, filled.excitation_trajectories) == (
        FREE_BODY_DEFAULTS["budget"], "bursts", FREE_BODY_DEFAULTS["excitation_trajectories"])
    assert LoopSettings().for_scene(pivoted=True).excitation == "swings"
    with pytest.raises(ValueError, match="free body's excitation"):
        LoopSettings(excitation="swings").for_scene(pivoted=False)
    with pytest.raises(ValueError, match="pivoted body's excitation"):
        LoopSettings(excitation="bursts").for_scene(pivoted=True)


def test_settings_refuse_an_excitation_batch_over_the_budget_and_a_cost_tolerance_below_one():
    with pytest.raises(ValueError, match="larger than the budget"):
        LoopSettings(budget=100, excitation_trajectories=20, segment_steps=20)
    with pytest.raises(ValueError, match="cost_tolerance"):
        LoopSettings(cost_tolerance=0.9)


def test_episodes_are_cut_into_whole_trajectories_and_the_tail_dropped():
    states, controls = np.arange(26 * 7.0).reshape(26, 7), np.arange(25.0).reshape(25, 1)
    state, u = episode_segments(states, controls, 10)
    assert state.shape == (2, 11, 7) and u.shape == (2, 10, 1)
    assert np.array_equal(state[1, 0], states[10]) and np.array_equal(state[0, -1], states[10])
    assert np.array_equal(u.reshape(-1), controls[:20, 0])


def test_exploration_noise_is_held_and_clipped_to_the_bounds():
    class Constant:
        def __call__(self, x):
            return np.array([0.9]), {}

        def reset(self):
            pass

    exploring = Exploring(Constant(), np.array([-1.0]), np.array([1.0]), 0.5, 3, np.random.default_rng(0))
    u = np.array([exploring(None)[0][0] for _ in range(9)])
    assert np.all(u <= 1.0) and np.all(u >= 0.4)
    assert len(set(u[:3])) == 1 and len(set(u[3:6])) == 1
