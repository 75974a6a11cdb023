"""The collection benchmark's report pieces that need no data: the workers' timeline."""
import matplotlib.image

from guidedmatch.evaluation.bench_collection import timeline_figure
from guidedmatch.plots import timeline_lanes


def _run(spans, wall, backend):
    return dict(spans=spans, wall_s=wall, summary=dict(backend=backend))


def test_lanes_give_every_worker_its_own_row_and_never_overlap_threads():
    spans = [["in-process", 0.5, 1.0], ["in-process", 0.5, 0.8], ["in-process", 0.8, 1.2], ["in-process", 1.0, 1.1]]
    lanes = timeline_lanes(spans)
    assert sorted(set(lanes)) == [0, 1]
    for lane in set(lanes):  # within a lane, the spans follow one another
        mine = sorted(s[1:] for s, k in zip(spans, lanes) if k == lane)
        assert all(a[1] <= b[0] for a, b in zip(mine, mine[1:]))
    workers = [["tcp://b", 0, 1], ["tcp://a", 0, 1], ["tcp://b", 1, 2]]
    assert timeline_lanes(workers) == [1, 0, 1]


def test_timeline_figure_draws_one_panel_per_logged_run(tmp_path):
    feats = dict(features_mean=11416.0)
    result = dict(note="test", sets=dict(default=dict(
        features=feats,
        ours=_run([["in-process", 0.5, 0.9], ["in-process", 0.5, 0.7], ["in-process", 0.7, 1.1]], 1.3, "in-process"),
        workers_1=_run([["tcp://a", 1.5, 2.0], ["tcp://a", 2.0, 2.6]], 2.9, "local-cluster"),
        workers_2=_run([["tcp://a", 1.4, 2.0], ["tcp://b", 1.4, 1.9]], 2.3, "local-cluster"),
        workers_0=dict(same_as="auto", spans=[["in-process", 0, 1]], wall_s=1.0, summary={}))))
    out = timeline_figure(result, tmp_path / "timeline.png")
    assert out == tmp_path / "timeline.png"
    img = matplotlib.image.imread(out)
    assert img.shape[0] > 300 and img.shape[1] > 800  # three panels (the "same as auto" run is not drawn twice)
    assert timeline_figure(dict(note="", sets=dict(default=dict(features=feats))), tmp_path / "none.png") is None
    assert not (tmp_path / "none.png").exists()


def test_collection_timeline_draws_this_runs_matched_pairs(tmp_path):
    from guidedmatch.plots import collection_timeline

    recs = [dict(status="done", worker="tcp://a", t_start=100.0, t_end=100.5),
            dict(status="done", worker="tcp://b", t_start=100.1, t_end=100.4),
            dict(status="failed", worker="tcp://b", t_start=100.4, t_end=100.6)]
    out = collection_timeline(tmp_path / "t.png", recs, title="local-cluster")
    assert out == tmp_path / "t.png" and matplotlib.image.imread(out).shape[1] > 500
    assert collection_timeline(tmp_path / "none.png", [dict(status="failed", reason="x")]) is None
    assert not (tmp_path / "none.png").exists()


def test_repeat_runs_alternate_the_order_and_report_medians(monkeypatch, tmp_path):
    from guidedmatch.evaluation import bench_collection as bc

    calls = []
    fake = {"colmap": 3.0, "ours": 1.5, "1": 12.0, "2": 8.0}

    def colmap_match(db):
        calls.append("colmap")
        return dict(wall_s=fake["colmap"] + len(calls) / 100, returncode=0)

    def ours(db, log, *extra):
        key = extra[-1] if extra else "ours"
        calls.append(key)
        return dict(wall_s=fake[key] + len(calls) / 100, returncode=0, stderr_tail=[])

    monkeypatch.setattr(bc, "colmap_match", colmap_match)
    monkeypatch.setattr(bc, "ours", ours)
    row = dict(colmap=dict(wall_s=3.3), ours=dict(wall_s=1.4), workers_1=dict(wall_s=12.5), workers_2=dict(wall_s=7.9))
    rep = bc._repeat_runs(row, 3, True, lambda tag: tmp_path / f"{tag}.db", tmp_path / "rep.jsonl")
    # round 1 reversed, round 2 in order: neither method always runs first
    assert calls == ["ours", "colmap", "2", "1", "colmap", "ours", "1", "2"]
    assert rep["colmap"]["walls"][0] == 3.3 and len(rep["colmap"]["walls"]) == 3
    assert rep["ours"]["median"] == sorted(rep["ours"]["walls"])[1]
    assert rep["workers_2"]["min"] == min(rep["workers_2"]["walls"]) and rep["workers_1"]["max"] == 12.5
    # one CPU entry and one 1-vs-2-worker accounting per round, round k against round k
    assert len(rep["ours"]["cpu"]) == 3 and len(rep["scaling_rounds"]) == 3
    assert [a["wall_2_s"] for a in rep["scaling_rounds"]] == rep["workers_2"]["walls"]
    # without scaling only COLMAP and ours repeat
    calls.clear()
    rep = bc._repeat_runs(row, 2, False, lambda tag: tmp_path / f"{tag}.db", tmp_path / "rep.jsonl")
    assert calls == ["ours", "colmap"] and set(rep) == {"colmap", "ours"}


def test_scaling_accounting_bounds_the_two_worker_time_from_its_cpu_time():
    from guidedmatch.evaluation.bench_collection import markdown, scaling_accounting

    w1 = dict(wall_s=10.0, cpu_s=11.0, summary=dict(load_s=0.5, image_loads=8),
              pair_match_s={"a b": 1.0, "a c": 1.0, "b c": 2.0})
    w2 = dict(wall_s=6.5, cpu_s=12.0, summary=dict(load_s=1.5, image_loads=15),
              pair_match_s={"a b": 1.2, "a c": 1.1, "b c": 2.0, "x y": 9.0})
    acc = scaling_accounting(w1, w2, cores=2, target=0.6)
    assert acc["ratio"] == 0.65 and acc["cpu_bound_s"] == 6.0 and acc["cpu_bound_without_extra_loads_s"] == 5.5
    assert acc["pair_slowdown"] == 1.1 and acc["pairs_compared"] == 3  # only the pairs both runs matched
    assert acc["target_reachable"] is True  # 5.5 / 10 <= 0.6: the bound does not rule the target out
    assert scaling_accounting(w1, dict(w2, cpu_s=14.0))["target_reachable"] is False  # (14 - 1) / 2 / 10 > 0.6
    # a run without CPU times (an older JSON) gives no bound, and no claim
    assert "cpu_bound_s" not in scaling_accounting(dict(w1, cpu_s=None), dict(w2, cpu_s=None))
    feats = dict(features_mean=1.0, images=8)
    run = dict(wall_s=1.0, inner_s=1.0, db=dict(verified_pairs=1, verified_inliers=1), summary=dict(wall_s=1.0))
    row = dict(features=feats, colmap=run, ours=run, rerun=dict(run, summary=dict(skipped=1, wall_s=0.1)),
               mapping_ours=dict(registered=8), warmup=dict(wall_s=0.5), scaling_accounting=acc,
               ratios=dict(time_ours_over_colmap=1.0, inliers_ours_over_colmap=1.0, workers_2_over_1=0.65,
                           workers_2_over_1_matching=0.6))
    text = markdown(dict(meta={}, note="n", sets=dict(default=row)))
    line = next(x for x in text.splitlines() if x.startswith("| default | 1 |"))
    assert "| 0.65 |" in line and "| 6.00 |" in line and "| 0.55 |" in line
