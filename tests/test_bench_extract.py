"""bench_extract: tables, medians over rounds and the report files from synthetic rows (the runs themselves are the
benchmark's job)."""
from __future__ import annotations

import json

import pytest

from guidedmatch.evaluation import bench_extract as be


def _row(scene, option, total, auc1, r=0):
    return {"scene": scene, "option": option, "round": r, "extraction_s": total / 2, "extraction_cpu_s": total / 3,
            "matching_s": total / 4, "matching_cpu_s": 1.0, "mapping_s": total / 4, "mapping_cpu_s": 1.0,
            "total_s": total, "total_cpu_s": total / 3 + 2.0, "features_median": 8000.0, "registered": 8,
            "median_pose_error_deg": 0.2, "auc": {"1": auc1, "2": 0.9, "5": 0.95}}


def test_report_from_rows(tmp_path):
    pytest.importorskip("matplotlib")
    rows = [_row("p8", "colmap", t, 0.74, r) for r, t in enumerate((50.0, 40.0, 60.0))] + \
        [_row("p8", "opencv", t, 0.78, r) for r, t in enumerate((20.0, 10.0, 15.0))]
    mappers = [{"scene": "p8", "option": "opencv", "mapper": "global", "cap": 500, "inliers": 1000, "mapping_s": 3.0,
                "mapping_cpu_s": 2.0, "registered": 8, "points3D": 100, "median_pose_error_deg": 0.3,
                "auc": {"1": 0.7, "2": 0.8, "5": 0.9}},
               {"scene": "p8", "option": "opencv", "mapper": "incremental", "cap": 0, "error": "boom"}]
    res = {"meta": {"timestamp_utc": "t", "git_commit": "abc"}, "command": "c", "rows": rows, "mappers": mappers,
           "load_before_round": [1.0, 2.0]}
    be.write_report(res, tmp_path)
    md = (tmp_path / "extract.md").read_text()
    assert "| p8 | opencv + guidedmatch colmap |" in md and "15.0 (10.0-20.0, 3) | 0.30 |" in md   # 15 / 50
    assert "failed: boom" in md and (tmp_path / "extract.png").stat().st_size > 1000
    table = json.loads((tmp_path / "extract.json").read_text())["table"]
    assert [t["option"] for t in table] == ["colmap", "opencv"] and table[1]["runs"] == [20.0, 10.0, 15.0]
    out2 = tmp_path / "again"
    assert be.main(["--render", str(tmp_path / "extract.json"), "--out", str(out2)]) == 0
    assert (out2 / "extract.md").read_text() == md


def test_unknown_names_refused():
    from guidedmatch.errors import ConfigError

    with pytest.raises(ConfigError, match="nope"):
        be.main(["--options", "nope", "--data", "."])
