import json

import pytest

from guidedmatch.testing.data import OXFORD_FILES, PHOTO_FILES, STRECHA_FILES, needs_data


@pytest.mark.data
@pytest.mark.slow
@needs_data(*OXFORD_FILES, *STRECHA_FILES, *PHOTO_FILES)
def test_bench_quick_writes_report_json_and_figures(tmp_path):
    from guidedmatch.cli import main

    rc = main(["bench", "all", "--quick", "--out", str(tmp_path)])
    assert rc == 0
    report = (tmp_path / "report.md").read_text()
    for section in ("## Oxford", "## Synthetic sets", "## Real high-resolution pairs", "## Alignment simulation"):
        assert section in report
    assert "paper: SO+EPI+IA" in report  # the paper's numbers sit next to ours
    res = json.loads((tmp_path / "results.json").read_text())
    assert res["meta"]["numpy"] and res["quick"] is True
    ox = res["oxford"]
    assert len(ox) == 3
    for row in ox:
        bf, g = row["methods"]["bf"], row["methods"]["so+epi+ia"]
        assert bf["comparisons"] == row["n1"] * row["n2"]
        assert 0 < g["comparisons"] < bf["comparisons"]
        assert 0 <= g["true"] <= g["matches"]
    assert all(len(v) == 1 for v in res["synthetic"].values())
    assert "ransac_precision" in res["real"][0]["methods"]["so+epi+ia"]
    assert (tmp_path / "alignment" / "alignment_ratio.png").exists()
    assert any(p.name.startswith("motion_") for p in tmp_path.glob("*.png"))


def test_bench_without_data_is_a_clean_error(tmp_path, capsys):
    from guidedmatch.cli import main

    rc = main(["bench", "oxford", "--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")])
    assert rc == 2
    err = capsys.readouterr().err
    assert "guidedmatch: error: no evaluation data" in err and "nowhere" in err
    assert not (tmp_path / "o").exists()  # checked before any work


def test_summary_table_sums_like_the_paper():
    from guidedmatch.evaluation.bench import summary_table

    rows = [dict(methods=dict(bf=dict(comparisons=100, matches=10, true=5, time_s=1.0),
                              **{"so+epi+ia": dict(comparisons=10, matches=8, true=6, time_s=0.5)})),
            dict(methods=dict(bf=dict(comparisons=300, matches=30, true=25, time_s=3.0),
                              **{"so+epi+ia": dict(comparisons=20, matches=22, true=20, time_s=0.5)}))]
    t = summary_table(rows, ["bf", "so+epi+ia"])
    assert "| BF | 400 | 100.00% | 40 | 30 | 75.00% | 4.00 | 1.00 |" in t
    assert "| SO+EPI+IA | 30 | 7.50% | 30 | 26 | 86.67% | 1.00 | 0.25 |" in t


def test_bench_unwritable_out_is_a_clean_error(tmp_path, capsys):
    from guidedmatch.cli import main

    (tmp_path / "file").write_text("x")
    assert main(["bench", "alignment", "--out", str(tmp_path / "file" / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"guidedmatch: error: cannot write --out {tmp_path / 'file' / 'o'}: ") and "probe" not in err
