"""Learning in the loop (fvin_mpc/studies/learning_loop.py, ``python -m fvin_mpc.learn``): a small
end-to-end run on a tiny budget, its counting checked against the data it saved, the evaluation starts
kept out of the training data, and the final checkpoint an ordinary one."""

import json
from pathlib import Path

import numpy as np
import pytest

from fvin_mpc.studies.learning_loop import (
    DEFAULT_COST_TOLERANCE,
    Exploring,
    LoopSettings,
    best_round,
    episode_segments,
    within_cost,
)

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
    kept = json.loads((out / f"round_{result['final_round']}.json").read_text())
    assert final["weights_sha256"] == kept["weights_sha256"]
    assert result["final_round"] == best_round(result["rounds"])["round"]
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


def _round(index, success, up, cost):
    return {"round": index, "success": success, "learned_up": up, "cost_learned": cost}


def test_final_keeps_a_successful_round_over_a_cheaper_later_one_that_lost_a_start():
    rounds = [_round(0, False, 3, 900.0), _round(1, True, 5, 520.0), _round(2, False, 4, 480.0),
              _round(3, True, 5, 505.0)]
    assert best_round(rounds)["round"] == 3  # successful rounds first, then the lower cost
    assert best_round(rounds[:3])["round"] == 1
    assert best_round([_round(0, False, 2, 10.0), _round(1, False, 3, 99.0)])["round"] == 1  # more starts up


def test_the_default_stop_asks_for_the_closed_forms_cost_within_five_percent():
    assert LoopSettings().cost_tolerance == DEFAULT_COST_TOLERANCE == 1.05
    verdict = {"cost_learned": 1.07 * 4741.0, "cost_closed": 4741.0}  # the weak pendulum's first success
    assert not within_cost(verdict, DEFAULT_COST_TOLERANCE)
    assert within_cost(verdict, None) and within_cost(verdict, 1.08)
    assert within_cost({"cost_learned": 0.93, "cost_closed": 1.0}, DEFAULT_COST_TOLERANCE)


def test_a_successful_round_that_no_longer_lowers_the_cost_stops_the_loop(tmp_path, monkeypatch):
    """The stop rules on a scripted loop: success at 1.16× the closed form's cost explores on; a round 1.4 %
    cheaper (less than the 2 % gain) stops it, keeping the cheaper round; without success nothing stops."""
    from fvin_mpc.studies import learning_loop

    costs = iter([(True, 2120.0), (True, 2090.0), (True, 1000.0)])

    def fake_verdict(learned, closed, key="swung_up"):
        success, cost = next(costs)
        return {"learned_up": 5, "closed_up": 5, "starts": 5, "success": success, "cost_learned": cost,
                "cost_closed": 1825.0, "cost_ratio_median": None, "cost_ratio_worst": None}

    settings = LoopSettings(budget=100, excitation_trajectories=3, segment_steps=10, explore_episodes=1,
                            explore_segments=1, evaluation_starts=1, evaluation_duration_s=0.1, max_rounds=3,
                            train_iterations=1, seed=3, mpc=TINY_MPC)
    closed = {"closed_up": 5, "starts": 5, "cost_closed": 1825.0, "learned_up": 5, "success": True,
              "cost_learned": 1825.0, "cost_ratio_median": None, "cost_ratio_worst": None}
    # the closed form's own verdict (learned is closed) stays fixed; the learned rounds follow the script
    monkeypatch.setattr(learning_loop, "_verdict", lambda learned, c, key="swung_up": (
        closed if learned is c else fake_verdict(learned, c)))
    result = learning_loop.run_loop(WEAK, settings, tmp_path, progress=False)
    rounds = result["rounds"]
    assert [r["cost_plateau"] for r in rounds] == [False, True]
    assert [r["within_cost"] for r in rounds] == [False, False]
    assert result["outcome"] == "success" and result["final_round"] == 1
    assert result["transitions_to_success"] == rounds[0]["transitions"] and result["transitions_to_stop"] == 40
    with pytest.raises(ValueError, match="min_cost_gain"):
        LoopSettings(min_cost_gain=1.0)
