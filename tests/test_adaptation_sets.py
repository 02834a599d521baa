"""benchmarks/adaptation_sets.py on a tiny workload: every set is fitted and the weaker motor is found."""

from __future__ import annotations

import json

import pytest

from benchmarks import adaptation_sets


def test_tiny_run_finds_the_weaker_motor(tmp_path):
    argv = ["--scenes", "pendulum", "--changes", "motor 70%", "--windows", "1", "--iterations", "6",
            "--out-dir", str(tmp_path)]
    assert adaptation_sets.main(argv) == 0
    rows = json.loads((tmp_path / "adaptation-sets.json").read_text())["rows"]
    assert {(row["model"], row["set"]) for row in rows} == {
        (model, name) for model in ("learned", "closed form") for name in adaptation_sets.SETS}
    gain = next(row for row in rows if row["model"] == "closed form" and row["set"] == "gain")
    assert gain["gain0 (median)"] == pytest.approx(0.7, abs=0.05)
    assert gain["held-out error / unfitted (median)"] < 1.0
    assert "python -m benchmarks.adaptation_sets" in (tmp_path / "adaptation-sets.md").read_text()
