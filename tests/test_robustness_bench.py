"""benchmarks/robustness.py: a small run writes its report from cached cells, and a second run resumes."""

from __future__ import annotations

import json

import pytest

from benchmarks import robustness


def test_small_run_reports_every_cell_and_resumes_from_the_cache(tmp_path, capsys):
    argv = ["--scenes", "pendulum", "--starts", "2", "--duration", "4", "--knock-extra", "2", "--latency", "none",
            "--conditions", "nominal", "delay-1-period", "knock-2", "--controllers", "energy-learned", "energy-true",
            "--cache-dir", str(tmp_path / "cache"), "--out-dir", str(tmp_path / "docs")]
    assert robustness.main(argv) == 0
    report = json.loads((tmp_path / "docs" / "robustness.json").read_text())
    assert set(report["per_start"]) == {f"pendulum/{c}/{n}" for c in ("nominal", "delay-1-period", "knock-2")
                                        for n in ("energy-learned", "energy-true")}
    for key, cell in report["per_start"].items():
        assert len(cell["swung_up"]) == 2 and report["summary"][key]["success_pct"] in (0.0, 50.0, 100.0)
    cells = [json.loads(path.read_text()) for path in (tmp_path / "cache").rglob("*.json")]
    assert len(cells) == 6
    for cell in cells:
        assert [e["start"] for e in cell["episodes"]] == [0, 1]
        assert cell["duration_s"] == (6.0 if cell["condition"] == "knock-2" else 4.0)
    text = (tmp_path / "docs" / "robustness.md").read_text()
    assert "waiting mode" in text and "python -m benchmarks.robustness" in text
    cached = {path.name: path.stat().st_mtime_ns for path in (tmp_path / "cache").rglob("*.json")}
    capsys.readouterr()
    assert robustness.main(argv) == 0  # everything from the cache: nothing rerun
    assert {path.name: path.stat().st_mtime_ns for path in (tmp_path / "cache").rglob("*.json")} == cached
    assert " up (" not in capsys.readouterr().err


def test_unknown_scene_is_refused_in_one_line(capsys):
    with pytest.raises(SystemExit):
        robustness.build_parser().parse_args(["--conditions", "rain"])
    assert robustness.run_command(robustness.main, ["--scenes", "quadrotor"]) == 2
    assert "built-in pivoted scenes" in capsys.readouterr().err
