"""`guidedmatch bench pairs` (evaluation/bench_pairs.py), the COLMAP-style IVF-SQ8 peer and the Strecha camera reader."""
import json

import numpy as np
import pytest

from guidedmatch.datasets import data_root

faiss = pytest.importorskip("faiss")


def _strecha_ok():
    r = data_root()
    return r is not None and (r / "pose_pairs" / "strecha" / "Herz-Jesus-P8" / "gt_dense_cameras").is_dir() and \
        (r / "photos" / "unsplash").is_dir()


needs_strecha = pytest.mark.skipif(not _strecha_ok(), reason="Herz-Jesus-P8 cameras / Unsplash photos not found "
                                   "(set GUIDEDMATCH_DATA to the shared data folder)")


def _byte_descriptors(rng, n, d=128):
    """Byte-valued float descriptors with some structure (clusters), like SIFT's 0..255 values."""
    centres = rng.integers(0, 120, (max(4, n // 50), d))
    x = centres[rng.integers(0, len(centres), n)] + rng.integers(0, 40, (n, d))
    return x.astype(np.float32)


def _pair_descriptors(rng, n1, n2, shared):
    """Two sets where ``shared`` image-2 descriptors are noisy copies of image-1 ones (true matches)."""
    d1 = _byte_descriptors(rng, n1)
    d2 = _byte_descriptors(rng, n2)
    src = rng.permutation(n1)[:shared]
    dst = rng.permutation(n2)[:shared]
    d2[dst] = np.clip(d1[src] + rng.integers(-3, 4, (shared, d1.shape[1])), 0, 255)
    return d1, d2


def _reference_nn2(q, db):
    """Slow, obviously-correct exact 2-NN (Euclidean) by full distance matrix."""
    d = np.sqrt(((q[:, None, :].astype(np.float64) - db[None, :, :]) ** 2).sum(-1))
    order = np.argsort(d, axis=1, kind="stable")[:, :2]
    return np.take_along_axis(d, order, 1), order


def _reference_colmap(d1, d2, ratio, max_distance):
    """Mutual ratio-test matches from the exact reference (what IVF gives when every list is probed)."""
    def one_way(a, b):
        D, I = _reference_nn2(a, b)
        ok = (D[:, 0] < ratio * D[:, 1]) & (D[:, 0] <= max_distance)
        return np.where(ok, I[:, 0], -1)
    f, b = one_way(d1, d2), one_way(d2, d1)
    q = np.flatnonzero(f >= 0)
    q = q[b[f[q]] == q]
    return np.stack([q, f[q]], 1)


def test_ivf_with_every_list_probed_is_exact_and_counts_comparisons(rng):
    from guidedmatch.evaluation.peers import build_ivf_index, match_faiss_ivf

    d1, d2 = _pair_descriptors(rng, 700, 900, 400)
    i1, i2 = build_ivf_index(d1), build_ivf_index(d2)
    assert i1.nlist == int(4 * np.sqrt(700)) and i2.nlist == int(4 * np.sqrt(900)) and i2.nprobe == 8
    for idx in (i1, i2):
        idx.index.nprobe = idx.nlist  # probe everything: the search becomes exact (QT_8bit_direct stores bytes as is)
    r = match_faiss_ivf(d1, d2, index1=i1, index2=i2, max_distance=300.0)
    ref = _reference_colmap(d1, d2, 0.8, 300.0)
    assert len(ref) > 300
    np.testing.assert_array_equal(r.pairs, ref)
    # comparisons: coarse quantizer (nlist per query) + every code of the other image, both directions
    assert r.stats.comparisons == 700 * (i2.nlist + 900) + 900 * (i1.nlist + 700)
    assert r.stats.details["build_s"] == 0.0 and r.stats.time_s >= 0


def test_ivf_default_probing_is_a_subset_with_fewer_comparisons(rng):
    from guidedmatch.evaluation.peers import build_ivf_index, match_faiss_ivf

    d1, d2 = _pair_descriptors(rng, 2000, 2000, 1000)
    r = match_faiss_ivf(d1, d2)  # builds both indexes itself: their time is reported
    assert r.stats.details["build_s"] > 0 and r.stats.time_s >= r.stats.details["build_s"]
    assert r.stats.comparisons < 2 * 2000 * 2000 and len(r) > 500
    # cross-check: every returned pair is mutual; no image-2 feature twice
    assert len(np.unique(r.pairs[:, 1])) == len(r)
    one = match_faiss_ivf(d1, d2, index2=build_ivf_index(d2), cross_check=False)
    s_one = {tuple(p) for p in one.pairs}
    assert {tuple(p) for p in r.pairs} <= s_one


def test_small_sets_use_a_flat_index_like_colmap(rng):
    from guidedmatch.evaluation.peers import build_ivf_index, match_faiss, match_faiss_ivf

    d1, d2 = _pair_descriptors(rng, 300, 400, 200)
    assert build_ivf_index(d2).nlist == 0
    r = match_faiss_ivf(d1, d2, cross_check=False, max_distance=None)
    assert r.stats.comparisons == 300 * 400
    ref = match_faiss(d1, d2)
    assert len(ref) > 150
    np.testing.assert_array_equal(r.pairs, ref.pairs)


def test_totals_sum_rows_and_find_the_worst_pair():
    from guidedmatch.evaluation.bench_pairs import totals

    def m(t, comp, matches, gt, verdict="verified"):
        return dict(time_s=t, comparisons=comp, matches=matches, gt_inliers=gt, verdict=verdict, verdict_source="post-hoc")

    rows = [dict(name="s/a-b", bf_comparisons=100, methods={"bf": m(1.0, 100, 10, 8), "so+epi+ia": m(0.2, 10, 9, 8)}),
            dict(name="s/c-d", bf_comparisons=100, methods={"bf": m(1.0, 100, 5, 1), "so+epi+ia": m(3.0, 90, 6, 1, "no-overlap")})]
    t = totals(rows)
    g = t["so+epi+ia"]
    assert g["time_s"] == pytest.approx(3.2) and g["comparisons"] == 100 and g["comparisons_frac"] == pytest.approx(0.5)
    assert g["matches"] == 15 and g["gt_inliers"] == 9 and g["wrong"] == 6
    assert g["slowest_pair"] == "s/c-d" and g["worst_vs_bf"] == pytest.approx(3.0)
    assert g["verdicts"] == {"verified": 1, "no-overlap": 1}
    assert t["bf"]["worst_vs_bf"] == pytest.approx(1.0)


def test_bench_pairs_without_data_is_a_clean_error(tmp_path, capsys):
    from guidedmatch.cli import main

    rc = main(["bench", "pairs", "--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")])
    assert rc == 2
    assert "guidedmatch: error:" in capsys.readouterr().err
    assert not (tmp_path / "o" / "pairs.json").exists()


@pytest.mark.data
@needs_strecha
def test_scene_pairs_agree_with_the_pairs_file():
    from guidedmatch.datasets import strecha_pairs, strecha_scene_pairs

    allp = strecha_scene_pairs()
    assert len(allp) == 28
    ref = {p.name: p for p in strecha_pairs(with_sizes=False)}
    assert set(ref) <= {p.name for p in allp}
    for p in allp:
        if p.name in ref:
            F1, F2 = p.gt.F, ref[p.name].gt.F
            np.testing.assert_allclose(F1 * np.sign((F1 * F2).sum()), F2, atol=1e-7)
            assert p.meta["rotation_deg"] == pytest.approx(ref[p.name].meta["rotation_deg"], abs=1e-6)


@pytest.mark.data
@pytest.mark.slow
@needs_strecha
def test_bench_pairs_quick_writes_consistent_json_md_png(tmp_path):
    from guidedmatch.cli import main

    rc = main(["bench", "pairs", "--quick", "--features", "8192", "--out", str(tmp_path)])
    assert rc == 0
    res = json.loads((tmp_path / "pairs.json").read_text())
    assert res["partial"] is False and res["meta"]["numpy"] and res["quick"] is True
    s = res["sets"]["8192"]
    rows = s["rows"]
    assert sum(r["unrelated"] for r in rows) == 1 and sum(not r["unrelated"] for r in rows) == 2
    for r in rows:
        m = r["methods"]
        n1n2 = r["n1"] * r["n2"]
        assert r["bf_comparisons"] == n1n2
        assert m["bf"]["comparisons"] == n1n2 and m["faiss_flat"]["comparisons"] == n1n2
        assert 0 < m["so+epi+ia"]["comparisons"] <= n1n2 and m["opencv_flann"]["comparisons"] is None
        for k, v in m.items():
            assert 0 <= v["gt_inliers"] <= v["matches"], k
            assert v["verdict"] in ("verified", "no-overlap", "too-few-matches")
        if r["unrelated"]:
            assert all(v["gt_inliers"] == 0 for v in m.values())
        else:
            assert 0 < r["rotation_deg"] < 90
        assert m["faiss_ivf+build"]["time_s"] > m["faiss_ivf"]["time_s"]
    tot = s["totals"]["scene"]
    scene = [r for r in rows if not r["unrelated"]]
    assert tot["bf"]["gt_inliers"] == sum(r["methods"]["bf"]["gt_inliers"] for r in scene)
    assert tot["so+epi+ia"]["time_s"] == pytest.approx(sum(r["methods"]["so+epi+ia"]["time_s"] for r in scene))
    md = (tmp_path / "pairs.md").read_text()
    for part in ("## Feature set `8192`", "### Totals over the 2 Herz-Jesus-P8 pairs", "### Targets on this run",
                 "IVF-SQ8 cached (search)", "/ faiss exact", "load average", "(+ prepare amortized)"):
        assert part in md
    png = tmp_path / "pairs_angle.png"
    assert png.exists() and png.stat().st_size > 10_000
    assert list((tmp_path / "features").glob("*.npz"))  # cached detections


def _readme_tool():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "tools" / "readme_results.py"
    spec = importlib.util.spec_from_file_location("readme_results", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_readme_headline_is_generated_from_the_json_totals():
    from guidedmatch.evaluation.bench_pairs import COLUMNS, totals

    def m(t, gt, verdict, comp=100):
        return dict(time_s=t, comparisons=comp, matches=gt + 2, gt_inliers=gt, verdict=verdict, verdict_source="matcher")

    def row(name, t, angle, unrelated=False):
        v = "no-overlap" if unrelated else "verified"
        return dict(name=name, bf_comparisons=100, rotation_deg=angle, unrelated=unrelated,
                    methods={c: m(t * (k + 1), 0 if unrelated else 40 + k, v)
                             for k, c in enumerate(c for c in COLUMNS if c != "so+epi+ia+prep")})

    scene = [row("s/0000-0001", 1.0, 3.6), row("s/0000-0007", 2.0, 42.4)]
    unrel = [row("unrelated/0000-vs-x", 0.5, None, True)]
    res = dict(meta=dict(git_commit="abc", cpu_model="cpu"), command="guidedmatch bench pairs", verdict_source_ours=["matcher"],
               sets={"8192": dict(images={"a": dict(n=8192)}, rows=scene + unrel,
                                  totals=dict(scene=totals(scene), unrelated=totals(unrel)))})
    block = _readme_tool().pairs_headline(res)
    assert block.startswith("<!-- pairs:start -->") and block.endswith("<!-- pairs:end -->")
    assert "all 2 Herz-Jesus-P8 pairs (4-42° between the cameras) + 1 unrelated pairs" in block
    # so+epi+ia: total 3.0 s, IVF search (5th column) 5x slower; slowest pair 0000-0007 = 2.0 s, BF there 6.0 s
    assert "| **guidedmatch so+epi+ia** | 3.00 | 0.20x | 0000-0007: 2.00 (0.3x) | 80 |" in block
    assert "1 no-overlap, 100.0 %" in block and "the matcher's own" in block


@needs_strecha
def test_bench_pairs_unwritable_out_is_a_clean_error_before_any_work(tmp_path, capsys):
    from guidedmatch.cli import main

    blocker = tmp_path / "file"
    blocker.write_text("x")
    rc = main(["bench", "pairs", "--quick", "--out", str(blocker / "sub")])
    assert rc == 2
    err = capsys.readouterr().err
    assert "guidedmatch: error:" in err and str(blocker) in err
