"""The data-efficiency study (benchmarks.data_efficiency): its training sets are whole
trajectories of the pool, nested per draw; its headline logic; and its --quick path end to end
through the bench CLI (resumable from its per-cell cache)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from benchmarks import data_efficiency as study


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
    with pytest.raises(ValueError):
        study.StudyConfig(sizes=(100,), draws=(0,), models=("mlp",), episode_budget_s=0.0)


def test_episode_budget_reaches_the_config_and_separates_the_cells(tmp_path):
    def config(**budget):
        return study.study_config(
            False, 0, "250", "3", "sign-invariant", 8, 0, tmp_path, "cached", 10.0, 20000, **budget
        )

    default, unbounded = config(), config(episode_budget=1000.0)
    assert default.episode_budget_s == study.EPISODE_BUDGET_S and unbounded.episode_budget_s == 1000.0
    assert "episode_budget_s" not in default.evaluation_fingerprint()  # the cells cached before the option stay valid
    assert unbounded.evaluation_fingerprint()["episode_budget_s"] == 1000.0
    assert unbounded.training_fingerprint() == default.training_fingerprint()  # the same trained models


def test_torque_reserve_reaches_both_mpcs_and_separates_the_cells(tmp_path):
    def config(**reserve):
        return study.study_config(
            False, 0, "250", "3", "sign-invariant", 8, 0, tmp_path, "cached", 10.0, 20000, **reserve
        )

    default, reserved = config(), config(torque_reserve=0.05)
    assert "mpc_overrides" not in default.evaluation_fingerprint()  # the cells cached before the option stay valid
    assert reserved.evaluation_fingerprint()["mpc_overrides"] == [["torque_reserve", 0.05]]
    assert reserved.training_fingerprint() == default.training_fingerprint()
    assert dict(reserved.mpc_overrides)["torque_reserve"] == 0.05  # closed_loop and pendulum_v1_returns apply these
    with pytest.raises(ValueError, match="torque-reserve"):
        study.run(torque_reserve=1.5, cache_dir=tmp_path)


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
    from benchmarks import pendulum_v1_mpc as pendulum_v1
    from benchmarks.__main__ import main

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
    # --report-suffix writes a report beside the main one
    assert main([*argv, "--cached-only", "--report-suffix", "extra"]) == 0
    assert json.loads((tmp_path / "out" / "data-efficiency.extra.json").read_text())["rows"] == rows
    assert (tmp_path / "out" / "data-efficiency.extra.png").exists()
    assert json.loads((tmp_path / "out" / "data-efficiency.json").read_text()) == partial
    # data-efficiency-terms reads the same cells (and one plain cell more) without computing any
    assert main(["data-efficiency", "--quick", "--sizes", "20", "--models", "plain", "--out-dir", "out",
                 "--cache-dir", "cache"]) == 0
    assert (
        main(["data-efficiency-terms", "--quick", "--sizes", "20,40", "--out-dir", "out", "--cache-dir", "cache"]) == 0
    )
    terms = json.loads((tmp_path / "out" / "data-efficiency-terms.json").read_text())
    by_cell = {(r["model"], r["transitions"]): r for r in terms["rows"]}
    assert set(by_cell) == {("sign-invariant", 20), ("sign-invariant", 40), ("plain", 20)}
    assert any("plain_n40_r0" in note and "fixed-inertia_n20_r0" in note for note in terms["notes"])
    for key in ("potential", "inertia", "gain"):
        for size in (20, 40):  # averaged over ±q: the two hemispheres agree by construction
            row = by_cell[("sign-invariant", size)]
            assert row[f"{key}_err_minus_q"] == pytest.approx(row[f"{key}_err_q"], rel=1e-9, abs=1e-12)
    plain = by_cell[("plain", 20)]
    assert plain["potential_err_minus_q"] != pytest.approx(plain["potential_err_q"], rel=1e-6)
    for row in terms["rows"]:
        assert 0.0 <= row["other_hemisphere_share"] <= 1.0 and row["scale"] != 0.0
        assert all(0 <= start < 1 for start in row["costly_starts"])  # the quick path runs one start
    # --trace replays an episode: per period the angle, the torque and the plan's closest approach,
    # which can be no farther than the measured state (the plan's first state)
    assert main(["data-efficiency-terms", "--quick", "--trace", "sign-invariant_n20_r0:0,closed-form:0",
                 "--out-dir", "out", "--cache-dir", "cache"]) == 0
    trace = json.loads((tmp_path / "out" / "data-efficiency-trace.json").read_text())["rows"]
    assert {r["cell"] for r in trace} == {"sign-invariant_n20_r0", "closed-form"}
    assert sum(r["cell"] == "closed-form" for r in trace) == 20  # the quick episode: 1 s of 0.05 s periods
    for r in trace:
        assert 0.0 <= r["plan_closest_rad"] <= r["angle_from_upright_rad"] + 1e-9 <= np.pi + 1e-9
        assert abs(r["u"]) <= 2.0 + 1e-9
    # a name that is no trained model, or no CELL:START: refused with the reason (exit status 2)
    assert main(["data-efficiency-terms", "--quick", "--trace", "plain_n99_r0:0", "--cache-dir", "cache"]) == 2
    assert main(["data-efficiency-terms", "--quick", "--trace", "closed-form", "--cache-dir", "cache"]) == 2


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


def test_headline_per_draw_claims_come_from_each_draw_alone():
    def row(size, draws):  # draws: (draw, successes, episodes, cost excess %)
        seeds = [{"draw": d, "successes": s, "episodes": e, "cost_excess_pct": x} for d, s, e, x in draws]
        return {"model": "m", "transitions": size, "per_seed": seeds,
                "all_succeed": all(s == e for _, s, e, _ in draws),
                "cost_within_2pct_all_seeds": max(x for *_, x in draws) <= 2.0}

    rows = [row(100, [(0, 7, 8, 50.0), (1, 8, 8, 1.5)]),
            row(250, [(0, 8, 8, 0.4), (1, 8, 8, 19.9), (2, 8, 8, 2.5)]),
            row(500, [(0, 8, 8, 0.05), (1, 8, 8, 0.09), (2, 8, 8, 1.0)]),
            row(1000, [(0, 8, 8, 0.08), (1, 8, 8, 11.0)]),
            {"model": study.CLOSED_FORM, "transitions": None}]
    best = study.headline(rows)["m"]
    assert best["full_success_from"] == 250 and best["cost_within_2pct_first"] == 500
    assert best["per_draw"][0] == {"sizes": [100, 250, 500, 1000], "full_success_from": 250, "full_success_first": 250,
                                   "cost_within_2pct_from": 250, "cost_within_2pct_first": 250}
    assert best["per_draw"][1] == {"sizes": [100, 250, 500, 1000], "full_success_from": 100, "full_success_first": 100,
                                   "cost_within_2pct_from": None, "cost_within_2pct_first": 100}
    # draw 2 was run at 250 and 500 only: its claims count over those sizes
    assert best["per_draw"][2] == {"sizes": [250, 500], "full_success_from": 250, "full_success_first": 250,
                                   "cost_within_2pct_from": 500, "cost_within_2pct_first": 500}
    # rows without per-draw figures (the closed form, older reports) give no per_draw entry
    assert "per_draw" not in study.headline([{"model": "m", "transitions": 10, "all_succeed": True,
                                              "cost_within_2pct_all_seeds": True}])["m"]


def test_a_cell_made_with_other_settings_is_never_overwritten(tmp_path):
    cells = tmp_path / "cells"
    cells.mkdir()
    assert study.cell_path(cells, "m_n250_r0", "aaaa") == cells / "m_n250_r0.json"  # nothing there yet
    (cells / "m_n250_r0.json").write_text(json.dumps({"key": "aaaa"}))
    assert study.cell_path(cells, "m_n250_r0", "aaaa") == cells / "m_n250_r0.json"
    assert study.cell_path(cells, "m_n250_r0", "bbbb") == cells / "m_n250_r0@bbbb.json"


def _fake_trained_cell(config, model, name, training, *, cell_name=None, write_cell_after_weights=True):
    """Model files at ``models/<name>`` and a cached cell ``cells/<cell_name or name>.json`` recording ``training``."""
    import os

    stem = config.cache_dir / "models" / name
    stem.parent.mkdir(parents=True, exist_ok=True)
    weights, sidecar = study.model_files(model, stem)
    weights.write_bytes(b"weights")
    sidecar.write_text("{}")
    cell = config.cache_dir / "cells" / f"{cell_name or name}.json"
    cell.parent.mkdir(parents=True, exist_ok=True)
    cell.write_text(json.dumps({"key": "k", "fingerprint": {"training": config.training_fingerprint()},
                                "training": training}))
    when = weights.stat().st_mtime + (10 if write_cell_after_weights else -10)
    os.utime(cell, (when, when))
    return stem


def test_trained_models_are_reused_only_when_training_settings_and_weights_match(tmp_path):
    config = study.StudyConfig(sizes=(250,), draws=(0,), models=("sign-invariant", "mlp"), cache_dir=tmp_path)
    stem = _fake_trained_cell(config, "sign-invariant", "sign-invariant_n250_r0", {"iterations": 7})
    assert study.trained_before("sign-invariant", 250, 0, config, stem) == {"iterations": 7}  # older cell: by date
    assert study.trained_before("sign-invariant", 250, 0, replace(config, jacobian_windows=8), stem) is None
    assert (
        study.trained_before("sign-invariant", 500, 0, config, tmp_path / "models" / "sign-invariant_n500_r0") is None
    )
    # weights newer than the cell that recorded them (retrained since, say by an aborted run): not reused
    stem = _fake_trained_cell(config, "sign-invariant", "sign-invariant_n250_r1", {"iterations": 3},
                              write_cell_after_weights=False)
    assert study.trained_before("sign-invariant", 250, 1, config, stem) is None
    # a recorded digest decides, whatever the dates
    digest = study.weights_digest("sign-invariant", stem)
    stem = _fake_trained_cell(
        config,
        "sign-invariant",
        "sign-invariant_n250_r1",
        {"iterations": 3, "weights_sha256": digest},
        write_cell_after_weights=False,
    )
    assert study.trained_before("sign-invariant", 250, 1, config, stem)["iterations"] == 3
    study.model_files("sign-invariant", stem)[0].write_bytes(b"other weights")
    assert study.trained_before("sign-invariant", 250, 1, config, stem) is None
    # the MLP's weights are found through its exact-Hessian twin's cell too
    stem = _fake_trained_cell(config, "mlp", "mlp_n250_r0", {"iterations": 60}, cell_name="mlp-exact-hessian_n250_r0")
    assert study.trained_before("mlp", 250, 0, config, stem) == {"iterations": 60}
    assert study.trained_before("fixed-inertia", 250, 0, config, tmp_path / "models" / "fixed-inertia_n250_r0") is None


def test_report_suffix_names_the_report_and_is_checked():
    with pytest.raises(ValueError):
        study.run(report_suffix="../x")
