"""The scene-families benchmark's small version (benchmarks/scene_families.py --quick): three generated
scenes through collect → train → build → learned beside closed-form episodes, cached and resumed."""

import json


def test_the_quick_benchmark_runs_three_scenes_and_resumes_from_its_cache(tmp_path):
    from benchmarks.scene_families import main

    args = [
        "--quick",
        "--scenes",
        "3",
        "--starts",
        "1",
        "--out-dir",
        str(tmp_path / "docs"),
        "--cache-dir",
        str(tmp_path / "cache"),
    ]
    assert main(args) == 0
    cached = sorted((tmp_path / "cache" / "hinge" / "quick" / "rti-none").glob("scene_*.json"))
    assert len(cached) == 3
    record = json.loads(cached[0].read_text())
    assert {"collect_s", "train_s", "build_s", "learned", "closed_form", "facts"} <= set(record)
    assert record["learned"][0]["deadline_misses"] == "not measured"  # waiting mode
    report = (tmp_path / "docs" / "scene-families.md").read_text()
    assert "python -m benchmarks.scene_families --quick" in report and "waits for the controller" in report
    assert (tmp_path / "docs" / "scene-families.png").stat().st_size > 0
    stamps = [p.stat().st_mtime_ns for p in cached]
    assert main(args) == 0  # resumes: every scene read back from the cache, none rerun
    assert [p.stat().st_mtime_ns for p in cached] == stamps
