"""The data-efficiency study (fvin_mpc.studies.data_efficiency): its training sets are whole
trajectories of the pool, nested per draw; its headline logic; and its --quick path end to end
through the bench CLI (resumable from its per-cell cache)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fvin_mpc.studies import data_efficiency as study


@pytest.fixture(scope="module")
def pool():
    from fvin_mpc.learning.collection import collect

    return collect("pendulum", trajectories=30, steps=10, seed=7, progress=False)


def test_subsets_are_whole_trajectories_of_the_pool_and_nested(pool):
    small = study.training_subset(pool, 50, draw=0, seed=0)
    large = study.training_subset(pool, 120, draw=0, seed=0)
    assert small.num_transitions == 50 and small.num_trajectories == 5
    assert large.num_transitions == 120

    def rows_in_pool(subset):
        return [int(np.flatnonzero(np.all(pool.q == q, axis=(1, 2)))[0]) for q in subset.q]

    small_rows, large_rows = rows_in_pool(small), rows_in_pool(large)
    for subset, rows in ((small, small_rows), (large, large_rows)):
        np.testing.assert_array_equal(subset.u, pool.u[rows])
        np.testing.assert_array_equal(subset.omega, pool.omega[rows])
    assert set(small_rows) <= set(large_rows)
    other = study.training_subset(pool, 50, draw=1, seed=0)
    assert not np.array_equal(other.q, small.q)
    with pytest.raises(ValueError):
        study.training_subset(pool, 55, draw=0, seed=0)
    with pytest.raises(ValueError):
        study.training_subset(pool, 310, draw=0, seed=0)


def test_config_rejects_unknown_models_and_partial_trajectories():
    with pytest.raises(ValueError):
        study.StudyConfig(sizes=(100,), draws=(0,), models=("resnet",))
    with pytest.raises(ValueError):
        study.StudyConfig(sizes=(105,), draws=(0,), models=("mlp",))


def test_headline_counts_from_where_it_holds_at_every_larger_size():
    def row(size, succeed, within):
        return {"model": "m", "transitions": size, "all_succeed": succeed, "cost_within_2pct_all_seeds": within}

    rows = [row(250, True, False), row(500, False, False), row(1000, True, True), row(2000, True, False),
            row(5000, True, True), {"model": study.CLOSED_FORM, "transitions": None}]
    best = study.headline(rows)["m"]
    assert best == {"full_success_from": 1000, "full_success_first": 250,
                    "cost_within_2pct_from": 5000, "cost_within_2pct_first": 1000}
    assert study.headline([row(250, False, False)])["m"]["full_success_from"] is None


def test_quick_study_via_the_bench_cli_and_resumes_from_its_cache(tmp_path, monkeypatch):
    from fvin_mpc.bench.__main__ import main
    from fvin_mpc.studies import pendulum_v1

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("FVIN_MPC_CACHE", str(tmp_path / "casadi"))
    monkeypatch.setattr(pendulum_v1, "EPISODE_STEPS", 4)  # a few Pendulum-v1 steps keep the test short
    argv = ["data-efficiency", "--quick", "--sizes", "20,40", "--out-dir", "out", "--cache-dir", "cache"]
    assert main(argv) == 0
    report = json.loads((tmp_path / "out" / "data-efficiency.json").read_text())
    assert (tmp_path / "out" / "data-efficiency.png").stat().st_size > 0
    rows = report["rows"]
    assert {(r["model"], r["transitions"]) for r in rows} == {("sign-invariant", 20), ("sign-invariant", 40),
                                                             ("mlp", 20), ("mlp", 40), ("closed-form", None)}
    closed_form = next(r for r in rows if r["model"] == "closed-form")
    learned = [r for r in rows if r["model"] != "closed-form"]
    # The exact rod predicts far better than models trained for two iterations on 20-40 transitions.
    assert closed_form["angle_error_1s_rad"] < min(r["angle_error_1s_rad"] for r in learned)
    for r in rows:
        assert np.isfinite(r["cost_mean"]) and r["v1_return_mean"] < 0
    cells = sorted((tmp_path / "cache" / "quick" / "cells").glob("*.json"))
    assert len(cells) == 5
    stamps = [c.stat().st_mtime_ns for c in cells]
    assert main(argv) == 0  # everything from the cache: no cell is rewritten
    assert [c.stat().st_mtime_ns for c in cells] == stamps
    assert json.loads((tmp_path / "out" / "data-efficiency.json").read_text())["rows"] == rows
    # --cached-only reports a partial grid: the uncached size is listed as not run, nothing is computed.
    assert main([*argv[:3], "20,40,60", *argv[4:], "--cached-only"]) == 0
    partial = json.loads((tmp_path / "out" / "data-efficiency.json").read_text())
    assert partial["rows"] == rows
    assert any("sign-invariant_n60_r0" in note and "mlp_n60_r0" in note for note in partial["notes"])
    assert not (tmp_path / "cache" / "quick" / "cells" / "mlp_n60_r0.json").exists()


def test_budgeted_controller_gives_up_with_zero_torque_once_its_budget_is_spent():
    import time

    class Slow:
        resets = 0

        def reset(self):
            Slow.resets += 1

        def __call__(self, x):
            time.sleep(0.02)
            return np.array([1.5]), {"success": True}

    controller = study.BudgetedController(Slow(), control_dim=1, budget_s=0.05)
    controller.reset()
    outputs = [controller(np.zeros(7)) for _ in range(6)]
    assert [float(u[0]) for u, _ in outputs[:3]] == [1.5, 1.5, 1.5]
    u, info = outputs[-1]
    assert float(u[0]) == 0.0 and info == {"success": False, "fallback": "budget"} and controller.exhausted
    controller.reset()
    assert not controller.exhausted and float(controller(np.zeros(7))[0][0]) == 1.5 and Slow.resets == 2
