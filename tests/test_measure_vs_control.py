"""The measure-vs-control study's arithmetic: outcomes per model and rank correlations within and across scenes."""

from __future__ import annotations

import math

import pytest

from benchmarks.measure_vs_control import correlations, outcomes


def _episode(up: bool, cost: float) -> dict:
    return {"swung_up": up, "cost": cost}


def test_outcomes_are_the_median_cost_ratio_and_the_share_of_the_closed_forms_successes_missed():
    closed = [_episode(True, 10.0), _episode(True, 20.0), _episode(False, 40.0), _episode(True, 10.0)]
    learned = [_episode(True, 10.0), _episode(False, 60.0), _episode(True, 40.0), _episode(True, 30.0)]
    result = outcomes(learned, closed)
    assert result["cost_ratio"] == pytest.approx(2.0)  # median of 1, 3, 1, 3
    assert result["missed_share"] == pytest.approx(1 / 3)  # one of the closed form's three successes
    assert (result["learned_up"], result["closed_up"]) == (3, 3)
    assert math.isnan(outcomes(learned, [_episode(False, 1.0)] * 4)["missed_share"])


def test_a_predictor_ranked_like_the_cost_within_each_scene_correlates_there_and_not_necessarily_pooled():
    rows = []
    for seed, offset in ((1, 0.0), (2, 10.0)):  # scene 2's numbers are all larger: pooled ranks mix scenes
        for k in range(4):
            rows.append({"seed": seed, "measure": offset + k, "validation": offset + 3 - k,
                         "cost_ratio": 1.0 + k + (0.0 if seed == 1 else -3.5), "missed_share": 0.0})
    result = correlations(rows)
    assert result["measure_vs_cost_ratio"]["within_mean"] == pytest.approx(1.0)
    assert result["measure_vs_cost_ratio"]["within_scenes"] == 2
    assert result["validation_vs_cost_ratio"]["within_mean"] == pytest.approx(-1.0)
    assert result["measure_vs_cost_ratio"]["pooled"] < 1.0  # scene 2's costs sit below scene 1's
    # A constant outcome defines no correlation: not a zero, not a scene counted.
    assert result["measure_vs_missed_share"] == {"within_mean": None, "within_scenes": 0, "pooled": None}
